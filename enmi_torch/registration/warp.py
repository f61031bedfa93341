"""Where the captured pixels lie on the map at a pose, and the map under them: positions, samples, which count.

:func:`warp_reference` samples the map under captured images at continuous poses (a cubic B-spline by default,
:mod:`~enmi_torch.registration.interpolation`); :class:`PreparedMap` is the same map prepared once for many poses
(its unobserved cells filled, its spline prefiltered), as :func:`~enmi_torch.registration.register`'s stages use it;
the Gaussian blur of a stage is here too.

Convention:
    A pose is ``(x, y, yaw)`` in map cells and degrees, absolute: ``x`` (column) and ``y`` (row, down) the map
    position of the captured image's pixel ``(h // 2, w // 2)``, ``yaw`` counter-clockwise as displayed; the captured
    pixel ``(u, v)`` (column, row) shows the map at :meth:`~enmi_torch.Localization.local_to_map` of that pose: the
    captured image turned about its centre ``((w - 1) / 2, (h - 1) / 2)``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from enmi_torch.registration.interpolation import INTERPOLATIONS, MapSampler, fill_unobserved
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import check_image_shape, check_map, check_margin, check_mask_of, check_option, check_pose

# Cells around a sample's nearest cell that its value leans on: the bilinear taps; the B-spline's 4 x 4 taps and one
# cell more for its prefilter, which spreads each cell over its neighbours (by 0.27 at one cell, 0.07 at two).
REACH = {"bilinear": 1, "bspline": 3}
WARP_BYTES_PER_ITEM = 40  # per sample: positions, weights and slopes per axis, the 16 taps' index and values


def sample_positions(pose: Tensor, shape: tuple[int, int]) -> Tensor:
    """``(B, h, w, 2)`` map positions ``(x, y)`` of every captured pixel at ``pose`` ``(B, 3)`` (differentiable)."""
    height, width = shape
    dtype, device = pose.dtype, pose.device
    rows = torch.arange(height, dtype=dtype, device=device) - (height - 1) / 2
    cols = torch.arange(width, dtype=dtype, device=device) - (width - 1) / 2
    angle = torch.deg2rad(-pose[:, 2])[:, None, None]
    cos, sin = angle.cos(), angle.sin()
    offset_x = pose[:, 0, None, None] + (width - 1) / 2 - width // 2
    offset_y = pose[:, 1, None, None] + (height - 1) / 2 - height // 2
    x = cos * cols[None, None, :] + sin * rows[None, :, None] + offset_x
    y = -sin * cols[None, None, :] + cos * rows[None, :, None] + offset_y
    return torch.stack([x, y], -1)


def yaw_motion(pose: Tensor, shape: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """``(B, h, w)`` each: how far every captured pixel's map ``x`` and ``y`` move per degree of yaw at ``pose``."""
    height, width = shape
    rows = torch.arange(height, dtype=pose.dtype, device=pose.device) - (height - 1) / 2
    cols = torch.arange(width, dtype=pose.dtype, device=pose.device) - (width - 1) / 2
    angle = torch.deg2rad(-pose[:, 2])[:, None, None]
    cos, sin = angle.cos(), angle.sin()
    per_degree = -math.pi / 180
    x_per_yaw = (-sin * cols[None, None, :] + cos * rows[None, :, None]) * per_degree
    y_per_yaw = (-cos * cols[None, None, :] - sin * rows[None, :, None]) * per_degree
    return x_per_yaw, y_per_yaw


def warp_reference(
    reference: Tensor,
    pose: Tensor,
    shape: tuple[int, int],
    reference_mask: Tensor | None = None,
    margin: float = 0.0,
    interpolation: str = "bspline",
) -> tuple[Tensor, Tensor]:
    """The map under captured images of ``shape`` at ``pose``: its samples and where they count.

    Args:
        reference: ``(1 or B, 1, Hm, Wm)`` map, real floating point; NaN or inf cells count as unobserved.
        pose: ``(B, 3)`` finite floating ``(x, y, yaw)`` (see the module's convention); the samples are
            differentiable in it.
        shape: ``(h, w)`` of the captured images, two positive ints.
        reference_mask: optional bool map ``(1 or B, 1, Hm, Wm)`` or ``(Hm, Wm)``, the map's size: ``False`` cells are
            unobserved.
        margin: cells ``>= 0`` a sample must keep from the map's border.
        interpolation: ``"bspline"`` (the cubic B-spline through the map's cells, mirrored beyond its border) or
            ``"bilinear"`` (:mod:`~enmi_torch.registration.interpolation` says which models what).

    Returns:
        ``(warped, valid)``: ``(B, 1, h, w)`` samples in ``pose``'s dtype (0 off the map and on non-finite cells) and
        bool ``(B, 1, h, w)``: the sample lies on the map, ``margin`` cells inside its border, and every map cell it
        leans on is observed (the 2 x 2 cells around it, bilinear; the 4 x 4 and one more cell around, B-spline).
        Unobserved cells are filled with the mean of the observed ones nearest them before the spline is fitted.

    Raises:
        TypeError, ValueError: naming the argument that is not as above.
        MemoryBudgetError: when the ``B x h x w`` samples would exceed the memory budget (nothing is allocated).

    Example:
        >>> reference = torch.arange(20.0).reshape(1, 1, 4, 5)
        >>> on_cells, valid = warp_reference(reference, torch.tensor([[2.0, 1.0, 0.0]]), (1, 2))
        >>> on_cells.flatten().round(decimals=4).tolist(), valid.flatten().tolist()  # pixel (0, 1) on cell (2, 1)
        ([6.0, 7.0], [True, True])
        >>> pose = torch.tensor([[2.5, 1.0, 0.0]])  # half a cell right
        >>> warp_reference(reference, pose, (1, 2), interpolation="bilinear")[0].flatten().tolist()
        [6.5, 7.5]
    """
    pose = check_pose("pose", pose)
    reference = check_map("reference", reference, pose.shape[0], "pose", pose)
    shape = check_image_shape("shape", shape)
    if reference_mask is not None:
        reference_mask = check_mask_of("reference_mask", reference_mask, "reference", reference)
    margin = check_margin("margin", margin)
    check_option("interpolation", interpolation, INTERPOLATIONS)
    check_warp_memory(pose.shape[0], shape, pose.element_size())
    check_map_memory(reference, interpolation, pose.element_size())
    prepared = PreparedMap(reference.to(pose.dtype), reference_mask, interpolation)
    warped, valid, _ = prepared.warp(pose, shape, margin)
    return warped, valid


def check_warp_memory(batch: int, shape: tuple[int, int], item_size: int) -> None:
    """Refuse ``batch`` warps of ``shape`` whose positions, taps and samples would exceed the memory budget."""
    check_cells_memory(
        f"shape={shape}",
        batch * shape[0] * shape[1],
        WARP_BYTES_PER_ITEM * item_size,
        f"the map positions, taps and samples of {batch} image(s) of {shape[0]} x {shape[1]}",
        "pass the captured images' own (h, w)",
    )


def check_map_memory(reference: Tensor, interpolation: str, item_size: int) -> None:
    """Refuse a map whose prepared table would exceed the memory budget.

    The table holds the polynomial of every cell; the B-spline's prefilter the mirrored map's spectrum besides.
    """
    maps, _, height, width = reference.shape
    taps = 4 if interpolation == "bspline" else 2
    # Per cell: taps^2 coefficients (and their padded and correlated copies), the mirrored map's complex spectrum.
    per_cell = (3 * taps * taps + (16 if interpolation == "bspline" else 0)) * item_size
    check_cells_memory(
        f"interpolation={interpolation!r}",
        maps * height * width,
        per_cell,
        f"the {interpolation} table of {maps} map(s) of {height} x {width} cells",
        "crop the map to the region the captured images can reach",
    )


class PreparedMap:
    """A map ready to be sampled at many poses: its unobserved cells filled, its spline prefiltered.

    Args:
        reference: ``(1 or B, 1, Hm, Wm)`` map in the compute dtype; NaN or inf cells are unobserved.
        reference_mask: optional bool, broadcastable to ``reference``: ``False`` cells are unobserved.
        interpolation: one of :data:`~enmi_torch.registration.interpolation.INTERPOLATIONS`.
    """

    def __init__(self, reference: Tensor, reference_mask: Tensor | None, interpolation: str) -> None:
        self.shape = reference.shape[-2:]
        observed = torch.isfinite(reference)
        if reference_mask is not None:
            observed = observed & reference_mask.reshape(-1, 1, *self.shape)
        values = torch.where(observed, reference, 0.0)
        self.near_unobserved = None
        if not bool(observed.all()):
            values = fill_unobserved(values, observed.expand_as(values))
            radius = REACH[interpolation]
            unobserved = (~observed).to(values.dtype).expand(values.shape[0], -1, -1, -1)
            self.near_unobserved = F.max_pool2d(unobserved, 2 * radius + 1, 1, radius)
        self.sampler = MapSampler(values, interpolation)

    def warp(
        self,
        pose: Tensor,
        shape: tuple[int, int],
        margin: float | None,
        gradient: bool = False,
        rows: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """Samples ``(B, 1, h, w)`` at ``pose``, where they count, and if asked their gradient ``(B, 1, h, w, 2)``.

        Where they count is bool, ``None`` if ``margin`` is ``None``; the gradient is in the map position ``(x, y)``.
        ``rows``: ``(B,)`` the images ``pose`` is of, when they are some of the images the map was prepared for.
        """
        positions = sample_positions(pose, shape)
        values, slopes = self.sampler.sample(positions, gradient, rows)
        valid = None
        if margin is not None:
            height, width = self.shape
            x, y = positions.detach().unbind(-1)
            valid = (x >= margin) & (x <= width - 1 - margin) & (y >= margin) & (y <= height - 1 - margin)
            if self.near_unobserved is not None:
                near = self.near_unobserved
                if rows is not None and near.shape[0] > 1:
                    near = near[rows]
                valid = valid & (_nearest(near, positions.detach()) <= 0)
            valid = valid[:, None]
        return values[:, None], valid, None if slopes is None else slopes[:, None]


def _nearest(table: Tensor, positions: Tensor) -> Tensor:
    """Nearest-cell values ``(B, h, w)`` of ``table`` ``(1 or B, 1, Hm, Wm)`` at positions ``(B, h, w, 2)`` on it."""
    height, width = table.shape[-2:]
    scale = torch.tensor([max(width - 1, 1), max(height - 1, 1)], dtype=positions.dtype, device=positions.device)
    expanded = table.to(positions.dtype).expand(positions.shape[0], -1, -1, -1)
    grid = positions / scale * 2 - 1
    return F.grid_sample(expanded, grid, mode="nearest", padding_mode="border", align_corners=True)[:, 0]


def blur_radius(sigma: float) -> int:
    """Cells of a Gaussian blur's kernel on each side of its centre: three standard deviations, at least one."""
    return max(1, math.ceil(3 * sigma))


def gaussian_taps(sigma: float, like: Tensor) -> Tensor:
    """The normalised 1-D Gaussian kernel of standard deviation ``sigma``, ``2 r + 1`` taps (:func:`blur_radius`)."""
    radius = blur_radius(sigma)
    offsets = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    return kernel / kernel.sum()


def separable(images: Tensor, kernel: Tensor) -> Tensor:
    """``images`` ``(..., H, W)`` convolved with a symmetric ``kernel`` along rows and columns, zero beyond the border.

    Shifted slices, the mirror taps paired: a few-tap kernel costs a few passes over the images (a convolution call
    would unfold them first).
    """
    radius = (kernel.numel() - 1) // 2
    height, width = images.shape[-2:]
    padded = F.pad(images, (radius, radius, 0, 0))
    rows = padded[..., radius : radius + width] * kernel[radius]
    for offset in range(1, radius + 1):
        rows = torch.addcmul(
            rows,
            padded[..., radius - offset : radius - offset + width]
            + padded[..., radius + offset : radius + offset + width],
            kernel[radius + offset],
        )
    padded = F.pad(rows, (0, 0, radius, radius))
    values = padded[..., radius : radius + height, :] * kernel[radius]
    for offset in range(1, radius + 1):
        pair = (
            padded[..., radius - offset : radius - offset + height, :]
            + padded[..., radius + offset : radius + offset + height, :]
        )
        values = torch.addcmul(values, pair, kernel[radius + offset])
    return values
