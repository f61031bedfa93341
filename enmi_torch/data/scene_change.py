"""Controlled scene changes: what a map photograph and a later capture of the same place differ by, beyond noise.

Each change is a pure function of ``(image, seed, strength)``: the same arguments give the same image, ``strength``
0 gives the image unchanged and the change grows with ``strength`` up to 1 (strong: what a photograph of the place at
another date or season can differ by). Every random draw comes from a ``torch.Generator`` seeded with ``seed``, in
float64, so float32 and float64 images get the same change up to float32 round-off. Random fields have a length
scale in pixels (not in image sizes), so a crop of a larger image gets changes of the same kind and size.

* :func:`illumination`: a smooth multiplicative gain field (sun angle, haze, vignetting);
* :func:`shadows`: hard-edged cast shadows (rotated boxes, soft penumbra) darkening what lies under them;
* :func:`occluders`: cars (rotated boxes) and trees (ragged blobs) with the texture of other photographs pasted
  over the scene (scikit-image's ``chelsea``, ``clock``, ``coins``, ``grass``, ``moon`` and ``cell``, none of them
  a map of the yardstick);
* :func:`tone`: seasonal tone change: two smooth random tone curves (non-linear, possibly non-monotonic), blended by
  a smooth spatial field, so that no single function of the map's grey level explains the change;
* :func:`resample_blur`: another sensor's resolution: an anisotropic Gaussian blur and resampling on a coarser grid
  with a random phase;
* :func:`warp`: small parallax or elastic displacements (a smooth field with zero mean: no net shift);
* :func:`scene_change`: several of them composed, in the order a scene and its capture happen.

Convention:
    Images are ``(H, W)`` floating-point tensors of grey levels; the result has the image's shape and dtype and lies
    in ``value_range`` (values are clipped there). Nothing gets gradients (a data generator).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional

from enmi_torch.utils.checks import check_floating, check_option, check_value_range

SOURCES = ("chelsea", "clock", "coins", "grass", "moon", "cell")


def _check(image, seed, strength, value_range) -> tuple[Tensor, float, tuple[float, float]]:
    check_floating("image", image)
    if image.ndim != 2 or min(image.shape) < 2:
        raise ValueError(f"image must be (H, W) with H, W >= 2, got shape {tuple(image.shape)}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed must be an int, got {type(seed).__name__} {seed!r}")
    if isinstance(strength, bool) or not isinstance(strength, (int, float)) or not 0 <= strength <= 1:
        raise ValueError(f"strength must be a number in [0, 1], got {strength!r}")
    return image.detach().to(torch.float64), float(strength), check_value_range(value_range)


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed % (1 << 63))


def smooth_field(shape: tuple[int, int], scale: float, generator: torch.Generator) -> Tensor:
    """A smooth random field ``(H, W)`` float64 with mean 0 and standard deviation 1 over the image.

    Normal draws on a grid of spacing ``scale`` pixels, interpolated bicubically: structures about ``scale`` wide.
    """
    height, width = shape
    rows, cols = math.ceil(height / scale) + 4, math.ceil(width / scale) + 4
    coarse = torch.randn(1, 1, rows, cols, generator=generator, dtype=torch.float64)
    fine = functional.interpolate(coarse, scale_factor=scale, mode="bicubic", align_corners=False)
    offset = int(1.5 * scale)  # skip the grid's first cells, where bicubic interpolation sees the padding
    field = fine[0, 0, offset : offset + height, offset : offset + width]
    return (field - field.mean()) / field.std().clamp_min(1e-12)


def _sample(image: Tensor, rows: Tensor, cols: Tensor) -> Tensor:
    """Bilinear samples of ``image`` ``(H, W)`` at pixel coordinates ``rows``, ``cols`` (any shape), reflected."""
    height, width = image.shape
    grid = torch.stack([2 * cols / (width - 1) - 1, 2 * rows / (height - 1) - 1], dim=-1)
    sampled = functional.grid_sample(
        image[None, None], grid.reshape(1, -1, 1, 2), mode="bilinear", padding_mode="reflection", align_corners=True
    )
    return sampled.reshape(rows.shape)


def _blur(image: Tensor, sigma_rows: float, sigma_cols: float) -> Tensor:
    """Separable Gaussian blur of ``(H, W)``, reflected at the border; a sigma of 0 leaves that axis alone."""
    out = image[None, None]
    for axis, sigma in ((-2, sigma_rows), (-1, sigma_cols)):
        if sigma <= 0:
            continue
        radius = max(1, math.ceil(3 * sigma))
        taps = torch.arange(-radius, radius + 1, dtype=image.dtype)
        kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
        kernel = kernel / kernel.sum()
        radius = min(radius, image.shape[axis] - 1)  # reflection needs the pad below the side's length
        kernel = kernel[kernel.shape[0] // 2 - radius : kernel.shape[0] // 2 + radius + 1]
        kernel = kernel / kernel.sum()
        pad = (radius, radius, 0, 0) if axis == -1 else (0, 0, radius, radius)
        weights = kernel.view(1, 1, 1, -1) if axis == -1 else kernel.view(1, 1, -1, 1)
        out = functional.conv2d(functional.pad(out, pad, mode="reflect"), weights)
    return out[0, 0]


def _finish(changed: Tensor, image: Tensor, value_range: tuple[float, float]) -> Tensor:
    return changed.clamp(*value_range).to(image.dtype)


def illumination(
    image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)
) -> Tensor:
    """A smooth multiplicative illumination field: ``image * exp(0.5 strength f)``, ``f`` about 40 pixels wide.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: in ``[0, 1]``; the log gain has standard deviation ``0.5 strength`` over the image.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.

    Example:
        >>> image = torch.full((4, 6), 100.0)
        >>> bool(torch.equal(illumination(image, 3, 0.0), image)), illumination(image, 3, 1.0).std().item() > 10
        (True, True)
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    field = smooth_field(values.shape, 40.0, _generator(seed))
    return _finish(values * torch.exp(0.5 * strength * field), image, value_range)


def _box(rows: Tensor, cols: Tensor, centre, half_length: float, half_width: float, angle: float) -> Tensor:
    """Coverage in ``[0, 1]`` of a rotated box with a one-pixel soft edge."""
    along = (cols - centre[1]) * math.cos(angle) + (rows - centre[0]) * math.sin(angle)
    across = -(cols - centre[1]) * math.sin(angle) + (rows - centre[0]) * math.cos(angle)
    inside = torch.minimum(half_length - along.abs(), half_width - across.abs())
    return (inside + 0.5).clamp(0, 1)


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))


def shadows(image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)) -> Tensor:
    """Cast shadows: rotated boxes covering about ``0.3 strength`` of the image, darkened by ``0.3 + 0.4 strength``.

    The boxes (5 to 40 pixels long, all at one sun angle) are drawn until they cover the target share; their union
    gets a penumbra of about 1.5 pixels.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: in ``[0, 1]``.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    if strength == 0:
        return _finish(values, image, value_range)
    generator = _generator(seed)
    height, width = values.shape
    rows, cols = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    angle = _uniform(generator, 0.0, math.pi)
    cover = torch.zeros_like(values)
    target = 0.3 * strength
    for _ in range(1000):
        if float(cover.mean()) >= target:
            break
        centre = (_uniform(generator, -10, height + 10), _uniform(generator, -10, width + 10))
        box = _box(rows, cols, centre, _uniform(generator, 2.5, 20), _uniform(generator, 2, 8), angle)
        cover = torch.maximum(cover, box)
    cover = _blur(cover, 1.0, 1.0)
    return _finish(values * (1 - (0.3 + 0.4 * strength) * cover), image, value_range)


@functools.cache
def _source(name: str) -> Tensor:
    from skimage import color, data

    picture = getattr(data, name)()
    if picture.ndim == 3:
        picture = color.rgb2gray(picture[..., :3]) * 255
    return torch.from_numpy(np.asarray(picture, dtype=np.float64))


def _texture(generator: torch.Generator, shape: tuple[int, int]) -> Tensor:
    """A crop of a random other photograph, tiled by reflection when the image is larger, re-toned at random."""
    source = _source(SOURCES[int(torch.randint(len(SOURCES), (), generator=generator))])
    height, width = shape
    top = _uniform(generator, 0, source.shape[0] - 1)
    left = _uniform(generator, 0, source.shape[1] - 1)
    rows = top + torch.arange(height, dtype=torch.float64)[:, None].expand(shape)
    cols = left + torch.arange(width, dtype=torch.float64)[None].expand(shape)
    # Reflect the coordinates into the source ourselves: grid_sample reflects once only.
    period_rows, period_cols = 2 * (source.shape[0] - 1), 2 * (source.shape[1] - 1)
    rows = (source.shape[0] - 1) - ((rows % period_rows) - (source.shape[0] - 1)).abs()
    cols = (source.shape[1] - 1) - ((cols % period_cols) - (source.shape[1] - 1)).abs()
    crop = _sample(source, rows, cols)
    # Occluders are bright or dark whatever the photograph's mean: keep part of its contrast around a random level.
    return _uniform(generator, 20, 235) + _uniform(generator, 0.4, 1.0) * (crop - crop.mean())


def occluders(image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)) -> Tensor:
    """Cars and trees pasted over the scene: about ``0.4 strength`` of the image covered by other photographs.

    Cars are rotated boxes (8 to 20 by 4 to 8 pixels), trees ragged blobs (radius 4 to 12 pixels), half and half;
    each takes the texture of a random crop of another photograph (see :data:`SOURCES`) around a random grey level,
    with a one-pixel soft edge. Occluders are drawn until they cover the target share.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: in ``[0, 1]``.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    if strength == 0:
        return _finish(values, image, value_range)
    generator = _generator(seed)
    height, width = values.shape
    rows, cols = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    cover = torch.zeros_like(values)
    changed = values.clone()
    target = 0.4 * strength
    for _ in range(1000):
        if float(cover.mean()) >= target:
            break
        centre = (_uniform(generator, -4, height + 4), _uniform(generator, -4, width + 4))
        if float(torch.rand((), generator=generator)) < 0.5:
            angle = _uniform(generator, 0, math.pi)
            alpha = _box(rows, cols, centre, _uniform(generator, 4, 10), _uniform(generator, 2, 4), angle)
        else:
            radius = _uniform(generator, 4, 12)
            ragged = 1 + 0.25 * smooth_field(values.shape, max(2.0, radius / 2), generator)
            distance = ((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2).sqrt()
            alpha = (radius * ragged - distance + 0.5).clamp(0, 1)
        if not bool(alpha.any()):
            continue
        changed = changed + alpha * (_texture(generator, values.shape) - changed)
        cover = torch.maximum(cover, alpha)
    return _finish(changed, image, value_range)


def _tone_curve(generator: torch.Generator, value_range: tuple[float, float], knots: int = 6) -> Tensor:
    """Knot values of a random tone curve: ``knots`` levels drawn uniformly in the range (any order)."""
    low, high = value_range
    return low + (high - low) * torch.rand(knots, generator=generator, dtype=torch.float64)


def _apply_curve(values: Tensor, levels: Tensor, value_range: tuple[float, float]) -> Tensor:
    """The Catmull-Rom spline through ``levels`` at equally spaced inputs over the range, evaluated at ``values``."""
    low, high = value_range
    position = ((values - low) / (high - low)).clamp(0, 1) * (levels.shape[0] - 1)
    index = position.floor().clamp(max=levels.shape[0] - 2).long()
    t = position - index
    padded = torch.cat([2 * levels[:1] - levels[1:2], levels, 2 * levels[-1:] - levels[-2:-1]])
    p0, p1, p2, p3 = (padded[index + shift] for shift in range(4))
    return 0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (3 * p1 - p0 - 3 * p2 + p3) * t**3)


def tone(image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)) -> Tensor:
    """Seasonal tone change: ``(1 - s) v + s g(v)``, ``g`` two random tone curves blended by a smooth field.

    Each curve is a Catmull-Rom spline through six levels drawn uniformly in ``value_range`` (non-linear, often
    non-monotonic); a sigmoid of a field about 32 pixels wide picks between them, so that the change depends on where
    a pixel lies as well as on its grey level.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: ``s`` in ``[0, 1]``.
        value_range: ``(low, high)`` of the tone curves; the result is clipped to it.

    Returns:
        The changed image, same shape and dtype.
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    generator = _generator(seed)
    first, second = _tone_curve(generator, value_range), _tone_curve(generator, value_range)
    blend = torch.sigmoid(2.5 * smooth_field(values.shape, 32.0, generator))
    toned = blend * _apply_curve(values, first, value_range) + (1 - blend) * _apply_curve(values, second, value_range)
    return _finish((1 - strength) * values + strength * toned, image, value_range)


def resample_blur(
    image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)
) -> Tensor:
    """Another sensor's resolution: an anisotropic blur, then resampling ``1 + strength`` times coarser and back.

    The blur's standard deviations are ``1.5 strength`` times a random factor in ``[0.5, 1]`` per axis; the coarse
    grid has a random phase (up to ``(1 + strength) strength`` pixels), and the image comes back to its own grid by
    bilinear interpolation.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: in ``[0, 1]``.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    if strength == 0:
        return _finish(values, image, value_range)
    generator = _generator(seed)
    sigma_rows = 1.5 * strength * _uniform(generator, 0.5, 1.0)
    sigma_cols = 1.5 * strength * _uniform(generator, 0.5, 1.0)
    factor = 1 + strength
    blurred = _blur(values, math.hypot(sigma_rows, 0.5 * (factor - 1)), math.hypot(sigma_cols, 0.5 * (factor - 1)))
    height, width = values.shape
    # The grid's phase spreads with the strength, so that a weak change stays close to the image.
    phase = (_uniform(generator, 0, factor * strength), _uniform(generator, 0, factor * strength))
    coarse_rows = torch.arange(phase[0] - factor, height + factor, factor, dtype=torch.float64)
    coarse_cols = torch.arange(phase[1] - factor, width + factor, factor, dtype=torch.float64)
    coarse = _sample(blurred, *torch.meshgrid(coarse_rows, coarse_cols, indexing="ij"))
    # Back on the image's grid: coarse index of pixel y is (y - first coarse row) / factor.
    rows = (torch.arange(height, dtype=torch.float64) - coarse_rows[0]) / factor
    cols = (torch.arange(width, dtype=torch.float64) - coarse_cols[0]) / factor
    return _finish(_sample(coarse, *torch.meshgrid(rows, cols, indexing="ij")), image, value_range)


def warp(image: Tensor, seed: int, strength: float, *, value_range: tuple[float, float] = (0.0, 255.0)) -> Tensor:
    """Small parallax or elastic warp: each pixel moved by a smooth field of standard deviation ``1.2 strength`` px.

    The displacement field (one per axis, about 16 pixels wide) has mean 0 over the image: no net shift.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the change's random draws.
        strength: in ``[0, 1]``.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.
    """
    values, strength, value_range = _check(image, seed, strength, value_range)
    if strength == 0:
        return _finish(values, image, value_range)
    generator = _generator(seed)
    height, width = values.shape
    row_shift = 1.2 * strength * smooth_field(values.shape, 16.0, generator)
    col_shift = 1.2 * strength * smooth_field(values.shape, 16.0, generator)
    rows = torch.arange(height, dtype=torch.float64)[:, None] + row_shift
    cols = torch.arange(width, dtype=torch.float64)[None] + col_shift
    return _finish(_sample(values, rows, cols), image, value_range)


CHANGES: dict[str, Callable[..., Tensor]] = {
    "warp": warp,
    "occluders": occluders,
    "tone": tone,
    "shadows": shadows,
    "illumination": illumination,
    "resample_blur": resample_blur,
}
"""The changes by name, in the order :func:`scene_change` applies them (the scene, then the light, then the sensor)."""


def scene_change(
    image: Tensor,
    seed: int,
    strength: float,
    *,
    kinds: Sequence[str] = tuple(CHANGES),
    value_range: tuple[float, float] = (0.0, 255.0),
) -> Tensor:
    """Several changes composed, each at ``strength`` with its own seed drawn from ``seed``, in :data:`CHANGES` order.

    Args:
        image: grey levels ``(H, W)``, floating point.
        seed: the changes' random draws.
        strength: in ``[0, 1]``, for every change.
        kinds: names from :data:`CHANGES` (all by default), applied in :data:`CHANGES` order whatever the order given.
        value_range: ``(low, high)`` the result is clipped to.

    Returns:
        The changed image, same shape and dtype.

    Example:
        >>> image = torch.arange(48.0).reshape(6, 8) * 5
        >>> changed = scene_change(image, 0, 0.5, kinds=["tone", "illumination"])
        >>> changed.shape, bool(torch.equal(changed, scene_change(image, 0, 0.5, kinds=["illumination", "tone"])))
        (torch.Size([6, 8]), True)
    """
    _check(image, seed, strength, value_range)
    if isinstance(kinds, str):
        raise TypeError(f"kinds must be a sequence of names from {list(CHANGES)}, got the string {kinds!r}")
    chosen = {check_option("kinds", kind, tuple(CHANGES)) for kind in kinds}
    changed = image
    for index, (name, change) in enumerate(CHANGES.items()):
        if name in chosen:
            # One seed per change, spread so that neighbouring seeds share no stream.
            changed = change(changed, (seed * len(CHANGES) + index) * 7919 + 17, strength, value_range=value_range)
    return changed
