"""Continuous pose refinement: the pose ``(x, y, yaw)`` of captured images in a map by Gauss-Newton through a score.

:func:`localize` finds the best integer shift and yaw bin; :func:`register` moves on from there (or from any pose) to
the continuous pose that maximises the score, batched. The map is sampled under the captured image at the pose
(:func:`~enmi_torch.registration.warp.warp_reference`: a cubic B-spline by default, bilinear on request; the
gradient in the pose in closed form), so the noisy captured image, its variance and its mask are never resampled.
The score is a weighted least-squares fit of the captured values by a response of the map's values, the likelihood
behind ECR (:class:`~enmi_torch.ECR`):

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
Gauss-Newton normal equations (Kaufman's approximation of the variable-projection Jacobian); each stage of ``blur``
compares both images blurred by a Gaussian (:mod:`~enmi_torch.registration.stage`). Histogram scores (NMI, ENMI, the
mixture) are not least-squares fits and are refused.

Why the last stage blurs by half a cell: a map cell and a captured pixel are each the mean of the scene over a cell,
and the scene varies within a cell, so the map's cells do not hold the scene between them: whatever interpolates
them (bilinear, a B-spline) misses detail finer than a cell that the captured pixels moved by a fraction of a cell
do hold (aliasing). Comparing both blurred by half a cell weighs that detail down. On 3 x 3 block means of aerial
photographs moved by whole source pixels (the truth a third of a cell), the B-spline and the blur each about halve
the error of a bilinear, unblurred fit (the docs' localization results page).

The pixels that count and the score's weights are read at the starting pose, for every stage: pixels whose map
sample lies within ``margin`` cells of the map's border, off the map or by an unobserved map cell do not count, nor do
the captured image's invalid pixels; the set is held fixed while the pose moves (a score whose pixel set changed with
the pose would jump), so a move of more than ``margin`` cells from the start ends the refinement of that image
(``Registration.converged`` is ``False``). The last stage's score at the result is compared with its score at the
start, with the same pixels and weights: a result that scores below the start is replaced by the start.

Convention:
    A pose is ``(x, y, yaw)`` as everywhere in the library: ``x`` (column) and ``y`` (row, down) the map position of
    the captured image's pixel ``(h // 2, w // 2)``, in cells, absolute; ``yaw`` in degrees, counter-clockwise as
    displayed: :func:`~enmi_torch.localize`'s ``pose``, and what :meth:`~enmi_torch.Tracker.start` takes. The
    captured pixel ``(u, v)`` shows the map at :meth:`~enmi_torch.Localization.local_to_map` of that pose.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.registration.interpolation import INTERPOLATIONS
from enmi_torch.registration.stage import Stage
from enmi_torch.registration.warp import blur_radius, check_map_memory, check_warp_memory
from enmi_torch.scores import Score, as_score
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import (
    check_floating,
    check_map,
    check_margin,
    check_mask_of,
    check_not_empty,
    check_option,
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
        score: ``(B,)`` the last stage's fit at ``pose`` with the pixels and weights read at the start: its
            log-likelihood ratio per valid pixel (half the weighted residual sum of squares the response removes, over
            the valid pixels; larger is better), what the refinement maximised:
            ``registration_score(..., pose=result.pose, weights_at=start)``. It is at least the start's.
        converged: ``(B,)`` bool: the last step moved less than ``tolerance`` (cells, and degrees for the yaw), or
            the fit stopped improving, without leaving the pixels fixed at the start. A result that scores below the
            start (a stage led astray) is replaced by the start, not converged.
        iterations: ``(B,)`` int64 steps taken.
    """

    pose: Tensor
    score: Tensor
    converged: Tensor
    iterations: Tensor


FINAL_BLUR = 0.5  # cells: the last stage's blur (the module's note)


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
    blur: float = FINAL_BLUR,
    interpolation: str = "bspline",
    weights_at: Tensor | None = None,
) -> Tensor:
    """The score :func:`register` maximises, ``(B,)``, at ``pose`` ``(B, 3)``; differentiable in ``pose``.

    The pixels that count and the weights (``tau^2`` for ECR) are read at ``weights_at`` (``(B, 3)``; ``None``:
    ``pose`` itself), without gradient; the response is refitted at ``pose``. ``blur``: the Gaussian (cells) both
    images are compared through, :func:`register`'s last stage (0: none). The other arguments as :func:`register`'s.

    Example:
        >>> from enmi_torch import ECR
        >>> from enmi_torch.registration import warp_reference
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
    blur = _check_blur((blur,), "blur", "a standard deviation >= 0")[0]
    check_option("interpolation", interpolation, INTERPOLATIONS)
    captured, reference, variance, captured_mask, reference_mask, pose = inputs
    if weights_at is not None:
        weights_at = check_pose("weights_at", weights_at, captured.shape[0]).detach()
    check_warp_memory(captured.shape[0], tuple(captured.shape[-2:]), captured.element_size())
    check_map_memory(reference, interpolation, captured.element_size())
    _check_blur_memory((blur,), captured)
    dtype = captured.dtype
    stage = Stage(
        captured, reference.to(dtype), variance, captured_mask, reference_mask, score, blur, margin, interpolation
    )
    fit = stage.setup((pose if weights_at is None else weights_at).detach())
    return stage.score_with(fit, pose).to(dtype)


def register(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    *,
    pose: Tensor,
    score: Score | str = "ecr",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    blur: tuple[float, ...] = (FINAL_BLUR,),
    iterations: int = 30,
    tolerance: float = 1e-3,
    margin: float = 2.0,
    interpolation: str = "bspline",
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
            for each stage, coarse to fine (0: none). The last one's half a cell weighs down the detail finer than a
            cell that no interpolation of the map holds (the module's note); from :func:`~enmi_torch.localize`'s pose
            (within a cell) it is the only stage needed. Starting farther away, a coarser stage first widens the
            basin of attraction: ``blur=(2.0, 0.5)``.
        iterations: Levenberg-Marquardt steps per stage at most.
        tolerance: a step smaller than this (cells and degrees) ends a stage: the next Gauss-Newton step would be
            far smaller still.
        margin: cells a counting pixel's map sample keeps from the map's border and from unobserved cells at the
            start; a larger move from the start ends the refinement.
        interpolation: how the map is sampled between its cells: ``"bspline"`` (cubic) or ``"bilinear"``
            (:mod:`~enmi_torch.registration.interpolation`).

    Returns:
        :class:`Registration` (``pose``, ``score``, ``converged``, ``iterations``), in ``captured``'s dtype.

    Raises:
        TypeError, ValueError: naming the argument (shapes, dtypes, devices, finite values, masks the size of what
            they mask, a pose where no pixel counts).
        MemoryBudgetError: when the score's normal equations (``ECR(bins=...)``), the samples or the blur's taps would
            exceed the memory budget, before anything is allocated.

    Convention:
        No gradient flows through the result. The per-pixel work runs in ``captured``'s dtype (float32 is about twice
        as fast), the normal equations in float64.

    Example:
        >>> import torch.nn.functional as F
        >>> from enmi_torch import ECR
        >>> from enmi_torch.registration import warp_reference
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
    blur = _check_blur(blur, "blur", "a non-empty sequence of standard deviations >= 0")
    check_option("interpolation", interpolation, INTERPOLATIONS)
    check_warp_memory(captured.shape[0], tuple(captured.shape[-2:]), captured.element_size())
    check_map_memory(reference, interpolation, captured.element_size())
    _check_blur_memory(blur, captured)
    batch, dtype = captured.shape[0], captured.dtype
    start = pose.detach().to(torch.float64)
    current = start.clone()
    steps = torch.zeros(batch, dtype=torch.int64, device=captured.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=captured.device)
    reference = reference.to(dtype)
    for sigma in blur:
        stage = Stage(captured, reference, variance, captured_mask, reference_mask, score, sigma, margin, interpolation)
        fit = stage.setup(start)
        origin = current
        current, taken, converged, after, before = stage.run(fit, current, start, iterations, tolerance)
        steps += taken
    # Never below the start, with the last stage's pixels and weights (read at the start) for both.
    if not torch.equal(origin, start):  # the last stage began where an earlier one ended
        before = stage.score_with(fit, start)
    astray = after < before
    current = torch.where(astray[:, None], start, current)
    return Registration(
        current.to(pose.dtype), torch.where(astray, before, after).to(dtype), converged & ~astray, steps
    )


def _check_blur(blur, name: str, expected: str) -> tuple[float, ...]:
    """``blur`` as a tuple of floats: standard deviations ``>= 0``, finite, at least one."""
    if (
        isinstance(blur, (int, float, str))
        or not hasattr(blur, "__len__")
        or not len(blur)
        or any(
            isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not math.isfinite(sigma) or sigma < 0
            for sigma in blur
        )
    ):
        shown = blur[0] if name == "blur" and expected.startswith("a standard") else blur
        raise ValueError(f"{name} must be {expected}, got {shown!r}")
    return tuple(float(sigma) for sigma in blur)


def _check_blur_memory(blur, captured: Tensor) -> None:
    """Refuse a blur whose padded images would exceed the memory budget.

    The captured images, the map's samples and their three derivatives in the pose, padded by the kernel's radius.
    """
    radius = blur_radius(max(blur))
    batch, _, height, width = captured.shape
    needed_cells = 4 * batch * (height + 2 * radius) * (width + 2 * radius)
    check_cells_memory(
        f"blur={tuple(blur)!r}",
        needed_cells,
        8,
        f"the {height} x {width} images padded by the Gaussian's radius ({radius} cells)",
        "blur by a few cells at most (a blur wider than the images averages them away)",
    )
