r"""The mirror sphere: its silhouette in the image, its position in space, and light directions by reflection.

Pixel coordinates are ``(u, v) = (column, row)`` with the centre of the top-left pixel at ``(0, 0)``. Space is
psmini's camera frame (x right, y up, z toward the camera) with, for the perspective model, the origin at the
camera's centre of projection, so the scene lies at negative z. Intrinsics ``K`` are OpenCV's 3×3 pinhole
matrix (``u = fx·X/Z + cx`` with OpenCV's y down, z forward axes); :func:`pixel_rays` converts.

Silhouette. The sphere's outline is sampled at sub-pixel edge points (the crossings between inside and
outside pixels, moved along the pair to where the gray level crosses halfway between the local inside and
outside levels when an image is given), and a circle is fitted to them: Kåsa's algebraic fit (I. Kåsa, "A
circle fitting procedure and its error analysis", IEEE Trans. Instrum. Meas. 1976) as the start, then
Gauss–Newton on the geometric distances with outliers (highlights or shadows breaking the outline) trimmed
at three robust standard deviations (Chernov, "Circular and linear regression", 2010, ch. 4). Hundreds of
edge points put the centre and radius within a few hundredths of a pixel.

Space. Under perspective the outline of a sphere of radius ``R`` is where the camera's tangent cone touches
it: every outline ray ``r_i`` (unit) makes the same angle ``α`` with the ray ``c`` to the sphere's centre,
``r_i · c = cos α``. Writing ``w = c / cos α`` makes this linear, ``r_i · w = 1``, solved by least squares;
then ``c = w/|w|``, ``cos α = 1/|w|`` and the centre lies at distance ``R / sin α`` along ``c`` (the image
radius, ``K`` and the true radius give the depth). The outline is an ellipse off the axis, which the cone
fit models exactly where a circle fit would not.

Reflection. A light's direction is the view ray reflected about the sphere's normal at the highlight,
``l = d - 2 (d·n) n`` with ``d`` the ray from the camera (Woodham 1980; the seed paper's step 2). The
orthographic form takes ``d = (0, 0, -1)`` and the normal from the highlight's offset from the circle's
centre; the perspective form intersects the pixel's ray with the sphere and reflects that ray, which at the
rig's 10 mm scale is exact where the orthographic form errs by degrees (FIELD_NOTES, "Mirror sphere").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini._checks import check_finite, check_positive, check_shape, check_tensor
from psmini.errors import CalibrationError, InputError, ShapeError

__all__ = [
    "SphereSilhouette",
    "fit_circle",
    "silhouette_edges",
    "segment_sphere",
    "find_sphere",
    "pixel_rays",
    "sphere_centre_from_silhouette",
    "reflect_orthographic",
    "reflect_perspective",
]

# Outline points farther from the fitted circle than this many robust standard deviations are outliers.
_TRIM_SIGMAS = 3.0
# The robust standard deviation is never taken below this (pixels): a clean digitised outline has ~0.3 px.
_MIN_SIGMA_PX = 0.25
# A detected outline is a circle when this fraction of its edge points lies within 1.5 px of the fit.
_MIN_INLIER_FRACTION = 0.8


@dataclass
class SphereSilhouette:
    """The sphere's outline in the image.

    Attributes:
        centre_px: centre of the fitted circle ``(u, v)``, shape :math:`(2,)`, pixels.
        radius_px: radius of the fitted circle, shape :math:`()`, pixels.
        edge_px: the outline's edge points ``(u, v)``, shape :math:`(N, 2)`, pixels.
        inliers: the edge points the fit kept, shape :math:`(N,)` bool.
        mask: pixels on the sphere, shape :math:`(H, W)` bool (given or detected).
    """

    centre_px: Tensor
    radius_px: Tensor
    edge_px: Tensor
    inliers: Tensor
    mask: Tensor

    @property
    def rms_px(self) -> float:
        """Root-mean-square distance of the kept edge points from the circle, pixels."""
        distance = (self.edge_px[self.inliers] - self.centre_px).norm(dim=-1) - self.radius_px
        return float(distance.square().mean().sqrt())


def _kasa(points: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Algebraic circle fit: least squares of ``x² + y² + D x + E y + F = 0``; points (B, N, 2), weights (B, N)."""
    x, y = points[..., 0], points[..., 1]
    design = torch.stack([x, y, torch.ones_like(x)], dim=-1) * weights.unsqueeze(-1)
    target = -(x.square() + y.square()) * weights
    solution = torch.linalg.lstsq(design, target.unsqueeze(-1), driver="gels").solution[..., 0]  # (B, 3)
    centre = -solution[..., :2] / 2
    radius = (centre.square().sum(-1) - solution[..., 2]).clamp_min(0).sqrt()
    return centre, radius


def _geometric_step(points: Tensor, weights: Tensor, centre: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
    """One Gauss–Newton step on the distances ``|p - c| - r``."""
    offset = points - centre.unsqueeze(-2)
    distance = offset.norm(dim=-1).clamp_min(torch.finfo(points.dtype).eps)
    residual = (distance - radius.unsqueeze(-1)) * weights
    # d(residual)/d(c) = -(p - c)/|p - c|, d(residual)/d(r) = -1
    jacobian = torch.cat([-offset / distance.unsqueeze(-1), -torch.ones_like(distance).unsqueeze(-1)], dim=-1)
    jacobian = jacobian * weights.unsqueeze(-1)
    step = torch.linalg.lstsq(jacobian, -residual.unsqueeze(-1), driver="gels").solution[..., 0]
    return centre + step[..., :2], radius + step[..., 2]


def fit_circle(
    points: Tensor, weights: Tensor | None = None, iterations: int = 5, trim: bool = True
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Fit circles to 2-D points: Kåsa's algebraic fit refined by Gauss–Newton on the geometric distances.

    With ``trim`` the points farther than three robust standard deviations (1.4826 × the median absolute
    distance, at least 0.25) from the current circle get weight 0 before each refinement, so that a few
    outliers (a highlight breaking the outline) do not pull the fit.

    Args:
        points: points ``(u, v)``, shape :math:`(N, 2)` or :math:`(B, N, 2)`, at least 3 per circle.
        weights: optional non-negative weights, shape :math:`(N,)` or :math:`(B, N)`.
        iterations: Gauss–Newton steps.
        trim: drop outliers between steps.

    Returns:
        centre :math:`(2,)` or :math:`(B, 2)`, radius :math:`()` or :math:`(B,)`, and the inliers :math:`(N,)` or
        :math:`(B, N)` bool. Differentiable in the points (the trimming is a fixed selection).

    Raises:
        ShapeError: for points not of shape (N, 2) or (B, N, 2), or weights of another shape.
        CalibrationError: for fewer than 3 points.

    Example:
        >>> angle = torch.linspace(0, 6.0, 50)
        >>> centre, radius, _ = fit_circle(torch.stack([3 + 2 * angle.cos(), 1 + 2 * angle.sin()], -1))
        >>> [round(v, 4) for v in centre.tolist()], round(float(radius), 4)
        ([3.0, 1.0], 2.0)
    """
    check_tensor(points, "points")
    single = points.ndim == 2
    batched = points.unsqueeze(0) if single else points
    check_shape(batched, ["B", "N", "2"], "points")
    check_finite(batched, "points")
    if batched.shape[1] < 3:
        raise CalibrationError(f"a circle needs at least 3 points, got {batched.shape[1]}")
    if weights is None:
        weights = torch.ones(batched.shape[:2], device=points.device, dtype=points.dtype)
    else:
        weights = weights.unsqueeze(0) if single else weights
        if tuple(weights.shape) != tuple(batched.shape[:2]):
            raise ShapeError(f"weights must have shape {tuple(points.shape[:-1])}, got {tuple(weights.shape)}")
        weights = weights.to(points)
    centre, radius = _kasa(batched, weights)
    inliers = weights > 0
    for _ in range(iterations):
        if trim:
            distance = ((batched - centre.unsqueeze(-2)).norm(dim=-1) - radius.unsqueeze(-1)).abs().detach()
            sigma = (1.4826 * distance.masked_fill(weights <= 0, float("nan")).nanmedian(dim=-1).values)
            sigma = sigma.clamp_min(_MIN_SIGMA_PX).unsqueeze(-1)
            inliers = (distance <= _TRIM_SIGMAS * sigma) & (weights > 0)
        centre, radius = _geometric_step(batched, weights * inliers, centre, radius)
    if single:
        return centre[0], radius[0], inliers[0]
    return centre, radius, inliers


def silhouette_edges(mask: Tensor, image: Tensor | None = None) -> Tensor:
    r"""Sub-pixel edge points of a region's outline.

    Every pair of 4-neighbouring pixels, one inside and one outside, gives a point between their centres: at
    the midpoint for a bare mask (the unbiased place for a region whose pixels are inside when their centres
    are), or, with ``image``, where the gray level crosses halfway between the local inside and outside
    levels (read two pixels beyond the pair on either side), which follows a soft (anti-aliased or
    slightly defocused, up to ~3 pixels wide) outline. Edges on the image border are skipped.

    Args:
        mask: the region, shape :math:`(H, W)` bool.
        image: optional gray image, shape :math:`(H, W)`.

    Returns:
        edge points ``(u, v)``, shape :math:`(N, 2)`, in the image's dtype (float32 without one).

    Raises:
        ShapeError: when the mask is not 2-D or empty, or the image's size differs.
        InputError: an image that is not a floating-point tensor.

    Example:
        >>> mask = torch.zeros(9, 9, dtype=torch.bool)
        >>> mask[3:6, 3:6] = True
        >>> silhouette_edges(mask).shape
        torch.Size([12, 2])
    """
    # an empty mask failed as a bare RuntimeError of narrow(), an image that is not a tensor as an AttributeError
    if not isinstance(mask, Tensor) or mask.ndim != 2 or mask.numel() == 0:
        raise ShapeError(f"mask must be a non-empty 2-D (H, W) tensor, got "
                         f"{getattr(mask, 'shape', type(mask).__name__)}")
    mask = mask.bool()
    if image is not None:
        check_shape(image, ["H", "W"], "image")
        if image.shape != mask.shape:
            raise ShapeError(f"image {tuple(image.shape)} and mask {tuple(mask.shape)} must have the same size")
    dtype = image.dtype if image is not None else torch.float32
    points = []
    for axis in (1, 0):  # horizontal pairs (u varies), then vertical pairs (v varies)
        first = mask.narrow(axis, 0, mask.shape[axis] - 1)
        second = mask.narrow(axis, 1, mask.shape[axis] - 1)
        rows, cols = torch.nonzero(first != second, as_tuple=True)
        fraction = torch.full(rows.shape, 0.5, device=mask.device, dtype=dtype)
        if image is not None:
            fraction = _crossing(image, mask, rows, cols, axis, fraction)
        u = cols.to(dtype) + (fraction if axis == 1 else 0)
        v = rows.to(dtype) + (fraction if axis == 0 else 0)
        points.append(torch.stack([u, v], dim=-1))
    return torch.cat(points)


def _crossing(image: Tensor, mask: Tensor, rows: Tensor, cols: Tensor, axis: int, fallback: Tensor) -> Tensor:
    """Fraction along each pair (from the first pixel) where the image crosses its local half level."""
    length = image.shape[axis]

    def read(offset: int) -> Tensor:
        if axis == 1:
            return image[rows, (cols + offset).clamp(0, length - 1)]
        return image[(rows + offset).clamp(0, length - 1), cols]

    first, second = read(0), read(1)
    before, after = read(-2), read(3)  # two pixels beyond the pair, on either side
    first_inside = mask[rows, cols]
    inside = torch.where(first_inside, before, after)
    outside = torch.where(first_inside, after, before)
    half = (inside + outside) / 2
    step = second - first
    contrast = (inside - outside).abs()
    fraction = (half - first) / torch.where(step.abs() > 0, step, torch.ones_like(step))
    # a crossing is trusted only where the pair itself spans the half level of a real step
    good = (contrast > 0) & (fraction >= 0) & (fraction <= 1)
    return torch.where(good, fraction, fallback)


def _label(binary: Tensor) -> Tensor:
    """Connected components (8-connected) of a batch of masks (B, H, W): each pixel gets the largest flat index
    + 1 of its component, 0 off the mask.

    Each pixel holds a pointer (a flat index, starting at its own); every round it takes the largest pointer in
    its 3×3 neighbourhood (hooking) and then follows pointers to pointers until they stop changing (pointer
    jumping), which carries the largest index across a component in a few rounds rather than one pixel per
    round (Shiloach & Vishkin, "An O(log n) parallel connectivity algorithm", J. Algorithms 1982).
    """
    batch, height, width = binary.shape
    count = height * width
    dtype = torch.float32 if count < 2**24 else torch.float64  # flat indices stay exact
    index = torch.arange(count, device=binary.device, dtype=dtype).view(1, 1, height, width)
    keep = binary.unsqueeze(1)
    off = torch.full((), -1.0, device=binary.device, dtype=dtype)
    pointer = torch.where(keep, index, off)
    while True:
        hooked = torch.where(keep, F.max_pool2d(pointer, 3, stride=1, padding=1), off).view(batch, count)
        while True:
            jumped = torch.where(hooked >= 0, hooked.gather(1, hooked.clamp_min(0).long()), hooked)
            if torch.equal(jumped, hooked):
                break
            hooked = jumped
        hooked = hooked.view(batch, 1, height, width)
        if torch.equal(hooked, pointer):
            break
        pointer = hooked
    return (pointer[:, 0] + 1).long()


def _fill_holes(region: Tensor) -> Tensor:
    """The region (H, W) with every background component that does not touch the border filled."""
    background = _label((~region).unsqueeze(0))[0]
    border = torch.cat([background[0], background[-1], background[:, 0], background[:, -1]]).unique()
    return region | ((background > 0) & ~torch.isin(background, border))


def _otsu(values: Tensor, bins: int = 256) -> Tensor:
    """Otsu's threshold of a set of values (N. Otsu, IEEE Trans. SMC 1979): maximum between-class variance."""
    low, high = values.min(), values.max()
    histogram = torch.histc(values, bins=bins, min=float(low), max=float(high))
    centres = low + (torch.arange(bins, device=values.device, dtype=values.dtype) + 0.5) * (high - low) / bins
    weight = histogram.cumsum(0)
    total = weight[-1]
    mean = (histogram * centres).cumsum(0)
    between = (mean[-1] * weight - mean * total).square() / (weight * (total - weight)).clamp_min(1)
    return centres[int(between[:-1].argmax())] + (high - low) / (2 * bins)


def segment_sphere(image: Tensor, min_radius_px: float = 5.0) -> Tensor:
    r"""Find the sphere's region in a summed or all-LEDs image, without a mask.

    The image is smoothed (Gaussian, σ = 1 px) and split by Otsu's threshold; the connected components of both
    classes (a mirror sphere may look darker or brighter than its surroundings) that do not touch the image's
    border and hold at least the area of a disc of ``min_radius_px`` are filled (highlights make holes in a
    dark sphere) and the largest one whose outline is a circle (80% of its edge points within 1.5 px of the
    fitted circle) is the sphere.

    Args:
        image: gray image, shape :math:`(H, W)`, e.g. the sum of the images under every LED.
        min_radius_px: the smallest sphere radius to accept, pixels.

    Returns:
        the sphere's pixels, shape :math:`(H, W)` bool.

    Raises:
        ShapeError: when the image is not 2-D.
        CalibrationError: "sphere not found" when no component qualifies (a flat image, the sphere cut by the
            image's border, no round region).

    Example:
        >>> v, u = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
        >>> disc = ((u - 30.3).square() + (v - 33.6).square() < 15.0**2).float()
        >>> int(segment_sphere(0.2 + 0.5 * disc).sum())
        709
    """
    import kornia.filters

    check_shape(image, ["H", "W"], "image")
    check_finite(image, "image")
    if float(image.max() - image.min()) <= 0:
        raise CalibrationError("sphere not found: the image is uniform (no contrast between sphere and background)")
    smooth = kornia.filters.gaussian_blur2d(image[None, None], (7, 7), (1.0, 1.0), border_type="replicate")[0, 0]
    threshold = _otsu(smooth.flatten())
    min_area = torch.pi * min_radius_px**2
    best, best_area = None, 0.0
    for region in (smooth <= threshold, smooth > threshold):
        labels = _label(region.unsqueeze(0))[0]
        border = torch.cat([labels[0], labels[-1], labels[:, 0], labels[:, -1]]).unique()
        ids, counts = labels[labels > 0].unique(return_counts=True)
        for label, count in zip(ids.tolist(), counts.tolist(), strict=True):
            if count < min_area or count <= best_area or label in border.tolist():
                continue
            candidate = _fill_holes(labels == label)
            edges = silhouette_edges(candidate).to(image.dtype)
            centre, radius, _ = fit_circle(edges)
            near = ((edges - centre).norm(dim=-1) - radius).abs() <= 1.5
            if float(near.float().mean()) >= _MIN_INLIER_FRACTION:
                best, best_area = candidate, float(count)
    if best is None:
        raise CalibrationError(
            f"sphere not found: no round region of radius >= {min_radius_px} px clear of the image border in the "
            f"{image.shape[1]}x{image.shape[0]} image; give the sphere's mask image (--mask) or check the framing"
        )
    return best


def find_sphere(image: Tensor | None = None, mask: Tensor | None = None) -> SphereSilhouette:
    r"""The sphere's silhouette: from its mask when given, else detected in ``image`` (:func:`segment_sphere`).

    Args:
        image: gray image, shape :math:`(H, W)` (the sum of the images under every LED); refines the edge
            points to sub-pixel level crossings when given.
        mask: the sphere's pixels, shape :math:`(H, W)` (non-zero inside).

    Returns:
        a :class:`SphereSilhouette`.

    Raises:
        InputError: when neither is given.
        CalibrationError: when the sphere is not found, or the mask's region is not round (its outline is
            not a circle) or touches the image border.

    Example:
        >>> v, u = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
        >>> mask = (u - 30.3).square() + (v - 33.6).square() < 15.0**2
        >>> sphere = find_sphere(mask=mask)
        >>> [round(c, 1) for c in sphere.centre_px.tolist()], round(float(sphere.radius_px), 1)
        ([30.3, 33.6], 15.0)
    """
    if mask is None:
        if image is None:
            raise InputError("find_sphere needs an image or a mask of the sphere")
        mask = segment_sphere(image)
    else:
        if not isinstance(mask, Tensor) or mask.ndim != 2:
            raise ShapeError(f"mask must be a 2-D (H, W) tensor, got {getattr(mask, 'shape', type(mask).__name__)}")
        mask = mask != 0
        if not bool(mask.any()):
            raise CalibrationError("sphere not found: the mask is empty")
        if bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any()):
            raise CalibrationError("the sphere's mask touches the image border: the whole sphere must be in view")
    edges = silhouette_edges(mask, image)
    if image is None:
        edges = edges.to(torch.get_default_dtype())
    centre, radius, inliers = fit_circle(edges)
    if float(inliers.float().mean()) < _MIN_INLIER_FRACTION:
        raise CalibrationError(
            f"the sphere's outline is not a circle: only {float(inliers.float().mean()):.0%} of its {len(edges)} edge "
            "points lie near the fitted circle"
        )
    return SphereSilhouette(centre, radius, edges, inliers, mask)


def _check_intrinsics(intrinsics: Tensor) -> Tensor:
    check_shape(intrinsics, ["3", "3"], "intrinsics")
    check_finite(intrinsics, "intrinsics")
    if not bool((intrinsics[0, 0] > 0) & (intrinsics[1, 1] > 0)):
        raise CalibrationError(f"intrinsics must have positive focal lengths fx, fy, got {intrinsics.tolist()}")
    return intrinsics


def pixel_rays(points_px: Tensor, intrinsics: Tensor) -> Tensor:
    r"""Unit rays from the camera's centre through pixels, in psmini's camera frame.

    Args:
        points_px: pixel coordinates ``(u, v)``, shape :math:`(..., 2)`.
        intrinsics: OpenCV pinhole matrix ``K``, shape :math:`(3, 3)`.

    Returns:
        unit directions, shape :math:`(..., 3)`, x right, y up, z toward the camera (so z < 0).

    Raises:
        ShapeError: for wrong shapes. CalibrationError: for focal lengths that are not positive.

    Example:
        >>> K = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
        >>> pixel_rays(torch.tensor([50.0, 50.0]), K).tolist()
        [0.0, -0.0, -1.0]
    """
    check_tensor(points_px, "points_px")
    if points_px.shape[-1] != 2:
        raise ShapeError(f"points_px must have shape (..., 2), got {tuple(points_px.shape)}")
    intrinsics = _check_intrinsics(intrinsics).to(points_px)
    homogeneous = torch.cat([points_px, torch.ones_like(points_px[..., :1])], dim=-1)
    opencv = torch.linalg.solve(intrinsics, homogeneous.unsqueeze(-1))[..., 0]  # x right, y down, z forward
    rays = opencv * torch.tensor([1.0, -1.0, -1.0], device=points_px.device, dtype=points_px.dtype)
    return rays / rays.norm(dim=-1, keepdim=True)


def sphere_centre_from_silhouette(
    edge_px: Tensor, intrinsics: Tensor, radius_mm: float, weights: Tensor | None = None
) -> Tensor:
    r"""The sphere's centre in space from its outline (the tangent cone), the intrinsics and its true radius.

    Solves ``r_i · w = 1`` by least squares for the outline rays ``r_i``; the centre lies along
    ``c = w / |w|`` at distance ``R / sin α`` with ``cos α = 1 / |w|``.

    Args:
        edge_px: outline points ``(u, v)``, shape :math:`(N, 2)`, pixels.
        intrinsics: OpenCV pinhole matrix ``K``, shape :math:`(3, 3)`.
        radius_mm: the sphere's true radius, mm.
        weights: optional weights of the points, shape :math:`(N,)` (0 drops an outlier).

    Returns:
        the centre, shape :math:`(3,)`, mm, camera frame with the origin at the centre of projection.
        Differentiable in the edge points and the intrinsics.

    Raises:
        CalibrationError: for fewer than 3 points, or an outline that is not a cone (a degenerate fit).
        ShapeError: edge points that are not :math:`(N, 2)`, weights that are not :math:`(N,)`, intrinsics that
            are not :math:`(3, 3)`. InputError: NaN or infinite edge points or weights, a radius that is not a
            positive number.

    Example:
        >>> K = torch.tensor([[1600.0, 0, 199.5], [0, 1600.0, 199.5], [0, 0, 1]])
        >>> angle = torch.linspace(0, 6.2, 100)
        >>> edges = torch.stack([199.5 + 62 * angle.cos(), 199.5 + 62 * angle.sin()], -1)
        >>> round(float(sphere_centre_from_silhouette(edges, K, 1.5)[2]), 1)
        -38.7
    """
    # NaN edge points were reported as "not a cone (|w| = nan)"; weights of another length or not a tensor failed
    # as bare RuntimeErrors and AttributeErrors
    sizes = check_shape(edge_px, ["N", "2"], "edge_px")
    check_finite(edge_px, "edge_px")
    check_positive(radius_mm, "radius_mm")
    if weights is not None:  # any dtype: the inliers of find_sphere as they are, or their floats
        if not isinstance(weights, Tensor) or tuple(weights.shape) != (sizes["N"],):
            got = tuple(weights.shape) if isinstance(weights, Tensor) else type(weights).__name__
            raise ShapeError(f"weights must have shape ({sizes['N']},), one per edge point, got {got}")
        check_finite(weights, "weights")
    if edge_px.shape[0] < 3:
        raise CalibrationError(f"the sphere's outline needs at least 3 points, got {edge_px.shape[0]}")
    rays = pixel_rays(edge_px, intrinsics)
    if weights is not None:
        rays = rays * weights.to(rays).unsqueeze(-1)
        target = weights.to(rays).unsqueeze(-1)
    else:
        target = torch.ones_like(rays[:, :1])
    # least squares by an explicit QR: the outline rays have full rank, pivoting drivers can flip their pivots
    # between nearby inputs, and torch 2.13's lstsq backward disagrees with finite differences here
    q, r = torch.linalg.qr(rays)
    w = torch.linalg.solve_triangular(r, q.transpose(-2, -1) @ target, upper=True)[:, 0]
    norm = w.norm()
    if not bool(norm > 1):
        raise CalibrationError("the sphere's outline does not form a cone around a sphere "
                               f"(|w| = {float(norm):.4g} <= 1)")
    sin_alpha = (1 - 1 / norm.square()).sqrt()
    return w / norm * (radius_mm / sin_alpha)


def reflect_orthographic(highlights_px: Tensor, centre_px: Tensor, radius_px: Tensor | float) -> Tensor:
    r"""Light directions from highlights on a mirror sphere seen by an orthographic camera (view ``(0, 0, 1)``).

    The normal at a highlight offset ``(du, dv)`` pixels from the centre is ``(du/ρ, -dv/ρ, √(1 - …))`` and the
    light direction ``l = 2 (n·v) n - v`` with ``v = (0, 0, 1)``.

    Args:
        highlights_px: highlights ``(u, v)``, shape :math:`(K, 2)` (or any :math:`(..., 2)`), pixels.
        centre_px: the sphere's centre in the image, shape :math:`(2,)`.
        radius_px: its radius in the image, pixels.

    Returns:
        unit light directions, shape :math:`(K, 3)`, camera frame. Differentiable.

    Raises:
        CalibrationError: naming the LED whose highlight lies outside the sphere's circle.

    Example:
        >>> reflect_orthographic(torch.tensor([[50.0, 50.0]]), torch.tensor([50.0, 50.0]), 20.0).tolist()
        [[0.0, -0.0, 1.0]]
    """
    check_tensor(highlights_px, "highlights_px")
    if highlights_px.shape[-1] != 2:
        raise ShapeError(f"highlights_px must have shape (K, 2), got {tuple(highlights_px.shape)}")
    radius = torch.as_tensor(radius_px, device=highlights_px.device, dtype=highlights_px.dtype)
    offset = (highlights_px - centre_px.to(highlights_px)) / radius
    planar = torch.stack([offset[..., 0], -offset[..., 1]], dim=-1)
    outside = planar.square().sum(-1) >= 1
    if bool(outside.any()):
        leds = torch.nonzero(outside.reshape(-1)).flatten().tolist()
        raise CalibrationError(f"highlight outside the sphere for LED(s) {leds}: the highlight lies beyond the circle")
    normals = torch.cat([planar, (1 - planar.square().sum(-1, keepdim=True)).sqrt()], dim=-1)
    view = torch.zeros_like(normals)
    view[..., 2] = 1
    return 2 * normals[..., 2:3] * normals - view


def reflect_perspective(
    highlights_px: Tensor, intrinsics: Tensor, centre_mm: Tensor, radius_mm: float
) -> tuple[Tensor, Tensor]:
    r"""Light directions from highlights on a mirror sphere seen by a pinhole camera: reflect the pixel's ray.

    Each highlight's ray ``d`` (:func:`pixel_rays`) meets the sphere first at ``P = t d`` with
    ``t = d·C - √((d·C)² - |C|² + R²)``; the normal there is ``n = (P - C)/R`` and the light direction
    ``l = d - 2 (d·n) n``.

    Args:
        highlights_px: highlights ``(u, v)``, shape :math:`(K, 2)`, pixels.
        intrinsics: OpenCV pinhole matrix ``K``, shape :math:`(3, 3)`.
        centre_mm: the sphere's centre, shape :math:`(3,)`, mm, camera frame with the origin at the centre of
            projection (:func:`sphere_centre_from_silhouette`).
        radius_mm: the sphere's radius, mm.

    Returns:
        unit light directions :math:`(K, 3)` and the reflection points on the sphere :math:`(K, 3)` (mm, same
        frame): each LED lies on the ray from its point along its direction. Differentiable.

    Raises:
        CalibrationError: naming the LED whose highlight's ray misses the sphere (a highlight outside it).

    Example:
        >>> K = torch.tensor([[1600.0, 0, 199.5], [0, 1600.0, 199.5], [0, 0, 1]])
        >>> centre = torch.tensor([0, 0, -38.5])
        >>> directions, points = reflect_perspective(torch.tensor([[199.5, 199.5]]), K, centre, 1.5)
        >>> float(directions[0, 2]), float(points[0, 2])
        (1.0, -37.0)
    """
    check_shape(highlights_px, ["K", "2"], "highlights_px")
    check_positive(radius_mm, "radius_mm")
    rays = pixel_rays(highlights_px, intrinsics)
    centre = centre_mm.to(rays)
    along = rays @ centre  # d · C, (K,)
    discriminant = along.square() - centre.square().sum() + radius_mm**2
    missed = discriminant <= 0
    if bool(missed.any()):
        leds = torch.nonzero(missed).flatten().tolist()
        raise CalibrationError(
            f"highlight outside the sphere for LED(s) {leds}: the ray through the highlight misses the sphere"
        )
    points = (along - discriminant.sqrt()).unsqueeze(-1) * rays
    normals = (points - centre) / radius_mm
    directions = rays - 2 * (rays * normals).sum(-1, keepdim=True) * normals
    return directions, points
