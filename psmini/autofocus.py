"""Autofocus: the seed's stop rule over a bounded sweep, peak refinement, a step-by-step controller and a whole sweep.

The seed moves the camera (or the cloth) through a range of heights, scores each frame with the modified Brenner
measure, and stops once the maximum is followed by five smaller values; psmini keeps that rule and adds what
practice needs (FIELD_NOTES, "Focus measures"):

- "smaller" means smaller than the maximum by a relative ``margin``, so noise around the peak does not count;
- a sweep stops only when the maximum stands out of the scores seen by a relative ``prominence``, so a flat,
  noisy start far from focus (whose first frame may be its largest) does not end the sweep;
- the peak is refined by a 3-point parabola (or a Gaussian: a parabola through the logarithms), and the fit is
  rejected when flat, not concave, or at the edge of the range, falling back to the best sampled position;
- the controller proposes only the positions of the sweep, all inside the allowed range, and the refined
  position lies between the peak's neighbours, so nothing ever leaves the range.

References: J. F. Brenner et al. (1976); the seed paper's stop rule; S. Pertuz et al., Pattern Recognition 46
(2013) on focus curves; Gaussian peak interpolation as in sub-pixel peak location (e.g. Fisher & Naidu 1996).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from psmini._checks import as_index
from psmini.errors import InputError, ShapeError
from psmini.focus import FocusMeasure, Roi

__all__ = ["AutofocusController", "AutofocusResult", "autofocus_sweep", "best_of_scores", "refine_peak",
           "sweep_positions"]

logger = logging.getLogger(__name__)

_REFINE = ("parabola", "gaussian", "none")


@dataclass
class AutofocusResult:
    """The outcome of a focus sweep.

    Attributes:
        best_position: the focus position, mm: the refined peak, or the best sampled position when no fit passed.
        best_index: index (in visiting order) of the largest score.
        best_score: the largest score.
        positions: the positions visited, mm, in order.
        scores: their scores.
        refined: whether ``best_position`` comes from an accepted peak fit.
        stopped_by_rule: True when the stop rule ended the sweep, False when the range ran out first.
        at_edge: True when the largest score is at the first or last position of the range (the true focus may
            lie outside it).
        stop_index: index of the last frame the sweep took (where the stop rule fired, or the range's end).
    """

    best_position: float
    best_index: int
    best_score: float
    positions: list[float] = field(default_factory=list)
    scores: list[float] = field(default_factory=list)
    refined: bool = False
    stopped_by_rule: bool = False
    at_edge: bool = False
    stop_index: int = -1

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field."""
        return dict(self.__dict__)


def sweep_positions(start: float, stop: float, step: float) -> list[float]:
    """The positions ``start, start ± step, ...`` up to ``stop`` inclusive, never beyond it.

    Args:
        start: first position, mm.
        stop: last allowed position, mm (above or below ``start``).
        step: step size, mm (> 0; its direction is taken from ``stop - start``).

    Returns:
        the positions, mm, as floats.

    Raises:
        InputError: non-finite values or a non-positive step.

    Example:
        >>> sweep_positions(1.0, 0.0, 0.25)
        [1.0, 0.75, 0.5, 0.25, 0.0]
    """
    for name, value in (("start", start), ("stop", stop), ("step", step)):
        if not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise InputError(f"sweep {name} must be a finite number, got {value!r}")
    if step <= 0:
        raise InputError(f"sweep step must be > 0 mm (its direction comes from start → stop), got {step!r}")
    count = int(math.floor(abs(stop - start) / step + 1e-9)) + 1
    direction = 1.0 if stop >= start else -1.0
    return [float(start + direction * k * step) for k in range(count)]


def refine_peak(positions: Sequence[float], scores: Sequence[float], index: int, method: str = "parabola",
                flat_tolerance: float = 1e-6) -> tuple[float, bool]:
    r"""Sub-step focus position from the peak sample and its two neighbours.

    Parabola: the vertex of :math:`s(z) = a z^2 + b z + c` through the three points (any spacing); Gaussian: the
    same on :math:`\ln s` (scores must be positive). The fit is rejected — the sampled position is returned with
    ``False`` — when the peak is the first or last sample, when the curvature is not negative (flat or convex),
    when the three scores differ by less than ``flat_tolerance`` relative to the peak, or when the vertex falls
    outside the neighbours' interval.

    Args:
        positions: sampled positions, mm, strictly monotonic.
        scores: their scores (same length).
        index: index of the peak sample.
        method: ``"parabola"``, ``"gaussian"`` or ``"none"``.
        flat_tolerance: relative spread below which the three scores count as flat.

    Returns:
        ``(position, accepted)``: the refined position, mm, and whether the fit was accepted.

    Raises:
        InputError: an unknown method, mismatched lengths, or an index that is not an integer or lies outside the
            samples.

    Example:
        >>> refine_peak([0.0, 1.0, 2.0], [3.0, 4.0, 1.0], 1)  # s = -2z² + 3z + 3 → vertex 0.75
        (0.75, True)
    """
    if method not in _REFINE:
        raise InputError(f"refine must be one of {', '.join(_REFINE)}, got {method!r}")
    if len(positions) != len(scores):
        raise InputError(f"positions ({len(positions)}) and scores ({len(scores)}) must have the same length")
    peak = as_index(index)  # 1.5 failed as a bare TypeError of list indexing; numpy and 0-d integer tensors are indices
    if peak is None:
        raise InputError(f"peak index must be an integer (the peak sample's index), got {index!r}")
    index = peak
    if not 0 <= index < len(scores):
        raise InputError(f"peak index {index} is outside the {len(scores)} samples")
    sampled = float(positions[index])
    if method == "none" or index == 0 or index == len(scores) - 1:
        return sampled, False
    z0, z1, z2 = (float(positions[i]) for i in (index - 1, index, index + 1))
    s0, s1, s2 = (float(scores[i]) for i in (index - 1, index, index + 1))
    if max(s0, s1, s2) - min(s0, s1, s2) <= flat_tolerance * max(abs(s1), 1e-300):
        return sampled, False
    if method == "gaussian":
        if min(s0, s1, s2) <= 0:
            return sampled, False
        s0, s1, s2 = math.log(s0), math.log(s1), math.log(s2)
    # Divided differences: curvature a and the vertex of the interpolating parabola.
    d01, d12 = (s1 - s0) / (z1 - z0), (s2 - s1) / (z2 - z1)
    curvature = (d12 - d01) / (z2 - z0)
    if not curvature < 0:
        return sampled, False
    vertex = 0.5 * (z0 + z1) - d01 / (2.0 * curvature)
    if not min(z0, z2) <= vertex <= max(z0, z2):
        return sampled, False
    return vertex, True


class AutofocusController:
    """A focus sweep driven one frame at a time: it says where to move next, or that it is done.

    Give it the positions of the sweep (or ``start``/``stop``/``step``), then repeatedly move to
    :attr:`position`, grab a frame and pass the frame (or its score) to :meth:`step`, until :attr:`done`.
    The stop rule: the sweep ends once at least ``patience`` scores after the maximum are *smaller* — below
    ``(1 - margin) · max`` — and the maximum stands out, ``max ≥ (1 + prominence) · min`` of the scores so far;
    otherwise it ends at the last position of the range.

    Args:
        positions: the sweep's positions, mm, strictly monotonic (a sequence or a 1-D tensor); or give ``start``,
            ``stop`` and ``step``.
        start: first position, mm.
        stop: last position, mm.
        step: step, mm (> 0).
        bounds: ``(low, high)`` allowed range, mm; every position must lie inside (default: the positions' span).
        measure: focus measure name (see :data:`psmini.focus.FOCUS_MEASURES`) or a callable
            ``frames (1, H, W) -> (1,)``, used when :meth:`step` gets a frame.
        roi: region ``(x, y, w, h)`` for a named measure.
        patience: how many smaller scores after the maximum end the sweep (the seed: 5).
        margin: relative drop below the maximum that makes a score "smaller" (≥ 0).
        prominence: relative height of the maximum over the smallest score needed to stop (≥ 0).
        refine: ``"parabola"``, ``"gaussian"`` or ``"none"``.

    Raises:
        InputError: bad positions, bounds, or parameters.

    Example:
        >>> ctl = AutofocusController(start=-1.0, stop=1.0, step=0.25, patience=2)
        >>> while not ctl.done:
        ...     z = ctl.position  # move the stage to z, grab a frame, score it:
        ...     _ = ctl.step(1.0 / (1.0 + (z - 0.1) ** 2))
        >>> round(ctl.result().best_position, 2), ctl.result().stopped_by_rule
        (0.1, True)
    """

    def __init__(self, positions: Sequence[float] | Tensor | None = None, *, start: float | None = None,
                 stop: float | None = None, step: float | None = None,
                 bounds: tuple[float, float] | None = None, measure: str | Callable[[Tensor], Tensor] = "brenner",
                 roi: Roi | str | None = None, patience: int = 5, margin: float = 0.02, prominence: float = 0.05,
                 refine: str = "parabola") -> None:
        self.positions = _plan(positions, start, stop, step)
        self.bounds = _check_bounds(bounds, self.positions)
        if not (isinstance(patience, int) and patience >= 1):
            raise InputError(f"patience must be an integer ≥ 1, got {patience!r}")
        for name, value in (("margin", margin), ("prominence", prominence)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a finite number ≥ 0, got {value!r}")
        if refine not in _REFINE:
            raise InputError(f"refine must be one of {', '.join(_REFINE)}, got {refine!r}")
        self.measure = FocusMeasure(measure, roi) if isinstance(measure, str) else measure
        self.patience, self.margin, self.prominence, self.refine = patience, float(margin), float(prominence), refine
        self.scores: list[float] = []
        self._stopped_by_rule = False

    @property
    def done(self) -> bool:
        """Whether the sweep is over (stop rule met or range exhausted)."""
        return self._stopped_by_rule or len(self.scores) == len(self.positions)

    @property
    def position(self) -> float | None:
        """Where the next frame must be taken, mm; ``None`` once :attr:`done`."""
        return None if self.done else self.positions[len(self.scores)]

    def step(self, observation: Tensor | float) -> float | None:
        """Record the frame (or score) taken at :attr:`position`; return the next position, or ``None`` when done.

        Args:
            observation: a frame :math:`(H, W)`, :math:`(1, H, W)` or :math:`(1, 1, H, W)` scored with the
                controller's measure, or a score (a number, or a one-element tensor such as a measure's
                :math:`(1,)` result).

        Returns:
            the next position, mm, or ``None`` when the sweep is over.

        Raises:
            InputError: when called after the sweep is done, with a non-finite score, or with something that is
                neither a frame tensor nor a number (a numpy frame: convert it with ``torch.from_numpy``).
            ShapeError: a tensor that is not one gray frame (a colour frame :math:`(H, W, 3)`, a batch
                :math:`(N, H, W)`), or a measure that does not return one score.
        """
        if self.done:
            raise InputError("the focus sweep is done; read result() instead of stepping again")
        if isinstance(observation, Tensor) and observation.ndim < 2 and observation.numel() == 1:
            score = float(observation)  # a score already, e.g. brenner(frame)'s (1,)
        elif isinstance(observation, Tensor):
            if observation.ndim < 2 or any(size != 1 for size in observation.shape[:-2]):
                raise ShapeError(f"a frame must be one gray image (H, W), (1, H, W) or (1, 1, H, W), got shape "
                                 f"{tuple(observation.shape)}; convert a colour frame to gray, step one frame at a "
                                 "time")
            scores = self.measure(observation.reshape(1, *observation.shape[-2:]))
            if not isinstance(scores, Tensor) or scores.numel() != 1:
                got = tuple(scores.shape) if isinstance(scores, Tensor) else type(scores).__name__
                raise ShapeError(f"the focus measure must return one score (1,) for one frame, got {got}")
            score = float(scores)
        else:
            try:
                score = float(observation)
            except (TypeError, ValueError):
                shape = getattr(observation, "shape", None)
                raise InputError(f"observation must be a frame tensor or a score (a number), got "
                                 f"{type(observation).__name__}{'' if shape is None else f' of shape {shape}'}"
                                 "; convert a numpy frame with torch.from_numpy") from None
        if not math.isfinite(score):
            raise InputError(f"focus score at {self.positions[len(self.scores)]} mm is not finite: {score}")
        self.scores.append(score)
        self._stopped_by_rule = self._rule_met()
        if self._stopped_by_rule:
            logger.info("autofocus: stop rule met after %d of %d positions", len(self.scores), len(self.positions))
        return self.position

    def _rule_met(self) -> bool:
        best_index = max(range(len(self.scores)), key=self.scores.__getitem__)
        best = self.scores[best_index]
        threshold = best - self.margin * abs(best)
        smaller = sum(1 for s in self.scores[best_index + 1 :] if s < threshold)
        stands_out = best - min(self.scores) >= self.prominence * abs(best) and best > min(self.scores)
        return smaller >= self.patience and stands_out

    def result(self) -> AutofocusResult:
        """The best position so far (final once :attr:`done`).

        Raises:
            InputError: when no score has been recorded yet.
        """
        if not self.scores:
            raise InputError("no frame has been scored yet: step() at least once before result()")
        visited = self.positions[: len(self.scores)]
        index = max(range(len(self.scores)), key=self.scores.__getitem__)
        position, refined = refine_peak(visited, self.scores, index, self.refine)
        low, high = self.bounds
        return AutofocusResult(
            best_position=min(max(position, low), high),
            best_index=index,
            best_score=self.scores[index],
            positions=list(visited),
            scores=list(self.scores),
            refined=refined,
            stopped_by_rule=self._stopped_by_rule,
            at_edge=index == 0 or index == len(self.positions) - 1,
            stop_index=len(self.scores) - 1,
        )


def _plan(positions: Sequence[float] | Tensor | None, start: float | None, stop: float | None,
          step: float | None) -> list[float]:
    """The sweep's positions from an explicit list or from start/stop/step; strictly monotonic."""
    if positions is None:
        if start is None or stop is None or step is None:
            raise InputError("give the sweep's positions, or all of start, stop and step")
        return sweep_positions(start, stop, step)
    if start is not None or stop is not None or step is not None:
        raise InputError("give either positions or start/stop/step, not both")
    if isinstance(positions, Tensor):
        positions = positions.detach().cpu().reshape(-1).tolist()
    values = [float(p) for p in positions]
    if not values or not all(math.isfinite(p) for p in values):
        raise InputError(f"positions must be a non-empty list of finite numbers, got {list(positions)!r}")
    steps = [b - a for a, b in itertools.pairwise(values)]
    if not (all(d > 0 for d in steps) or all(d < 0 for d in steps)):
        raise InputError("positions must be strictly increasing or strictly decreasing (one sweep direction)")
    return values


def _check_bounds(bounds: tuple[float, float] | None, positions: list[float]) -> tuple[float, float]:
    if bounds is None:
        return min(positions), max(positions)
    try:
        low, high = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise InputError(f"bounds must be (low, high) in mm, got {bounds!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise InputError(f"bounds must be finite with low ≤ high, got {bounds!r}")
    outside = [p for p in positions if not low <= p <= high]
    if outside:
        raise InputError(f"sweep positions {outside[:3]} lie outside the allowed range [{low}, {high}] mm")
    return low, high


def autofocus_sweep(move_to: Callable[[float], object], grab: Callable[[], Tensor],
                    positions: Sequence[float] | Tensor | None = None, *, start: float | None = None,
                    stop: float | None = None, step: float | None = None,
                    bounds: tuple[float, float] | None = None,
                    measure: str | Callable[[Tensor], Tensor] = "brenner", roi: Roi | str | None = None,
                    patience: int = 5, margin: float = 0.02, prominence: float = 0.05, refine: str = "parabola",
                    move_to_best: bool = True) -> AutofocusResult:
    """Run a whole focus sweep on a robot: move, grab, score, until the stop rule; then go to the best position.

    Args:
        move_to: ``move_to(z)`` moves the stage to ``z`` mm (and waits until it is there).
        grab: ``grab()`` returns a frame :math:`(H, W)` (uint8, uint16 or float tensor) taken at the current z.
        positions, start, stop, step, bounds, measure, roi, patience, margin, prominence, refine: as for
            :class:`AutofocusController`.
        move_to_best: move to the result's ``best_position`` at the end (always inside the range).

    Returns:
        the :class:`AutofocusResult`.

    Raises:
        InputError: bad sweep parameters or frames (see :class:`AutofocusController`, :mod:`psmini.focus`), or a
            ``move_to`` or ``grab`` that is not callable.

    Example:
        >>> stage = {"z": 0.0}
        >>> def grab():
        ...     sharpness = 1.0 / (1.0 + (stage["z"] - 0.3) ** 2)
        ...     return sharpness * torch.tensor([0.0, 0.0, 1.0, 1.0]).repeat(4, 2)  # stripes, contrast ∝ sharpness
        >>> result = autofocus_sweep(lambda z: stage.update(z=z), grab, start=-1.0, stop=1.0, step=0.2)
        >>> round(result.best_position, 1), round(stage["z"], 1)
        (0.3, 0.3)
    """
    # the positions in move_to's place, or a frame for grab, failed as a bare TypeError (not callable)
    for name, function in (("move_to", move_to), ("grab", grab)):
        if not callable(function):
            raise InputError(f"{name} must be callable ({'move_to(z)' if name == 'move_to' else 'grab()'}), got "
                             f"{type(function).__name__}")
    controller = AutofocusController(positions, start=start, stop=stop, step=step, bounds=bounds, measure=measure,
                                     roi=roi, patience=patience, margin=margin, prominence=prominence, refine=refine)
    position = controller.position
    while position is not None:  # None once the sweep is done
        move_to(position)
        position = controller.step(grab())
    result = controller.result()
    if move_to_best:
        move_to(result.best_position)
    return result


def best_of_scores(scores: Tensor | Sequence[float], positions: Sequence[float] | None = None, *,
                   patience: int = 5, margin: float = 0.02, prominence: float = 0.05,
                   refine: str = "parabola") -> AutofocusResult:
    """The best frame of a recorded sweep (all scores known): the global maximum, refined.

    Args:
        scores: :math:`(N,)` focus scores in sweep order.
        positions: their positions, mm, strictly monotonic (default: the indices 0..N-1).
        patience, margin, prominence: the stop rule, as for :class:`AutofocusController`.
        refine: ``"parabola"``, ``"gaussian"`` or ``"none"``.

    Returns:
        an :class:`AutofocusResult` over all N frames; ``stopped_by_rule`` and ``stop_index`` tell whether and
        where the stop rule would have ended a live sweep.

    Raises:
        InputError: empty or non-finite scores, scores that are not numbers, or positions of another length or
            not monotonic.
        ShapeError: scores of several sweeps (more than one dimension longer than 1, e.g. :math:`(2, N)`).

    Example:
        >>> best_of_scores([1.0, 3.0, 2.0], [0.0, 0.5, 1.0]).best_index
        1
    """
    try:
        tensor = torch.as_tensor(scores, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"scores must be a sequence or a 1-D tensor of numbers, got {type(scores).__name__}") from None
    if sum(size > 1 for size in tensor.shape) > 1:  # (N,), (N, 1) of stacked (1,) scores: one sweep
        raise ShapeError(f"scores must be one sweep's (N,) scores, got shape {tuple(tensor.shape)}; find the best "
                         "of each sweep apart")
    values = tensor.reshape(-1).tolist()
    if positions is None:
        positions = [float(i) for i in range(len(values))]
    if len(positions) != len(values):
        raise InputError(f"positions ({len(positions)}) and scores ({len(values)}) must have the same length")
    live = AutofocusController(positions, patience=patience, margin=margin, prominence=prominence, refine=refine)
    for value in values:
        if live.step(value) is None:
            break
    index = max(range(len(values)), key=values.__getitem__)
    position, refined = refine_peak(live.positions, values, index, refine)
    return AutofocusResult(
        best_position=position,
        best_index=index,
        best_score=values[index],
        positions=list(live.positions),
        scores=values,
        refined=refined,
        stopped_by_rule=live.result().stopped_by_rule,
        at_edge=index == 0 or index == len(values) - 1,
        stop_index=len(live.scores) - 1,
    )
