"""psmini.evaluation: the one scoring rule, against closed-form errors, and its guards."""

import dataclasses
import math

import pytest
import torch

from psmini import InputError, ShapeError
from psmini.evaluation import evaluate_sample, evaluation_mask, score_reconstruction
from psmini.io import Sample
from psmini.lights import DirectionalLights, ring_lights
from psmini.nearlight import NearLightResult
from psmini.result import Reconstruction

SIZE = 8


def _tilted(angle_deg: float) -> torch.Tensor:
    """Unit normals tilted by ``angle_deg`` about the y axis, (3, SIZE, SIZE)."""
    a = math.radians(angle_deg)
    return torch.tensor([math.sin(a), 0.0, math.cos(a)]).view(3, 1, 1).repeat(1, SIZE, SIZE)


def _sample(**changes) -> Sample:
    lights = ring_lights(8, 45.0)
    flat = _tilted(0.0)
    images = (lights @ flat.reshape(3, -1)).reshape(8, SIZE, SIZE) * 0.5
    return dataclasses.replace(Sample(name="plane", images=images, lights=DirectionalLights(lights), normals_gt=flat),
                               **changes)


def _result(normals: torch.Tensor, depth: torch.Tensor | None = None, solved: torch.Tensor | None = None,
            **near) -> Reconstruction:
    zeros = torch.zeros(1, 1, SIZE, SIZE)
    mask = torch.ones_like(zeros, dtype=torch.bool) if solved is None else solved
    parts = (zeros + 0.5, normals[None], zeros, zeros, zeros if depth is None else depth, mask)
    return NearLightResult(*parts, **near) if near else Reconstruction(*parts)


def test_mask_combines_finite_truth_and_both_masks():
    normals = _tilted(0.0)
    normals[:, 0, 0] = float("nan")  # 1 pixel without truth
    gt_mask = torch.ones(1, SIZE, SIZE, dtype=torch.bool)
    gt_mask[:, 1, :] = False  # a gap between yarns: 8 pixels
    mask = torch.ones(1, SIZE, SIZE, dtype=torch.bool)
    mask[:, :, 7] = False  # outside the object: 8 pixels, one of them also in the gap
    selected = evaluation_mask(_sample(normals_gt=normals, gt_mask=gt_mask, mask=mask))
    assert selected.shape == (1, 1, SIZE, SIZE) and selected.dtype == torch.bool
    assert int(selected.sum()) == 64 - 1 - 8 - 8 + 1
    assert not bool(selected[0, 0, 0, 0]) and not bool(selected[0, 0, 1, 3]) and not bool(selected[0, 0, 5, 7])


def test_scores_a_known_tilt_unsolved_pixels_and_depth():
    normals = _tilted(10.0)
    solved = torch.ones(1, 1, SIZE, SIZE, dtype=torch.bool)
    solved[..., :2, :] = False  # 16 pixels left out by the solver still count, with their normal
    depth_gt = torch.linspace(0, 1, SIZE * SIZE).view(1, SIZE, SIZE)
    wobble = torch.tensor([0.01, -0.01]).repeat(SIZE * SIZE // 2).view(1, 1, SIZE, SIZE)  # zero mean, 10 µm
    result = _result(normals, depth=depth_gt[None] + 2.0 + wobble, solved=solved)
    scores = score_reconstruction(result, _sample(depth_gt=depth_gt))
    assert scores["pixels"] == 64 and scores["unsolved_pixels"] == 16 and scores["unsolved_share"] == 0.25
    assert scores["mean_angular_error_deg"] == pytest.approx(10.0, abs=1e-4)
    assert scores["median_angular_error_deg"] == pytest.approx(10.0, abs=1e-4)
    assert scores["depth_rmse_mm"] == pytest.approx(0.01, rel=1e-4)  # the 2 mm offset is removed
    assert scores["depth_mae_mm"] == pytest.approx(0.01, rel=1e-4)
    assert "normal_std_median_deg" not in scores  # only near light predicts its errors


def test_predicted_error_statistics():
    """10° of error everywhere, predicted as 20° on the top half and 5° on the bottom: half within their
    prediction, mean (error / predicted)² = (0.5² + 2²) / 2."""
    normal_std = torch.full((1, 1, SIZE, SIZE), 5.0)
    normal_std[..., : SIZE // 2, :] = 20.0
    solved = torch.ones(1, 1, SIZE, SIZE, dtype=torch.bool)
    solved[..., 0, 0] = False  # an unsolved pixel's prediction is not scored
    normal_std[..., 0, 0] = 1e6
    scores = score_reconstruction(_result(_tilted(10.0), solved=solved, normal_std=normal_std), _sample())
    assert scores["normal_std_median_deg"] == pytest.approx(5.0)  # 31 of 63 at 20°, 32 at 5°
    assert scores["within_normal_std_share"] == pytest.approx(31 / 63)
    assert scores["error_to_normal_std_ratio"] == pytest.approx((31 * 0.25 + 32 * 4.0) / 63, rel=1e-4)


def test_evaluate_sample_reconstructs_and_names_the_configuration():
    scores = evaluate_sample(_sample())
    assert scores["mean_angular_error_deg"] < 1e-3  # the images are exactly Lambertian under the lights
    assert scores["config"]["solver"] == "distant"  # directional lights resolve to the distant pipeline


class TestErrors:
    def test_no_ground_truth(self):
        sample = _sample(normals_gt=None)
        with pytest.raises(InputError, match="'plane' has no ground-truth normals"):
            evaluation_mask(sample)
        with pytest.raises(InputError, match="no ground-truth normals"):
            score_reconstruction(_result(_tilted(0.0)), sample)
        with pytest.raises(InputError, match="no ground-truth normals"):
            evaluate_sample(sample)

    def test_no_valid_pixel(self):
        with pytest.raises(InputError, match="no pixel with valid ground truth"):
            score_reconstruction(_result(_tilted(0.0)), _sample(normals_gt=torch.full((3, SIZE, SIZE), math.nan)))

    def test_shapes(self):
        with pytest.raises(ShapeError, match="normals_gt"):
            evaluation_mask(_sample(normals_gt=torch.zeros(SIZE, SIZE)))
        with pytest.raises(ShapeError, match="gt_mask"):
            evaluation_mask(_sample(gt_mask=torch.ones(1, 4, 4, dtype=torch.bool)))
        with pytest.raises(ShapeError, match=r"one sample.*\(1, 3, 4, 4\); got \(1, 3, 8, 8\)"):
            score_reconstruction(_result(_tilted(0.0)), _sample(normals_gt=torch.zeros(3, 4, 4)))

    def test_a_batch_is_scored_sample_by_sample(self):
        one = _result(_tilted(0.0))
        two = Reconstruction(*(torch.cat([t, t]) for t in (one.albedo, one.normals, one.p, one.q, one.depth,
                                                             one.mask)))
        with pytest.raises(ShapeError, match="score each sample"):
            score_reconstruction(two, _sample())

    def test_not_a_reconstruction(self):
        with pytest.raises(InputError, match="needs a psmini Reconstruction, got dict"):
            score_reconstruction({"normals": _tilted(0.0)}, _sample())
