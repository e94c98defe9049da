"""psmini: differentiable, GPU-optional photometric stereo for close-range imaging of textiles.

The public API. Every stage of the data flow is a functional on batched torch tensors with a thin
``nn.Module`` beside it where state belongs; see DESIGN.md for shapes, axes and units.

``import psmini`` loads the core only (torch, numpy, kornia). Files live in :mod:`psmini.io` (OpenCV, plyfile),
the rig in :mod:`psmini.rig` (pyserial, OpenCV), batch processing and the command line around them.
"""

from __future__ import annotations

__version__ = "0.1.0"

from psmini.threads import prefer_passive_waiting, set_threads

# before torch loads OpenMP: idle threads sleep rather than spin, so concurrent processes do not stall each other
prefer_passive_waiting()

from psmini import (
    fabric,  # the subpackage: ISO 25178-2 parameters, yarn structure, descriptors
    integrate,  # the package, callable as psmini.integrate.integrate
)
from psmini.autofocus import AutofocusController, AutofocusResult, autofocus_sweep, best_of_scores, refine_peak
from psmini.calibration import calibrate_sphere, card_reference, triangulate_leds
from psmini.config import ReconstructionConfig
from psmini.errors import CalibrationError, DataFormatError, InputError, PsminiError, RigError, ShapeError
from psmini.evaluation import evaluate_sample, evaluation_mask, score_reconstruction
from psmini.flatfield import FlatField, FlatFieldResult, flatfield
from psmini.focus import (
    FOCUS_MEASURES,
    FOCUS_OPERATORS,
    FocusMeasure,
    FocusVolume,
    brenner,
    focus_measure,
    focus_volume,
    gaussian_derivative,
    image_contrast,
    normalized_variance,
    tenengrad,
    variance_of_laplacian,
    wavelet_sum,
)
from psmini.geometry import depth_to_points, pixel_grid_mm, point_cloud
from psmini.integrate import METHODS as INTEGRATION_METHODS
from psmini.integrate import (
    BilateralIntegration,
    DCTPoisson,
    FrankotChellappa,
    MaskedLeastSquares,
    bilateral_integration,
    dct_poisson,
    frankot_chellappa,
    integrate_normals,
    masked_least_squares,
)
from psmini.ledcal import LEDFit, LEDFitOptions, LightFit, LightFitOptions, fit_leds, fit_lights
from psmini.lights import (
    DirectionalLights,
    LEDLights,
    LightField,
    LightModel,
    PointLights,
    as_batched_lights,
    check_spans_3d,
    light_model_class,
    lights_from_dict,
    lights_to_dict,
    ring_lights,
)
from psmini.metrics import angular_error_deg, depth_error, mean_angular_error, median_angular_error
from psmini.nearlight import (
    NearLightOptions,
    NearLightResult,
    near_light_energy,
    near_light_vectors,
    solve_near_light,
)
from psmini.nonlambertian import (
    BlinnPhongFit,
    NonLambertianNormals,
    NonLambertianOptions,
    blinn_phong_images,
    fit_blinn_phong,
    nonlambertian_normals,
)
from psmini.normals import LeastSquaresNormals, albedo_normals, normals_to_gradients
from psmini.pipeline import NORMAL_ESTIMATORS, PhotometricStereo, Reconstruction, distant_light_matrix, reconstruct

# psmini.render is the function once the package is imported; reach the module by `from psmini.render import ...`
from psmini.render import Renderer, cast_shadows, normals_from_height, render, render_lambertian
from psmini.robust import (
    RECOMMENDED_ROBUST_METHOD,
    ROBUST_METHODS,
    RobustNormals,
    RobustOptions,
    rank_trim_weights,
    robust_normals,
    threshold_weights,
)
from psmini.sff import DepthFromFocus, SFFConfig, depth_from_focus

__all__ = [
    "__version__",
    # errors
    "PsminiError",
    "InputError",
    "ShapeError",
    "CalibrationError",
    "DataFormatError",
    "RigError",
    # lights
    "ring_lights",
    "check_spans_3d",
    "as_batched_lights",
    "LightModel",
    "LightField",
    "light_model_class",
    "lights_to_dict",
    "lights_from_dict",
    "DirectionalLights",
    "PointLights",
    "LEDLights",
    # flat-fielding
    "flatfield",
    "FlatField",
    "FlatFieldResult",
    # normals
    "albedo_normals",
    "LeastSquaresNormals",
    "normals_to_gradients",
    # robust normals
    "robust_normals",
    "RobustNormals",
    "RobustOptions",
    "nonlambertian_normals",
    "NonLambertianNormals",
    "NonLambertianOptions",
    "fit_blinn_phong",
    "blinn_phong_images",
    "BlinnPhongFit",
    "rank_trim_weights",
    "threshold_weights",
    "ROBUST_METHODS",
    "RECOMMENDED_ROBUST_METHOD",
    # geometry
    "pixel_grid_mm",
    "depth_to_points",
    "point_cloud",
    # metrics and evaluation
    "angular_error_deg",
    "mean_angular_error",
    "median_angular_error",
    "depth_error",
    "evaluate_sample",
    "evaluation_mask",
    "score_reconstruction",
    "set_threads",
    # near light
    "solve_near_light",
    "NearLightOptions",
    "near_light_vectors",
    "near_light_energy",
    "NearLightResult",
    # pipeline
    "ReconstructionConfig",
    "NORMAL_ESTIMATORS",
    "PhotometricStereo",
    "Reconstruction",
    "distant_light_matrix",
    "reconstruct",
    # rendering
    "render_lambertian",
    "render",
    "Renderer",
    "cast_shadows",
    "normals_from_height",
    # light-model and LED calibration from card images
    "fit_lights",
    "LightFit",
    "LightFitOptions",
    "fit_leds",
    "LEDFit",
    "LEDFitOptions",
    # calibration
    "calibrate_sphere",
    "triangulate_leds",
    "card_reference",
    # integration
    "integrate",
    "INTEGRATION_METHODS",
    "integrate_normals",
    "bilateral_integration",
    "BilateralIntegration",
    "frankot_chellappa",
    "FrankotChellappa",
    "dct_poisson",
    "DCTPoisson",
    "masked_least_squares",
    "MaskedLeastSquares",
    # fabric structure (the subpackage)
    "fabric",
    # focus and autofocus
    "focus_measure",
    "FOCUS_MEASURES",
    "FocusMeasure",
    "brenner",
    "image_contrast",
    "wavelet_sum",
    "gaussian_derivative",
    "tenengrad",
    "variance_of_laplacian",
    "normalized_variance",
    "FOCUS_OPERATORS",
    "focus_volume",
    "FocusVolume",
    "depth_from_focus",
    "DepthFromFocus",
    "SFFConfig",
    "AutofocusController",
    "AutofocusResult",
    "autofocus_sweep",
    "best_of_scores",
    "refine_peak",
]
