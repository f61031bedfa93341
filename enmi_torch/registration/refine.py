"""Continuous pose refinement: the pose ``(x, y, yaw)`` of captured images in a map by Gauss-Newton through a score.

:func:`localize` finds the best integer shift and yaw bin; :func:`register` moves on from there (or from any pose) to
the continuous pose that maximises the score, batched. The map is sampled under the captured image at the pose
(:func:`warp_reference`, bilinear, differentiable in the pose), so the noisy captured image, its variance and its mask
are never resampled. The score is a weighted least-squares fit of the captured values by a response of the map's
values, the likelihood behind ECR (:class:`~enmi_torch.ECR`):

* ECR, ``response="binned"``: a piecewise-linear response with one knot per bin centre over ``value_range`` (the
  binned response made continuous in the map's values, so the score is smooth in the pose), each pixel weighed by
  ``1 / (sigma_n^2 + tau^2)``, ``tau^2`` the ECR estimate at the starting pose (or the fixed ``model_variance``);
* ECR, ``response="shrunk"`` (the default): the same piecewise-linear response, its knots pulled toward a line by a
  penalty ``|| (I - P) theta ||^2 / delta^2`` (``P`` the projection of the knot values onto lines in the knots'
  positions), ``delta^2`` the shrunk response's choice at the starting pose
  (:mod:`~enmi_torch.scores.shrunk_response`): the posterior mean of the bin means under its model;
* ECR, ``response="linear"``: ``a + b m``, the same weights;
* NCC (:class:`~enmi_torch.NCC`): ``a + b m``, every pixel alike.

The response is profiled out (refitted at every pose) and the pose moves by Levenberg-Marquardt steps on the
Gauss-Newton normal equations (Kaufman's approximation of the variable-projection Jacobian). Histogram scores (NMI,
ENMI, the mixture) are not least-squares fits and are refused.

Pixels whose map sample at the starting pose lies within ``margin`` cells of the map's border, off the map or on an
invalid map cell do not count, nor do the captured image's invalid pixels; the set is held fixed while the pose moves
(a score whose pixel set changed with the pose would jump), so a move of more than ``margin`` cells ends the
refinement of that image (``Registration.converged`` is ``False``).

Convention:
    A pose is ``(x, y, yaw)`` as everywhere in the library: ``x`` (column) and ``y`` (row, down) the map position of
    the captured image's pixel ``(h // 2, w // 2)``, absolute; ``yaw`` in degrees, counter-clockwise as displayed:
    :func:`~enmi_torch.localize`'s ``pose`` and what :meth:`~enmi_torch.Tracker.start` takes. The captured pixel
    ``(u, v)`` shows the map at :meth:`~enmi_torch.Localization.local_to_map` of that pose.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from enmi_torch.registration.response_fit import ResponseFit
from enmi_torch.scores import Score, as_score
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import (
    check_floating,
    check_image_shape,
    check_map,
    check_margin,
    check_mask_of,
    check_not_empty,
    check_pose,
    check_positive_int,
    check_positive_number,
    check_real_data,
    check_variance_given,
)
from enmi_torch.utils.layout import variance_map
from enmi_torch.variance.base import VarianceModel


class Registration(NamedTuple):
    """The result of :func:`register`.

    Attributes:
        pose: ``(B, 3)`` refined ``(x, y, yaw)``: map column and row of the captured centre pixel, yaw in degrees.
        score: ``(B,)`` the fit's log-likelihood ratio per valid pixel at ``pose`` (half the weighted residual sum of
            squares the response removes, over the valid pixels; larger is better).
        converged: ``(B,)`` bool: the last step moved less than ``tolerance`` (cells, and degrees for the yaw), or
            the fit stopped improving, without leaving the pixels fixed at the start. A result that scores below the
            start (a blurred stage led astray) is replaced by the start, not converged.
        iterations: ``(B,)`` int64 steps taken.
    """

    pose: Tensor
    score: Tensor
    converged: Tensor
    iterations: Tensor


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


def warp_reference(
    reference: Tensor, pose: Tensor, shape: tuple[int, int], reference_mask: Tensor | None = None, margin: float = 0.0
) -> tuple[Tensor, Tensor]:
    """The map under captured images of ``shape`` at ``pose``: bilinear samples and where they count.

    Args:
        reference: ``(1 or B, 1, Hm, Wm)`` map, real floating point; NaN or inf cells count as unobserved.
        pose: ``(B, 3)`` finite floating ``(x, y, yaw)`` (see the module's convention); the samples are
            differentiable in it.
        shape: ``(h, w)`` of the captured images, two positive ints.
        reference_mask: optional bool map ``(1 or B, 1, Hm, Wm)`` or ``(Hm, Wm)``, the map's size: ``False`` cells are
            unobserved.
        margin: cells ``>= 0`` a sample must keep from the map's border.

    Returns:
        ``(warped, valid)``: ``(B, 1, h, w)`` samples (0 off the map and on non-finite cells) and bool
        ``(B, 1, h, w)``: the sample lies on the map, ``margin`` cells inside its border, and its four neighbouring
        cells are observed.

    Raises:
        TypeError, ValueError: naming the argument that is not as above.
        MemoryBudgetError: when the ``B x h x w`` samples would exceed the memory budget (nothing is allocated).

    Example:
        >>> reference = torch.arange(20.0).reshape(1, 1, 4, 5)
        >>> warped, valid = warp_reference(reference, torch.tensor([[2.5, 1.0, 0.0]]), (1, 2))
        >>> warped.flatten().tolist(), valid.flatten().tolist()  # centre pixel (0, 1) on column 2.5 of row 1
        ([6.5, 7.5], [True, True])
    """
    pose = check_pose("pose", pose)
    reference = check_map("reference", reference, pose.shape[0], "pose", pose)
    shape = check_image_shape("shape", shape)
    if reference_mask is not None:
        reference_mask = check_mask_of("reference_mask", reference_mask, "reference", reference)
    margin = check_margin("margin", margin)
    check_cells_memory(
        f"shape={shape}",
        pose.shape[0] * shape[0] * shape[1],
        WARP_BYTES_PER_ITEM * pose.element_size() + 2,
        f"the map positions, samples and masks of {pose.shape[0]} image(s) of {shape[0]} x {shape[1]}",
        "pass the captured images' own (h, w)",
    )
    return _warp(reference, pose, shape, reference_mask, margin)


WARP_BYTES_PER_ITEM = 8  # per sample: positions (x, y), their normalised copy, the sample, the mask taps


def _warp(
    reference: Tensor, pose: Tensor, shape: tuple[int, int], reference_mask: Tensor | None, margin: float
) -> tuple[Tensor, Tensor]:
    """:func:`warp_reference` on checked inputs; NaN or inf map cells count as unobserved (and sample as 0)."""
    height, width = reference.shape[-2:]
    positions = sample_positions(pose, shape)
    finite = torch.isfinite(reference)
    unobserved = None if reference_mask is None else ~reference_mask
    if not bool(finite.all()):
        reference = torch.where(finite, reference, 0.0)
        unobserved = ~finite if unobserved is None else unobserved | ~finite
    warped = _sample(reference.to(pose.dtype), positions)
    x, y = positions.detach().unbind(-1)
    valid = (x >= margin) & (x <= width - 1 - margin) & (y >= margin) & (y <= height - 1 - margin)
    if unobserved is not None:
        # A cell the bilinear sample leans on at all (weight > 0) must be observed: each lies within the 3 x 3 cells
        # around the nearest one.
        near_unobserved = F.max_pool2d(unobserved.to(pose.dtype), 3, 1, 1)
        near = _sample(near_unobserved, positions.detach(), mode="nearest")
        valid = valid & (near[:, 0] <= 0)
    return warped, valid[:, None]


def _sample(reference: Tensor, positions: Tensor, mode: str = "bilinear") -> Tensor:
    """Bilinear (or nearest) samples ``(B, 1, h, w)`` of a map ``(1 or B, 1, Hm, Wm)`` at positions ``(B, h, w, 2)``.

    Positions are map ``(x, y)`` in cells; a sample off the map is 0.
    """
    height, width = reference.shape[-2:]
    scale = torch.tensor([max(width - 1, 1), max(height - 1, 1)], dtype=positions.dtype, device=positions.device)
    expanded = reference.expand(positions.shape[0], -1, -1, -1) if reference.shape[0] == 1 else reference
    return F.grid_sample(expanded, positions / scale * 2 - 1, mode=mode, padding_mode="zeros", align_corners=True)


def check_registration_score(score: Score | str) -> Score:
    """``score`` as a :class:`~enmi_torch.scores.Score` that :func:`register` can fit (ECR or NCC), else ValueError."""
    score = as_score(score)
    score.require("least_squares", "register")  # a weighted least-squares fit, smooth in the pose
    return score


class _Inputs(NamedTuple):
    """Checked inputs of :func:`register` and :func:`registration_score`."""

    captured: Tensor
    reference: Tensor
    variance: Tensor | None  # (B, 1, h, w) in captured's dtype, 1 where a pixel does not count
    captured_mask: Tensor | None  # bool (1 or B, 1, h, w)
    reference_mask: Tensor | None  # bool (1 or B, 1, Hm, Wm)
    pose: Tensor


def _prepare(captured, reference, variance, captured_mask, reference_mask, score: Score, pose) -> _Inputs:
    """Every input by name (shapes, dtypes, devices, finite values, masks the size of what they mask); the budget."""
    check_floating("captured", captured)
    check_real_data("captured", captured)
    if captured.ndim != 4 or captured.shape[1] != 1:
        raise ValueError(f"captured must have shape (B, 1, h, w), got {tuple(captured.shape)}")
    check_not_empty("captured", captured)
    batch = captured.shape[0]
    reference = check_map("reference", reference, batch, "captured", captured)
    pose = check_pose("pose", pose, batch)
    if pose.device != captured.device:
        raise ValueError(f"pose must be on the device of captured ({captured.device}), got {pose.device}")
    if captured_mask is not None:
        captured_mask = check_mask_of("captured_mask", captured_mask, "captured", captured)
    if reference_mask is not None:
        reference_mask = check_mask_of("reference_mask", reference_mask, "reference", reference)
    if isinstance(variance, VarianceModel):
        model_mask = variance.valid_mask(captured)
        variance = variance(captured)
        if model_mask is not None:
            captured_mask = model_mask if captured_mask is None else captured_mask & model_mask
    if score.uses_variance:
        check_variance_given(variance)
        check_same_device_of("variance", variance, captured)
        valid = None if captured_mask is None else captured_mask.expand_as(captured).flatten(1)
        variance = variance_map("variance", variance, captured, captured.dtype, valid).view_as(captured)
    elif variance is not None:
        raise ValueError(f"variance is not used by score {score.name!r}; pass None")
    size = score.response_basis().size
    check_cells_memory(
        f"bins={size}" if size > 2 else "score",
        (4 * batch + 3) * size * size,  # the normal equations; the shrunk response's pull toward a line
        8,
        f"the normal equations ({batch}, {size}, {size}) of the fitted response in float64",
        "lower the score's bins",
    )
    return _Inputs(captured, reference, variance, captured_mask, reference_mask, pose)


def check_same_device_of(name: str, value, captured: Tensor) -> None:
    """A tensor ``value`` must hold data on the device of ``captured`` (a number is fine)."""
    if isinstance(value, Tensor):
        check_real_data(name, value)
        if value.device != captured.device:
            raise ValueError(f"{name} must be on the device of captured ({captured.device}), got {value.device}")


def _check_counting(valid: Tensor, pose: Tensor, map_shape, margin: float, masked: bool) -> None:
    """Raise ``ValueError`` naming the pose if a sample has no pixel that counts at ``pose``."""
    empty = ~valid.flatten(1).any(1)
    if bool(empty.any()):
        samples = empty.nonzero()[:, 0].tolist()
        raise ValueError(
            f"no captured pixel counts at pose {pose[samples[0]].tolist()} (sample(s) {samples}): its samples of the "
            f"{map_shape[0]} x {map_shape[1]} map all lie off the map, within margin={margin} cells of its border or "
            "by unobserved cells (reference_mask, NaN cells)"
            + (", or are masked out by captured_mask" if masked else "")
            + "; start from a pose on the map"
        )


def registration_score(
    captured: Tensor,
    reference: Tensor,
    pose: Tensor,
    variance: Tensor | float | None = None,
    *,
    score: Score | str = "ecr",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    margin: float = 0.0,
) -> Tensor:
    """The score :func:`register` maximises, ``(B,)``, at ``pose`` ``(B, 3)``; differentiable in ``pose``.

    The weights (``tau^2`` for ECR) and the pixels that count are read at ``pose`` itself, without gradient; the
    response is refitted. Arguments as :func:`register`'s.

    Example:
        >>> from enmi_torch import ECR
        >>> reference = torch.rand(1, 1, 40, 40, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 255
        >>> truth = torch.tensor([[20.3, 19.6, 4.0]], dtype=torch.float64)
        >>> captured = warp_reference(reference, truth, (16, 16))[0]
        >>> pose = truth + torch.tensor([[0.2, 0.0, 0.0]], dtype=torch.float64)
        >>> score = registration_score(captured, reference, pose, 1.0, score=ECR(model_variance=1.0))
        >>> bool(score < registration_score(captured, reference, truth, 1.0, score=ECR(model_variance=1.0)))
        True
    """
    score = check_registration_score(score)
    inputs = _prepare(captured, reference, variance, captured_mask, reference_mask, score, pose)
    margin = check_margin("margin", margin)
    captured, reference, variance, captured_mask, reference_mask, pose = inputs
    warped, valid = _warp(reference, pose, tuple(captured.shape[-2:]), reference_mask, margin)
    if captured_mask is not None:
        valid = valid & captured_mask.expand_as(valid)
    _check_counting(valid, pose, reference.shape[-2:], margin, captured_mask is not None)
    values = captured.to(pose.dtype)
    fit = ResponseFit.of(score, values, warped, variance, valid)
    batch = captured.shape[0]
    return fit.solve(values.reshape(batch, -1), warped.reshape(batch, -1))[2]


def register(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    *,
    pose: Tensor,
    score: Score | str = "ecr",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    blur: tuple[float, ...] = (1.0, 0.0),
    iterations: int = 30,
    tolerance: float = 1e-4,
    margin: float = 2.0,
) -> Registration:
    """Refine the pose of captured images in a map by Gauss-Newton through a least-squares score, batched.

    Args:
        captured: ``(B, 1, h, w)`` captured images on the map's cell grid.
        reference: ``(1 or B, 1, Hm, Wm)`` the map (one for all, or one per image).
        variance: the captured images' noise variance for ECR (a number, ``(h, w)``, ``(1 or B, 1, h, w)`` or a
            :class:`~enmi_torch.variance.VarianceModel`); ``None`` for NCC.
        pose: ``(B, 3)`` starting ``(x, y, yaw)``, absolute in the map (the module's convention), e.g.
            :func:`~enmi_torch.localize`'s ``pose`` unchanged.
        score: :class:`~enmi_torch.ECR` (its bins, value range, model variance and response) or
            :class:`~enmi_torch.NCC`, or the name of either.
        captured_mask: bool like ``variance``: ``False`` pixels do not count.
        reference_mask: bool ``(1 or B, 1, Hm, Wm)``: ``False`` map cells are unobserved.
        blur: the multi-resolution schedule: Gaussian standard deviations (cells) of the map and the captured images
            for each stage, coarse to fine (0: none). A blurred stage widens the basin of attraction.
        iterations: Levenberg-Marquardt steps per stage at most.
        tolerance: a step smaller than this (cells and degrees) ends a stage.
        margin: cells a counting pixel's map sample keeps from the map's border and from unobserved cells at the
            stage's start; a larger move ends the refinement.

    Returns:
        :class:`Registration` (``pose``, ``score``, ``converged``, ``iterations``).

    Raises:
        TypeError, ValueError: naming the argument (shapes, dtypes, devices, finite values, masks the size of what
            they mask, a pose where no pixel counts).
        MemoryBudgetError: when the score's normal equations (``ECR(bins=...)``) or the blur's taps would exceed the
            memory budget, before anything is allocated.

    Example:
        >>> from enmi_torch import ECR
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = F.avg_pool2d(torch.rand(1, 1, 80, 80, generator=generator, dtype=torch.float64), 3, 1) * 255
        >>> truth = torch.tensor([[39.3, 40.6, 2.5]], dtype=torch.float64)
        >>> captured = warp_reference(reference, truth, (32, 32))[0]
        >>> start = torch.tensor([[39.0, 41.0, 2.0]], dtype=torch.float64)  # e.g. localize's pose
        >>> found = register(captured, reference, 1.0, pose=start, score=ECR(bins=16))
        >>> found.pose.round(decimals=3).tolist(), bool(found.converged)
        ([[39.3, 40.6, 2.5]], True)
    """
    score = check_registration_score(score)
    inputs = _prepare(captured, reference, variance, captured_mask, reference_mask, score, pose)
    captured, reference, variance, captured_mask, reference_mask, pose = inputs
    iterations = check_positive_int("iterations", iterations)
    tolerance = check_positive_number("tolerance", tolerance)
    margin = check_margin("margin", margin, positive=True, meaning="the largest move, in cells")
    if (
        isinstance(blur, (int, float, str))
        or not hasattr(blur, "__len__")
        or not len(blur)
        or any(
            isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not math.isfinite(sigma) or sigma < 0
            for sigma in blur
        )
    ):
        raise ValueError(f"blur must be a non-empty sequence of standard deviations >= 0, got {blur!r}")
    _check_blur_memory(blur, captured, reference)
    batch = captured.shape[0]
    dtype = torch.float64
    start = pose.detach().to(dtype)
    current = start.clone()
    steps = torch.zeros(batch, dtype=torch.int64, device=captured.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=captured.device)
    noise = None if variance is None else torch.as_tensor(variance, dtype=dtype, device=captured.device)
    for sigma in blur:
        stage = _Stage(captured, reference, noise, captured_mask, reference_mask, score, float(sigma), margin)
        current, taken, converged = stage.run(current, iterations, tolerance)
        steps += taken
    final = _Stage(captured, reference, noise, captured_mask, reference_mask, score, 0.0, margin)
    # Never worse than the start: a blurred stage can lead astray where the scene changed (the pixels and weights of
    # the start for both, so the two scores compare).
    fit = final._setup(start)
    before, after = (final.score_with(fit, at) for at in (start, current))
    astray = after < before
    current = torch.where(astray[:, None], start, current)
    converged = converged & ~astray
    return Registration(current.to(pose.dtype), final.score(current).to(captured.dtype), converged, steps)


def _check_blur_memory(blur, captured: Tensor, reference: Tensor) -> None:
    """Refuse a blur whose kernels (and their unfolded copies of the images) exceed the memory budget."""
    radius = _blur_radius(max(blur))
    height, width = reference.shape[-2:]
    cells = max(reference[:, 0].numel(), captured[:, 0].numel())
    # A 1-D convolution on the CPU unfolds every output cell's taps; the map is padded by the radius on both sides.
    needed_cells = cells * (2 * radius + 1) + reference.shape[0] * (height + 2 * radius) * (width + 2 * radius)
    check_cells_memory(
        f"blur={tuple(blur)!r}",
        needed_cells,
        8,
        f"the Gaussian taps ({2 * radius + 1} per cell) over the {height} x {width} map and the captured images",
        "blur by a few cells at most (a blur wider than the map averages it away)",
    )


def _blur_radius(sigma: float) -> int:
    return max(1, math.ceil(3 * sigma))


def _gaussian(images: Tensor, sigma: float, weight: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised Gaussian blur of ``images`` over ``weight`` (0 or 1), and the blurred weight."""
    radius = _blur_radius(sigma)
    offsets = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()

    def smooth(values: Tensor) -> Tensor:
        values = F.conv2d(F.pad(values, (radius, radius, 0, 0)), kernel.view(1, 1, 1, -1))
        return F.conv2d(F.pad(values, (0, 0, radius, radius)), kernel.view(1, 1, -1, 1))

    mass = smooth(weight)
    return smooth(images * weight) / mass.clamp_min(1e-12), mass


class _Stage:
    """One stage of :func:`register`: the (blurred) images, the weights and pixels fixed at the stage's start."""

    def __init__(self, captured, reference, noise, captured_mask, reference_mask, score, sigma, margin) -> None:
        dtype = torch.float64
        self.captured = captured.detach().to(dtype)
        self.reference = reference.detach().to(dtype)
        self.noise, self.score_, self.margin, self.reference_mask = noise, score, margin, reference_mask
        self.captured_valid = torch.ones_like(self.captured, dtype=torch.bool)
        self.masked = captured_mask is not None
        if captured_mask is not None:
            self.captured_valid = self.captured_valid & captured_mask.expand_as(self.captured)
        self.captured_valid = self.captured_valid & torch.isfinite(self.captured)
        self.captured = torch.where(self.captured_valid, self.captured, 0.0)
        self.sigma = sigma
        finite = torch.isfinite(self.reference)
        if not bool(finite.all()):  # NaN or inf map cells are unobserved, and must not bleed into the blur
            self.reference_mask = finite if reference_mask is None else reference_mask & finite
            self.reference = torch.where(finite, self.reference, 0.0)
        if sigma > 0:
            observed = torch.ones_like(self.reference)
            if self.reference_mask is not None:
                observed = self.reference_mask.expand_as(self.reference).to(dtype)
            self.reference, _ = _gaussian(self.reference, sigma, observed)
        self.shape = captured.shape[-2:]

    def _setup(self, pose: Tensor) -> ResponseFit:
        """The pixels that count at ``pose`` (the captured image blurred over them alone) and their weights."""
        warped, valid = _warp(self.reference, pose, self.shape, self.reference_mask, self.margin)
        self.valid = valid & self.captured_valid
        _check_counting(self.valid, pose, self.reference.shape[-2:], self.margin, self.masked)
        self.values = self.captured
        if self.sigma > 0:  # pixels off the map must not bleed into the blurred image
            self.values, _ = _gaussian(self.captured, self.sigma, self.valid.to(self.captured.dtype))
        return ResponseFit.of(self.score_, self.values, warped, self.noise, self.valid)

    def score(self, pose: Tensor) -> Tensor:
        """The score at ``pose``, with the pixels and weights of ``pose``."""
        return self.score_with(self._setup(pose), pose)

    def score_with(self, fit: ResponseFit, pose: Tensor) -> Tensor:
        """The score at ``pose`` with the pixels and weights of ``fit``."""
        warped, _ = _warp(self.reference, pose, self.shape, None, 0.0)
        return fit.solve(self.values.flatten(1), warped.flatten(1))[2]

    def _residuals(self, fit: ResponseFit, pose: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Residuals ``(B, N)``, their Jacobian ``(B, N, 3)`` in the pose, and the scores."""
        with torch.enable_grad():
            positions = sample_positions(pose.detach(), self.shape).requires_grad_(True)
            warped = _sample(self.reference, positions)
            # Each sample depends on its own position only: the gradient of the sum is every pixel's own.
            (gradient,) = torch.autograd.grad(warped.sum(), positions)
        # d position / d pose per pixel: x and y move one to one; the yaw turns the pixel about the image's centre.
        rows = torch.arange(self.shape[0], dtype=pose.dtype, device=pose.device) - (self.shape[0] - 1) / 2
        cols = torch.arange(self.shape[1], dtype=pose.dtype, device=pose.device) - (self.shape[1] - 1) / 2
        angle = torch.deg2rad(-pose[:, 2])[:, None, None]
        cos, sin = angle.cos(), angle.sin()
        x_per_yaw = (-sin * cols[None, None, :] + cos * rows[None, :, None]) * (-math.pi / 180)
        y_per_yaw = (-cos * cols[None, None, :] - sin * rows[None, :, None]) * (-math.pi / 180)
        per_pose = torch.stack(
            [gradient[..., 0], gradient[..., 1], gradient[..., 0] * x_per_yaw + gradient[..., 1] * y_per_yaw], -1
        ).flatten(1, 2)
        residual, slope, score = fit.solve(self.values.flatten(1), warped.detach().flatten(1))
        jacobian = -(fit.weights.sqrt() * slope)[..., None] * per_pose
        return residual, jacobian, score

    def run(self, pose: Tensor, iterations: int, tolerance: float) -> tuple[Tensor, Tensor, Tensor]:
        start = pose.clone()
        fit = self._setup(pose)
        batch = pose.shape[0]
        damping = torch.full((batch,), 1e-3, dtype=pose.dtype)
        steps = torch.zeros(batch, dtype=torch.int64)
        done = torch.zeros(batch, dtype=torch.bool)
        converged = torch.zeros(batch, dtype=torch.bool)
        residual, jacobian, _ = self._residuals(fit, pose)
        cost = residual.square().sum(1)
        for _ in range(iterations):
            if bool(done.all()):
                break
            normal = jacobian.transpose(1, 2) @ jacobian
            gradient = (jacobian.transpose(1, 2) @ residual[..., None])[..., 0]
            diagonal = normal.diagonal(dim1=1, dim2=2).clamp_min(1e-12)
            damped = normal + torch.diag_embed(damping[:, None] * diagonal)
            step = -torch.linalg.solve(damped, gradient)
            step = torch.where(done[:, None], 0.0, step)
            trial = pose + step
            left = ((trial[:, :2] - start[:, :2]).abs() > self.margin).any(1)
            new_residual, new_jacobian, _ = self._residuals(fit, trial)
            new_cost = new_residual.square().sum(1)
            better = (new_cost <= cost) & ~done & ~left
            stalled = better & (cost - new_cost <= 1e-10 * cost)  # the fit no longer improves
            pose = torch.where(better[:, None], trial, pose)
            residual = torch.where(better[:, None], new_residual, residual)
            jacobian = torch.where(better[:, None, None], new_jacobian, jacobian)
            cost = torch.where(better, new_cost, cost)
            damping = torch.where(better, damping / 10, damping * 10).clamp(1e-9, 1e9)
            steps += (~done).long()
            small = step.abs().amax(1) < tolerance
            converged = converged | (small & ~left & ~done)
            converged = converged | (stalled & ~done)
            done = done | small | stalled | left | (damping >= 1e9)
        return pose, steps, converged & ~((pose[:, :2] - start[:, :2]).abs() > self.margin).any(1)
