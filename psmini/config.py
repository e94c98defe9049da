"""One configuration of a reconstruction: built once by every entry point, passed on unchanged, written with results.

:class:`ReconstructionConfig` says everything that decides a reconstruction besides the data: which solver
(distant or near light), which normal estimator with which options, which integrator with which options, the
near-light options, the flat-field threshold, device and dtype. ``psmini reconstruct``, ``evaluate``, ``batch``
and ``demo`` build it from the same flags (:func:`psmini.commands._common.config_from_args`), the Python entry
points (:func:`psmini.reconstruct`, :func:`psmini.evaluate_sample`, :func:`psmini.batch.reconstruct_dataset`,
:class:`psmini.PhotometricStereo`) take it as it is, and every output folder's ``outputs.json`` and every batch
summary records :meth:`ReconstructionConfig.to_dict` of the resolved configuration, so a result says how it was made.

A bad configuration (an unknown solver or estimator, options of another integrator, near light asked of
directional lights) raises :class:`~psmini.errors.InputError` when it is built or resolved, before any work.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from psmini._checks import check_positive
from psmini.errors import InputError
from psmini.integrate import METHODS as INTEGRATION_METHODS
from psmini.integrate.api import method_options
from psmini.lights import LightModel
from psmini.nearlight import NearLightOptions
from psmini.nonlambertian import NonLambertianOptions
from psmini.robust import ROBUST_METHODS, RobustOptions

__all__ = ["SOLVERS", "ESTIMATORS", "ReconstructionConfig"]

#: ``auto`` picks ``near`` for light models with positions (point lights, LEDs) and ``distant`` for directions.
SOLVERS = ("auto", "distant", "near")

#: Normal estimators: ``auto`` (the solver's own: least squares for distant lights, the near solver's shadow- and
#: highlight-rejecting least squares for near ones), ``lstsq``, the robust estimators of :mod:`psmini.robust`
#: (``robust`` names the recommended one) and ``nonlambertian`` (:mod:`psmini.nonlambertian`); all but ``auto``
#: are distant-light estimators.
ESTIMATORS = ("auto", "lstsq", "robust") + ROBUST_METHODS + ("nonlambertian",)

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
# the options type of each estimator that has options
_ESTIMATOR_OPTIONS = {**{name: RobustOptions for name in ("robust",) + ROBUST_METHODS},
                      "nonlambertian": NonLambertianOptions}


@dataclass(frozen=True)
class ReconstructionConfig:
    """Everything that decides a reconstruction; built once, passed on unchanged, written with every result.

    Attributes:
        solver: ``"auto"``, ``"distant"`` or ``"near"`` (:data:`SOLVERS`). ``auto`` lets the light model decide:
            point and LED models (their positions known) → near-light photometric stereo; directions → the
            classical distant-light pipeline.
        estimator: normal estimator, one of :data:`ESTIMATORS` (default ``auto``: least squares for distant
            lights, the near solver's own robust least squares for near ones).
        estimator_options: the estimator's options: a :class:`~psmini.robust.RobustOptions` for the robust
            estimators, a :class:`~psmini.nonlambertian.NonLambertianOptions` for ``nonlambertian`` (or their
            ``to_dict()`` form); ``None``: the estimator's defaults.
        integrator: ``"auto"`` or a name of :data:`psmini.integrate.METHODS`. ``auto``: for distant lights masked
            least squares when the sample has a mask, Frankot–Chellappa over the full rectangle otherwise; for near
            light the near options' integrator (weighted masked least squares: the unsolved crevices of cloth are
            holes in the domain). A name given here replaces the near options' integrator too.
        integrator_options: keyword options of the distant solver's integrator, checked against it (so options of
            another integrator are refused; the near solver weights its own).
        near: the near-light solver's :class:`~psmini.nearlight.NearLightOptions` (alternations, tolerance,
            shadow and highlight rejection, offset search, integration).
        min_reference: card pixels darker than this fraction of the LED's brightest card pixel are not trusted
            (:func:`psmini.flatfield.flatfield`).
        card_smoothing_px: denoise the card before dividing by it (:func:`psmini.flatfield.smooth_card`, a
            Gaussian window of this many pixels; default 5, whose local quadratic fit leaves the card as much noise
            as the local linear fit over 3 pixels that it replaced, without its curvature bias); ``None`` divides by
            the card as captured. Every
            flat-fielded capture inherits the card's noise: on independent 8-bit captures the card as captured costs
            0.3° over the noise floor, and a smoothed one nothing measurable (see the near-light guide).
        device: where to compute (``"cpu"``, ``"cuda"``, ``"cuda:1"``).
        dtype: ``"float32"`` or ``"float64"``.

    Raises:
        InputError: an unknown solver, estimator, integrator or dtype; options the named method does not take;
            an estimator other than ``auto`` with the near solver.

    Example:
        >>> config = ReconstructionConfig(estimator="robust")
        >>> config.to_dict()["estimator"]
        'robust'
        >>> ReconstructionConfig.from_dict(config.to_dict()) == config
        True
    """

    solver: str = "auto"
    estimator: str = "auto"
    estimator_options: RobustOptions | NonLambertianOptions | None = None
    integrator: str = "auto"
    integrator_options: Mapping[str, Any] = field(default_factory=dict)
    near: NearLightOptions = field(default_factory=NearLightOptions)
    min_reference: float = 0.02
    card_smoothing_px: float | None = 5.0
    device: str = "cpu"
    dtype: str = "float32"

    def __post_init__(self) -> None:
        self._check_name("solver", self.solver, SOLVERS)
        self._check_name("estimator", self.estimator, ESTIMATORS)
        self._check_name("integrator", self.integrator, ("auto",) + tuple(sorted(INTEGRATION_METHODS)))
        self._check_name("dtype", self.dtype, tuple(_DTYPES))
        if self.solver == "near" and self.estimator != "auto":
            raise InputError(f"estimator {self.estimator!r} is for distant lights; the near-light solver has its own "
                             "(leave estimator='auto')")
        if not (isinstance(self.min_reference, (int, float)) and 0 <= self.min_reference < 1):
            raise InputError(f"min_reference must be a number in [0, 1), got {self.min_reference!r}")
        if self.card_smoothing_px is not None:
            check_positive(self.card_smoothing_px, "card_smoothing_px")
        try:
            torch.device(self.device)
        except (RuntimeError, TypeError) as error:
            raise InputError(f"device must name a torch device (cpu, cuda, cuda:1), got {self.device!r}") from error
        self._check_integrator_options()
        self._check_estimator_options()
        if isinstance(self.near, Mapping):  # the JSON form (from_dict, --near-option)
            try:
                object.__setattr__(self, "near", NearLightOptions(**self.near))
            except TypeError as error:
                raise InputError(f"near: {error} (the fields of NearLightOptions)") from error
        if not isinstance(self.near, NearLightOptions):
            raise InputError(f"near must be a NearLightOptions, got {type(self.near).__name__}")
        if self.solver == "distant" and self.near != NearLightOptions():
            changed = sorted(k for k, v in self.near.to_dict().items() if v != NearLightOptions().to_dict()[k])
            raise InputError(f"near-light options {changed} were given but the solver is 'distant'")

    def _check_estimator_options(self) -> None:
        options, kind = self.estimator_options, _ESTIMATOR_OPTIONS.get(self.estimator)
        if options is None or (isinstance(options, Mapping) and not options):
            object.__setattr__(self, "estimator_options", None)
            return
        if kind is None:
            raise InputError(f"estimator {self.estimator!r} takes no options, got {options!r}")
        if isinstance(options, Mapping):  # the JSON form (from_dict)
            try:
                options = kind(**options)
            except TypeError as error:
                raise InputError(f"estimator_options: {error} (the fields of {kind.__name__})") from error
            object.__setattr__(self, "estimator_options", options)
        if not isinstance(options, kind):
            raise InputError(f"estimator {self.estimator!r} takes a {kind.__name__}, got {type(options).__name__}")

    @staticmethod
    def _check_name(what: str, value: Any, allowed: tuple[str, ...]) -> None:
        if value not in allowed:
            raise InputError(f"{what} must be one of {', '.join(allowed)}, got {value!r}")

    def _check_integrator_options(self) -> None:
        options = self.integrator_options
        if not isinstance(options, Mapping):
            raise InputError(f"integrator_options must be a mapping of keyword options, got {type(options).__name__}")
        # with auto the options must suit every integrator the distant solver may pick
        names = ("masked", "fc") if self.integrator == "auto" else (self.integrator,)
        for name in names:
            accepted = method_options(name)
            unknown = sorted(set(options) - accepted)
            if unknown:
                raise InputError(f"integrator_options: {INTEGRATION_METHODS[name].__name__} takes {sorted(accepted)}, "
                                 f"got unknown {unknown}")

    @property
    def torch_dtype(self) -> torch.dtype:
        """The torch dtype of :attr:`dtype`."""
        return _DTYPES[self.dtype]

    def solver_for(self, lights: LightModel) -> str:
        """The solver that runs for ``lights``: ``"near"`` or ``"distant"``.

        Raises:
            InputError: ``"near"`` asked of a light model without positions (directional lights).

        Example:
            >>> from psmini.lights import DirectionalLights, ring_lights
            >>> ReconstructionConfig().solver_for(DirectionalLights(ring_lights(8, 55.0)))
            'distant'
        """
        if not isinstance(lights, LightModel):
            raise InputError(f"lights must be a psmini LightModel, got {type(lights).__name__}")
        if self.solver == "auto":
            return "near" if lights.is_near else "distant"
        if self.solver == "near" and not lights.is_near:
            raise InputError(f"the near-light solver needs light positions (a point or LED model); the lights are "
                             f"{type(lights).__name__} (give solver='distant', or a lights file with positions)")
        return self.solver

    def integrator_for(self, solver: str, has_mask: bool) -> str:
        """The integrator that runs: :attr:`integrator`, or for ``auto`` the near options' with near light, masked
        least squares with a mask and Frankot–Chellappa otherwise."""
        if self.integrator != "auto":
            return self.integrator
        if solver == "near":
            return self.near.integrator
        return "masked" if has_mask else "fc"

    def near_options(self, has_mask: bool) -> NearLightOptions:
        """The :class:`~psmini.nearlight.NearLightOptions` that run, with the integrator of :meth:`integrator_for`."""
        return self.near.replace(integrator=self.integrator_for("near", has_mask))

    def resolved(self, lights: LightModel, has_mask: bool) -> ReconstructionConfig:
        """This configuration with ``auto`` replaced by what runs for ``lights`` (what results record).

        Example:
            >>> from psmini.lights import LEDLights, ring_lights
            >>> ring = ring_lights(8, 58.0)
            >>> resolved = ReconstructionConfig().resolved(LEDLights(ring * 18.6, -ring), has_mask=False)
            >>> resolved.solver, resolved.integrator
            ('near', 'masked')
        """
        solver = self.solver_for(lights)
        estimator = self.estimator if self.estimator != "auto" else ("lstsq" if solver == "distant" else "auto")
        near = self.near_options(has_mask) if solver == "near" else self.near
        return dataclasses.replace(self, solver=solver, estimator=estimator, near=near,
                                   integrator=self.integrator_for(solver, has_mask))

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of every field (what ``outputs.json`` and batch summaries record)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values.update(estimator_options=None if self.estimator_options is None else self.estimator_options.to_dict(),
                      integrator_options=dict(self.integrator_options), near=self.near.to_dict())
        return values

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ReconstructionConfig:
        """The configuration of :meth:`to_dict`'s dict (unknown keys raise :class:`InputError`)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise InputError(f"a reconstruction configuration has the keys {sorted(names)}, got unknown {unknown}")
        return cls(**data)
