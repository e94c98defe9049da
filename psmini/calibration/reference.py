r"""The flat-field reference: the matte card's image under each LED, averaged, dark-subtracted and smoothed.

Every reconstruction is divided by the card's image (:mod:`psmini.flatfield`), so whatever noise and dust the
card image carries prints into every result. The reference is therefore built from repeated frames
(averaging divides the sensor noise by √N), with the dark frame (averaged too) subtracted, and then replaced
by a smooth surface, which the LED's irradiance on a flat card is (inverse square law, beam shape,
vignetting):

- ``"polynomial"``: a 2-D polynomial of total degree ``degree`` in coordinates scaled to [-1, 1], fitted per
  LED by weighted least squares over the trusted pixels (a low-order fit leaves dust specks and noise out
  entirely);
- ``"gaussian"``: a normalised Gaussian convolution (``blur(card · valid) / blur(valid)``, Knutsson &
  Westin, "Normalized and differential convolution", CVPR 1993) with ``kornia.filters.gaussian_blur2d``,
  which follows any smooth shape and ignores untrusted pixels;
- ``"mean"``: the average alone.

Pixels whose averaged card level is below ``min_level`` of that LED's brightest pixel, or that saturate in any
frame, are not trusted: they get a reference of 0, which :func:`psmini.flatfield.flatfield` drops.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from psmini._checks import check_finite, check_positive, check_tensor
from psmini.errors import InputError, ShapeError

__all__ = ["CardReference", "card_reference", "polynomial_surface", "SMOOTHING_METHODS"]

SMOOTHING_METHODS = ("polynomial", "gaussian", "mean")


@dataclass
class CardReference:
    """A flat-field reference.

    Attributes:
        reference: the card under each LED, dark-subtracted and smoothed, shape :math:`(K, H, W)`; 0 where not
            trusted.
        dark: the averaged dark frame, shape :math:`(1, H, W)`, or None.
        valid: trusted pixels, shape :math:`(K, H, W)` bool.
        frames: how many frames were averaged.
        residual: root-mean-square difference between the averaged card and the smooth reference over the
            trusted pixels, per LED, shape :math:`(K,)`: the noise (and dust) the smoothing removed.
    """

    reference: Tensor
    dark: Tensor | None
    valid: Tensor
    frames: int
    residual: Tensor


def _as_frames(frames: Tensor) -> Tensor:
    check_tensor(frames, "frames")
    if frames.ndim == 3:
        frames = frames.unsqueeze(0)
    if frames.ndim != 4:
        raise ShapeError(f"frames must have shape (K, H, W) or (N, K, H, W) (N repeats), got {tuple(frames.shape)}")
    return check_finite(frames, "frames")


def _as_dark(dark: Tensor | None, height: int, width: int) -> Tensor | None:
    if dark is None:
        return None
    check_tensor(dark, "dark")
    if dark.ndim == 2:
        dark = dark[None, None]
    elif dark.ndim == 3:
        dark = dark.unsqueeze(1)
    if dark.ndim != 4 or dark.shape[1] != 1 or tuple(dark.shape[2:]) != (height, width):
        raise ShapeError(f"dark must have shape (H, W), (N, H, W) or (N, 1, H, W) with H, W = {height}, {width}, "
                         f"got {tuple(dark.shape)}")
    return check_finite(dark, "dark").mean(dim=0)


def polynomial_surface(values: Tensor, weights: Tensor, degree: int) -> Tensor:
    r"""Least-squares 2-D polynomials of total degree ``degree``, one per image.

    Coordinates are scaled to [-1, 1] over the image (well-conditioned monomials); the normal equations are
    solved in float64.

    Args:
        values: images, shape :math:`(K, H, W)`.
        weights: non-negative weights, shape :math:`(K, H, W)` (0 leaves a pixel out).
        degree: total degree, 0 to 10.

    Returns:
        the fitted surfaces, shape :math:`(K, H, W)`, in the dtype of ``values``. Differentiable in ``values``.

    Raises:
        InputError: for a degree out of range, or fewer weighted pixels than coefficients.

    Example:
        >>> y, x = torch.meshgrid(torch.linspace(-1, 1, 20), torch.linspace(-1, 1, 30), indexing="ij")
        >>> plane = (1 + 0.5 * x - 0.25 * y)[None]
        >>> torch.allclose(polynomial_surface(plane, torch.ones_like(plane), 1), plane, atol=1e-5)
        True
    """
    if not isinstance(degree, int) or not 0 <= degree <= 10:
        raise InputError(f"degree must be an integer from 0 to 10, got {degree!r}")
    count, height, width = values.shape
    y, x = torch.meshgrid(
        torch.linspace(-1, 1, height, device=values.device, dtype=torch.float64),
        torch.linspace(-1, 1, width, device=values.device, dtype=torch.float64),
        indexing="ij",
    )
    design = torch.stack([x**i * y**j for i in range(degree + 1) for j in range(degree + 1 - i)], dim=-1)
    design = design.reshape(height * width, -1)  # (P, M)
    terms = design.shape[1]
    w = weights.reshape(count, -1).to(torch.float64)
    if bool(((w > 0).sum(-1) < terms).any()):
        raise InputError(f"a degree-{degree} polynomial needs at least {terms} trusted pixels per image")
    normal = torch.einsum("pm,kp,pn->kmn", design, w, design)
    right = torch.einsum("pm,kp,kp->km", design, w, values.reshape(count, -1).to(torch.float64))
    coef = torch.linalg.solve(normal, right)
    return (coef @ design.T).reshape(count, height, width).to(values.dtype)


def _gaussian(values: Tensor, weights: Tensor, sigma_px: float) -> Tensor:
    import kornia.filters

    size = 2 * int(3 * sigma_px) + 1
    pad = size // 2
    if pad >= min(values.shape[-2:]):
        raise InputError(f"sigma_px {sigma_px} is too large for a {values.shape[-1]}x{values.shape[-2]} image")
    blur = lambda x: kornia.filters.gaussian_blur2d(x[None], (size, size), (sigma_px, sigma_px), "reflect")[0]  # noqa: E731
    weights = weights.to(values)
    return blur(values * weights) / blur(weights).clamp_min(torch.finfo(values.dtype).tiny)


def card_reference(
    frames: Tensor,
    dark: Tensor | None = None,
    *,
    method: str = "polynomial",
    degree: int = 6,
    sigma_px: float = 8.0,
    min_level: float = 0.02,
    saturation_level: float | None = 1.0,
) -> CardReference:
    r"""Build the flat-field reference from repeated frames of the matte card under each LED.

    Args:
        frames: the card under each LED, shape :math:`(K, H, W)` or :math:`(N, K, H, W)` for N repeats, linear
            values in [0, 1].
        dark: all-LEDs-off frame(s), shape :math:`(H, W)`, :math:`(N, H, W)` or :math:`(N, 1, H, W)`; averaged and
            subtracted.
        method: ``"polynomial"``, ``"gaussian"`` or ``"mean"`` (see the module's description).
        degree: total degree of the polynomial.
        sigma_px: standard deviation of the Gaussian, pixels.
        min_level: fraction of each LED's brightest (averaged, dark-subtracted) pixel below which a pixel is
            not trusted.
        saturation_level: raw level at which a pixel counts as saturated (in any frame), or None.

    Returns:
        :class:`CardReference`.

    Raises:
        ShapeError: for frames not (K, H, W) or (N, K, H, W), or a dark frame of another size.
        InputError: for an unknown method or an option out of range; a card with no trusted pixel.

    Example:
        >>> card = card_reference(0.5 + 0.01 * torch.randn(4, 8, 32, 32), method="polynomial", degree=2)
        >>> card.reference.shape, bool((card.reference - 0.5).abs().max() < 0.01)
        (torch.Size([8, 32, 32]), True)
    """
    frames = _as_frames(frames)
    repeats, count, height, width = frames.shape
    if method not in SMOOTHING_METHODS:
        raise InputError(f"method must be one of {list(SMOOTHING_METHODS)}, got {method!r}")
    if not 0 <= min_level < 1:
        raise InputError(f"min_level must lie in [0, 1), got {min_level}")
    mean_dark = _as_dark(dark, height, width)
    card = frames.mean(dim=0)
    if mean_dark is not None:
        card = card - mean_dark.to(card)
    valid = (card > min_level * card.amax(dim=(-2, -1), keepdim=True)) & (card > 0)
    if saturation_level is not None:
        valid = valid & ~(frames >= saturation_level).any(dim=0)
    empty = torch.nonzero(~valid.flatten(1).any(-1)).flatten().tolist()
    if empty:
        raise InputError(f"the card images of LED(s) {empty} have no trusted pixel (dark, or saturated everywhere)")
    if method == "polynomial":
        smooth = polynomial_surface(card, valid.to(card), degree)
    elif method == "gaussian":
        smooth = _gaussian(card, valid, check_positive(sigma_px, "sigma_px"))
    else:
        smooth = card
    smooth = torch.where(valid, smooth.clamp_min(0), torch.zeros_like(smooth))
    difference = torch.where(valid, card - smooth, torch.zeros_like(card))
    residual = (difference.square().sum(dim=(-2, -1)) / valid.sum(dim=(-2, -1))).sqrt()
    return CardReference(smooth, mean_dark, valid, repeats, residual)
