"""Guards shared by every stage: shapes, finiteness, dtypes. Internal."""

from __future__ import annotations

import operator
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from psmini.errors import InputError, ShapeError


def all_true(mask: Tensor) -> bool:
    """``bool(mask.all())``; for a bool tensor through a uint8 minimum, since all() of a bool 4 × 8 × 400 × 400
    batch measured 8.2 ms on the CPU and the minimum 0.3 ms (the same answer: a bool is stored as 0 or 1)."""
    if mask.dtype == torch.bool and mask.numel():
        return bool(mask.view(torch.uint8).amin())
    return bool(mask.all())


def any_true(mask: Tensor) -> bool:
    """``bool(mask.any())``; for a bool tensor through a uint8 maximum (see :func:`all_true`)."""
    if mask.dtype == torch.bool and mask.numel():
        return bool(mask.view(torch.uint8).amax())
    return bool(mask.any())


def check_tensor(x: object, name: str) -> Tensor:
    """Raise :class:`InputError` unless ``x`` is a floating-point tensor."""
    if not isinstance(x, Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise InputError(
            f"{name} must be a floating-point tensor (float32 or float64), got {x.dtype}; "
            "convert integer images with psmini.io (which scales uint8/uint16 to [0, 1])"
        )
    return x


def check_shape(x: Tensor, dims: Sequence[str], name: str) -> dict[str, int]:
    """Check the number of dimensions and the fixed sizes of ``x``; return the named sizes.

    ``dims`` holds one entry per dimension: a letter names a free size (``"B"``), a digit string a fixed one
    (``"3"``). The same letter used twice must match.
    """
    check_tensor(x, name)
    expected = "(" + ", ".join(dims) + ")"
    if x.ndim != len(dims):
        raise ShapeError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    sizes: dict[str, int] = {}
    for dim, size in zip(dims, x.shape, strict=True):
        if dim.isdigit():
            if size != int(dim):
                raise ShapeError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
        elif sizes.setdefault(dim, size) != size:
            raise ShapeError(f"{name} must have shape {expected} with equal {dim}, got {tuple(x.shape)}")
    return sizes


def check_same_size(a: int, b: int, what: str, name_a: str, name_b: str) -> None:
    """Raise :class:`ShapeError` unless two sizes agree."""
    if a != b:
        raise ShapeError(f"{what} of {name_a} ({a}) and {name_b} ({b}) must match")


def check_finite(x: Tensor, name: str) -> Tensor:
    """Raise :class:`InputError` when ``x`` holds NaN or infinite values.

    This one check syncs with the device; it runs once per public call, never inside a loop. A single sum
    carries any NaN or infinity through, so the element-wise test runs only when the sum is not finite (which an
    overflow of large finite values can also cause).
    """
    if x.numel() and not bool(torch.isfinite(x.detach().sum())) and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise InputError(f"{name} must be finite, got {bad} NaN or infinite value(s) of {x.numel()}")
    return x


def check_mask(mask: Tensor | None, batch: int, height: int, width: int, name: str = "mask") -> Tensor | None:
    """Check an optional ``(B, 1, H, W)`` mask (bool or float); broadcast a batch of one."""
    if mask is None:
        return None
    if not isinstance(mask, Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(mask).__name__}")
    if (mask.ndim != 4 or mask.shape[1] != 1 or tuple(mask.shape[2:]) != (height, width)
            or mask.shape[0] not in (1, batch)):
        raise ShapeError(f"{name} must have shape ({batch}, 1, {height}, {width}), got {tuple(mask.shape)}")
    return mask.expand(batch, 1, height, width)


def check_positive(value: object, name: str) -> float:
    """Raise :class:`InputError` unless ``value`` is a finite positive number (anything else may come: an
    optional argument's None, a string from a file); return it as a float."""
    if not (isinstance(value, (int, float)) and value > 0 and value == value and value != float("inf")):
        raise InputError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def records_gradient(*tensors: Tensor | None) -> bool:
    """Whether autograd records operations on any of ``tensors`` (``None`` skipped): out= writes would then break
    the graph."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def check_out(out, shapes: tuple[tuple[int, ...], ...], names: tuple[str, ...],
              inputs: tuple[Tensor | None, ...]) -> None:
    """Refuse ``out`` tensors that cannot receive a result: not a tuple of ``len(shapes)`` tensors, another shape,
    dtype or device than ``inputs[0]``, memory shared between them, or an autograd graph to break (an out tensor
    that requires grad, or inputs that do while grad is enabled: out= writes are not differentiable). ``None``
    inputs (optional frames not given) are skipped."""
    given = tuple(t for t in inputs if t is not None)
    if not isinstance(out, tuple) or len(out) != len(shapes) or not all(isinstance(t, Tensor) for t in out):
        raise InputError(f"out must be a tuple of {len(shapes)} tensors ({', '.join(names)}), got {out!r:.80}")
    reference = given[0]
    for tensor, shape, name in zip(out, shapes, names, strict=True):
        if tuple(tensor.shape) != tuple(shape) or tensor.dtype != reference.dtype or tensor.device != reference.device:
            raise ShapeError(f"out {name} must be a {reference.dtype} tensor of shape {tuple(shape)} on "
                             f"{reference.device}, got {tensor.dtype} {tuple(tensor.shape)} on {tensor.device}")
        if tensor.requires_grad:
            raise InputError(f"out {name} requires grad: out= writes are not differentiable; pass no out")
    if records_gradient(*given):
        raise InputError("out= writes are not differentiable, and an input requires grad: pass no out, or compute "
                         "under torch.no_grad()")
    pointers = [t.untyped_storage().data_ptr() for t in out]
    if len(set(pointers)) != len(pointers) or any(t.untyped_storage().data_ptr() in pointers for t in given):
        raise InputError(f"the out tensors ({', '.join(names)}) must not share memory with each other or the inputs")


def as_index(value: object) -> int | None:
    """``value`` as an ``int`` when it is an integer (an int, a numpy integer, a one-element integer tensor), else
    ``None``: a bool is no count, and 2.5 or a float tensor no index (``operator.index`` refuses them)."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)  # type: ignore[arg-type]  # refused below when not an index
    except TypeError:
        return None


def check_light_module(light_model: object, name: str) -> None:
    """Raise :class:`InputError` unless ``light_model`` is a light model (any ``nn.Module``: a user's need not subclass
    :class:`~psmini.lights.LightModel`); a tensor of directions, which failed as a bare "'Tensor' object is not
    callable", is told where it goes."""
    if not isinstance(light_model, nn.Module):
        hint = (f" of shape {tuple(light_model.shape)}; wrap a (K, 3) tensor of directions in DirectionalLights "
                "(render_lambertian takes one as it is)" if isinstance(light_model, Tensor) else "")
        raise InputError(f"{name} must be a light model of psmini.lights (an nn.Module), got "
                         f"{type(light_model).__name__}{hint}")
