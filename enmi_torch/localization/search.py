"""Localization: search a prior map for the pose (x/y shift and yaw) of a captured image with dense score surfaces.

The vehicle's captured image (a rectified camera view or a lidar intensity grid, on the map's cell grid) is compared
with the map at every integer shift of a window around the prior pose and at a few yaw angles; the best candidate is
refined below one cell by a quadratic fit of the surface, and the surface's curvature and its second peak say how
sure the estimate is. Each candidate is scored by the score object's surface (:meth:`~enmi_torch.scores.Score.surface`:
ECR, ENMI, mixture, NMI or NCC over every shift at once); the search knows no score by name. How the candidates are
visited is a :class:`~enmi_torch.localization.strategy.SearchStrategy`, carried out by
:mod:`~enmi_torch.localization.candidates`.

Run ``enmi-localize --help`` (or ``python -m enmi_torch.cli.localize --help``) for the command-line tool.

Convention:
    A pose is ``(x, y, yaw)`` in map cells and degrees, absolute, as everywhere in the library (:func:`register`,
    :class:`~enmi_torch.Tracker`): ``x`` the map column and ``y`` the map row (down) under the captured image's
    centre pixel ``(h // 2, w // 2)``, and the captured image is the map section there rotated by ``yaw`` degrees
    about its centre, counter-clockwise as displayed (kornia's :func:`~kornia.geometry.transform.rotate`, y axis
    down). The prior pose ``around = (x, y)`` is the map cell the search window is centred on; the result's
    ``shift`` is the pose's move ``(dx, dy)`` from it. Each yaw is searched by rotating the captured image, its
    variance and its valid mask by ``-yaw`` (nearest neighbour by default; with ``resample="bilinear"`` a pixel
    stays valid only where all four of its neighbours are); corners that rotate out of the ``(h, w)`` frame are
    lost. Map cells outside the map are invalid. Searches run without gradient.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from enmi_torch.localization.candidates import RESAMPLING, CandidateSurfaces
from enmi_torch.localization.peak import Localization, NoCandidateError, read_peak
from enmi_torch.localization.strategy import SearchStrategy, as_search_strategy, refuse_moved_search_options
from enmi_torch.registration.refine import register
from enmi_torch.scores import Score, as_score
from enmi_torch.utils.budget import check_search_memory
from enmi_torch.utils.checks import (
    check_bool,
    check_captured_in_reference,
    check_non_negative_int,
    check_option,
    check_same_device,
    check_shifts,
)
from enmi_torch.utils.options import signature_defaults
from enmi_torch.variance.base import VarianceModel, call_variance, check_variance_model

MAX_YAW_DEG = 1e6  # a float32 yaw of 1e6 degrees is exact to 1/16 degree; 1e300 would read as inf


def accept_center(function: Callable) -> Callable:
    """``function`` that still takes ``center=(row, col)`` (deprecated: it warns) as ``around=(col, row)``."""

    @functools.wraps(function)
    def converted(*args: Any, **kwargs: Any) -> Any:
        if "center" in kwargs:
            center = kwargs.pop("center")
            if kwargs.get("around") is not None:
                raise TypeError(f"{function.__qualname__}() got center and around: pass around=(x, y) alone")
            warnings.warn(
                f"{function.__qualname__}(center=(row, col)) is deprecated and will be removed in the next release: "
                "pass around=(x, y) = (col, row), e.g. around=(20, 10) for center=(10, 20); Localization.pose is "
                "now the absolute (x, y, yaw) and Localization.shift the (dx, dy) from around",
                DeprecationWarning,
                stacklevel=2,
            )
            kwargs["around"] = None if center is None else _center_as_around(center)
        return function(*args, **kwargs)

    return converted


def _center_as_around(center) -> tuple[int, int] | Tensor:
    """A former ``center``: ``(row, col)`` integers or a ``(2,)`` or ``(B, 2)`` integer tensor, as ``(x, y)``."""
    if isinstance(center, Tensor):
        if center.is_floating_point() or center.is_complex() or center.ndim not in (1, 2) or center.shape[-1] != 2:
            raise ValueError(
                f"center must be (row, col) or an integer tensor of shape (2,) or (B, 2), got {center.dtype} "
                f"{tuple(center.shape)}"
            )
        return center.flip(-1)
    if (
        not isinstance(center, (tuple, list))
        or len(center) != 2
        or not all(isinstance(value, int) and not isinstance(value, bool) for value in center)
    ):
        raise ValueError(f"center must be (row, col) integers or a (B, 2) integer tensor, got {center!r}")
    return (center[1], center[0])


@accept_center
@refuse_moved_search_options
def localize(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    *,
    score: Score | str = "ecr",
    shifts: int | tuple[int, int] = 16,
    around: tuple[float, float] | Tensor | None = None,
    yaws: Sequence[float] | Tensor | None = None,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    min_overlap: float = 0.5,
    exclusion_radius: int = 3,
    resample: str = "nearest",
    search: SearchStrategy | str = "exhaustive",
    refine: bool = False,
) -> Localization:
    """Find the pose of each captured image in the prior map: the best of a window of shifts and a set of yaws.

    Args:
        captured: captured images ``(B, 1, h, w)``, floating point, on the map's cell grid.
        reference: ``(1, 1, Hm, Wm)`` (one map for all) or ``(B, 1, Hm, Wm)``, floating point.
        variance: for a score that uses one (ECR, ENMI, mixture): the captured images' per-pixel noise variance (a
            number, ``(h, w)``, ``(1, 1, h, w)`` or ``(B, 1, h, w)``) or a :class:`~enmi_torch.variance.VarianceModel`
            (its ``valid_mask`` is used too). Must be ``None`` for the others (NMI, NCC).
        score: the score of a candidate, a :class:`~enmi_torch.scores.Score` or its name
            (:func:`~enmi_torch.scores.as_score`):
            :class:`~enmi_torch.ECR` (the default: the noise-aware correlation ratio, where the per-pixel variance
            weighs each pixel's evidence),
            :class:`~enmi_torch.ENMI` (the paper's score; a ``(B, bins)`` ``log_prior`` gives each sample its row,
            applied to all of that sample's yaws), :class:`~enmi_torch.Mixture` (shifts that its cheap first stage
            does not rescore are ``-inf`` in ``surface``), :class:`~enmi_torch.NMI` (hard bins) or
            :class:`~enmi_torch.NCC`. Each candidate is scored by ``score.surface``.
        shifts: search radius in cells, ``r`` or ``(ry, rx)``: shifts ``dy`` in ``[-ry, ry]``, ``dx`` in
            ``[-rx, rx]``.
        around: the prior pose ``(x, y)``: the map column and row under the captured centre pixel, a pair of numbers
            or a ``(2,)`` or ``(B, 2)`` tensor (one per sample), rounded to the nearest cell (the window's middle);
            ``None`` for the map's centre cell ``(Wm // 2, Hm // 2)``. It takes no yaw: the ``yaws`` are absolute
            (to search around a prior yaw ``a``, pass ``yaws=[a - 2, a, a + 2]``). ``center=(row, col)``, its former
            spelling, still works for one release with a ``DeprecationWarning``: ``around=(col, row)``.
        yaws: yaw angles to search, in degrees (absolute); ``None`` for ``[0]``.
        captured_mask: bool, broadcast like ``variance``: ``False`` pixels are unobserved.
        reference_mask: bool ``(Hm, Wm)``, ``(1, 1, Hm, Wm)`` or ``(B, 1, Hm, Wm)``: ``False`` cells are unmapped.
        min_overlap: in ``(0, 1]``: a candidate counts only if at least this fraction of the (rotated) captured image's
            valid pixels land on valid map cells; the others score ``-inf``.
        exclusion_radius: cells around the peak (Chebyshev distance) left out when looking for the second peak.
        resample: how the captured image, its variance and mask are rotated for a yaw: ``"nearest"`` (default: every
            pixel keeps its own value and noise variance, at most half a cell off) or ``"bilinear"`` (sub-cell
            geometry, but the average of neighbours is less noisy than a pixel of the yaw-0 image, which biases
            noisy searches towards rotated yaws; the variance is propagated as ``sum_k w_k^2 sigma_k^2``).
        search: how the candidates are visited: a :class:`~enmi_torch.localization.SearchStrategy` (every candidate,
            coarse to fine, or two stages with a cheap first stage: see there), or its method's name
            (``"exhaustive"``, ``"two_stage"``) for its default options.
        refine: move on from the best candidate to the continuous pose that maximises the score, by Gauss-Newton
            (:func:`~enmi_torch.registration.register`, ECR or NCC, from ``pose``, as ``register(..., pose=pose)``
            would): ``pose`` is then the refined pose; the surface, score, covariance and margin stay those of the
            search.

    Returns:
        :class:`Localization`: ``pose`` ``(B, 3)`` absolute ``(x, y, yaw)`` (pass it to :func:`register` or
        :meth:`~enmi_torch.Tracker.start` unchanged), ``shift`` ``(B, 2)`` its move from ``around``.

    Raises:
        ValueError: on inconsistent shapes, empty masks, a captured image larger than the map, a variance given to
            a score that does not use one (or none to one that does), or when no candidate of a sample passes
            ``min_overlap``.

    Convention:
        No gradient (a search). Scores are computed in float64 for float64 ``captured`` and in float32 otherwise;
        results have the dtype and device of ``captured``. Cost: one FFT surface per sample and yaw, dominated by
        ``bins^2`` inverse FFTs of the ``(h + 2 ry) x (w + 2 rx)`` window (ENMI, NMI; ``3 bins`` for ECR).

    Example:
        >>> from enmi_torch import ECR
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 48, 48, generator=generator) * 256
        >>> captured = reference[..., 14:30, 19:35] + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> result = localize(captured, reference, 64.0, score=ECR(bins=16), shifts=6, around=(24, 24))
        >>> result.pose.round().tolist(), result.shift.round().tolist(), result.surface.shape  # column 27, row 22
        ([[27.0, 22.0, 0.0]], [[3.0, -2.0]], torch.Size([1, 1, 13, 13]))
    """
    score = as_score(score)
    check_bool("refine", refine)
    check_option("resample", resample, RESAMPLING)
    check_same_device("reference", reference, "captured", captured)
    batch = check_captured_in_reference(captured, reference, "Hm, Wm")[0]
    radius = check_shifts(shifts)
    centers, around = _check_around(around, batch, tuple(reference.shape[2:]), captured.device)
    yaw_list = _check_yaws(yaws)
    _check_search_settings(min_overlap, exclusion_radius)
    strategy = as_search_strategy(search)
    score.check_variance(variance)
    samples = score.per_sample(batch)
    _check_strategy_fits_score(strategy, score)
    bins = score.options.get("bins")
    check_search_memory(captured, shifts, radius, len(yaw_list), bins, strategy.coarse_factor)
    with torch.no_grad():
        candidates = CandidateSurfaces.prepare(
            captured, reference, variance, captured_mask, reference_mask, centers, radius, yaw_list, samples, resample
        )
        surface = candidates.run(strategy, min_overlap, exclusion_radius)
        finalists = None
        if strategy.finalists and not all(sample.surface_is_exact for sample in samples):
            finalists = candidates.finalists(surface, strategy.finalists)
        try:
            yaw_tensor = torch.tensor(yaw_list, dtype=surface.dtype)
            found = read_peak(surface, yaw_tensor, radius, exclusion_radius, around, finalists)
        except NoCandidateError as error:
            off_map = _windows_off_map(centers, radius, tuple(captured.shape[2:]), tuple(reference.shape[2:]))
            if off_map:
                raise NoCandidateError(
                    f"the search window lies off the map in sample(s) {off_map}: every candidate around (x, y) = "
                    f"{centers[off_map[0]].flip(0).tolist()} with shifts {radius} places captured "
                    f"{tuple(captured.shape[2:])} outside the {tuple(reference.shape[2:])} map (rows, columns); move "
                    "around onto the map"
                ) from None
            raise error from None
    if not refine:
        return found
    return _refined(found, captured, reference, variance, score, captured_mask, reference_mask)


def _refined(found: Localization, captured, reference, variance, score, captured_mask, reference_mask):
    """``found`` with its pose moved on by :func:`~enmi_torch.registration.register`, from that pose as it is."""
    if reference_mask is not None and reference_mask.ndim == 2:
        reference_mask = reference_mask[None, None]
    refined = register(
        captured,
        reference,
        variance,
        pose=found.pose.double(),
        score=score,
        captured_mask=captured_mask,
        reference_mask=reference_mask,
        margin=1.0,  # the search scored the neighbouring cells: the continuous optimum lies within one of its best
    )
    return found._replace(pose=refined.pose.to(found.pose.dtype))


def _check_search_settings(min_overlap: float, exclusion_radius: int) -> None:
    """The search's own settings (the score checks its options itself, the strategy its own)."""
    if not isinstance(min_overlap, (int, float)) or isinstance(min_overlap, bool) or not 0 < min_overlap <= 1:
        raise ValueError(f"min_overlap must be a fraction in (0, 1], got {min_overlap!r}")
    check_non_negative_int("exclusion_radius", exclusion_radius)


def _check_strategy_fits_score(strategy: SearchStrategy, score: Score) -> None:
    """A two-stage search ranks by the score's rough surface: the score must have one, with more bins than it.

    A finalist count other than the default's and 0 needs a score whose surface is not exact (one that has a finalist
    stage); 0, no finalist stage, is what such a score's search does anyway.
    """
    if strategy.finalists not in (0, signature_defaults(SearchStrategy)["finalists"]) and score.surface_is_exact:
        raise ValueError(
            f"finalists={strategy.finalists} has no effect with score={score!r}: its surface is its exact value at "
            "every placement, so a search has no finalists to rescore; drop finalists, or pass a score that fits a "
            "model to each pair (ECR())"
        )
    if strategy.method != "two_stage":
        return
    score.require("two_stage", "search='two_stage'")
    if strategy.cheap_bins > score.bins:
        raise ValueError(f"cheap_bins must be at most bins ({score.bins}), got {strategy.cheap_bins}")


class Localizer(nn.Module):
    """Module form of :func:`localize`: stores the score, the search settings and an optional variance model.

    Args:
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` for a score that uses a variance (else
            give the variance per call).
        score: a :class:`~enmi_torch.scores.Score` or its name (see :func:`localize`).
        shifts: search radius (see :func:`localize`).
        yaws: yaws in degrees (stored as a non-persistent buffer).
        min_overlap: see :func:`localize`.
        exclusion_radius: see :func:`localize`.
        resample: see :func:`localize`.
        search: a :class:`~enmi_torch.localization.SearchStrategy` or its method's name (see :func:`localize`).

    Example:
        >>> from enmi_torch import ECR
        >>> from enmi_torch.variance import ConstantVariance
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 40, 40, generator=generator) * 256
        >>> localizer = Localizer(ConstantVariance(16.0), score=ECR(bins=16), shifts=5)
        >>> localizer(reference[..., 15:31, 14:30], reference).pose.round().tolist()  # column 22, row 23
        [[22.0, 23.0, 0.0]]
    """

    @refuse_moved_search_options
    def __init__(
        self,
        variance_model: VarianceModel | None = None,
        *,
        score: Score | str = "ecr",
        shifts: int | tuple[int, int] = 16,
        yaws: Sequence[float] | Tensor | None = None,
        min_overlap: float = 0.5,
        exclusion_radius: int = 3,
        resample: str = "nearest",
        search: SearchStrategy | str = "exhaustive",
    ) -> None:
        super().__init__()
        self.variance_model = check_variance_model(variance_model)
        self.score = as_score(score)
        self.shifts = check_shifts(shifts)
        self.register_buffer("yaws", torch.tensor(_check_yaws(yaws), dtype=torch.float64), persistent=False)
        self.options = {
            "min_overlap": min_overlap,
            "exclusion_radius": exclusion_radius,
            "resample": check_option("resample", resample, RESAMPLING),
            "search": as_search_strategy(search),
        }
        _check_search_settings(min_overlap, exclusion_radius)
        _check_strategy_fits_score(self.options["search"], self.score)

    @accept_center
    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        around: tuple[float, float] | Tensor | None = None,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Localization:
        """Localize ``captured`` ``(B, 1, h, w)`` in ``reference`` around the prior ``(x, y)`` (see :func:`localize`).

        ``variance`` per call unless a model is stored; ``center=(row, col)`` is deprecated as in :func:`localize`.
        """
        return localize(
            captured,
            reference,
            call_variance("Localizer", variance, self.variance_model),
            score=self.score,
            shifts=self.shifts,
            around=around,
            yaws=self.yaws.tolist(),
            captured_mask=captured_mask,
            reference_mask=reference_mask,
            **self.options,
        )


def _windows_off_map(
    centers: Tensor, radius: tuple[int, int], captured_shape: tuple[int, int], map_shape: tuple[int, int]
) -> list[int]:
    """The samples whose every candidate (any shift, any yaw) places the captured box wholly outside the map.

    A rotation keeps the turned image within its ``(h, w)`` box, so no yaw can bring such a window onto the map.
    """
    height, width = captured_shape
    tops = centers[:, 0].cpu() - height // 2
    lefts = centers[:, 1].cpu() - width // 2
    rows_off = (tops + radius[0] + height <= 0) | (tops - radius[0] >= map_shape[0])
    cols_off = (lefts + radius[1] + width <= 0) | (lefts - radius[1] >= map_shape[1])
    return (rows_off | cols_off).nonzero()[:, 0].tolist()


def _check_yaws(yaws) -> list[float]:
    if yaws is None:
        return [0.0]
    values = yaws.flatten().tolist() if isinstance(yaws, Tensor) else list(yaws)
    if not values or not all(isinstance(value, (int, float)) and math.isfinite(value) for value in values):
        raise ValueError(f"yaws must be a non-empty sequence of finite angles in degrees, got {yaws!r}")
    largest = max(abs(value) for value in values)
    if largest > MAX_YAW_DEG:
        raise ValueError(
            f"yaws must be angles within +-{MAX_YAW_DEG:g} degrees (float32 poses cannot tell yaws apart beyond), "
            f"got {largest:g}"
        )
    return [float(value) for value in values]


def _check_around(around, batch: int, map_shape: tuple[int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    """``(B, 2)`` int64 ``(row, col)`` window middles and ``(B, 2)`` float64 ``(x, y)`` of the prior pose ``around``.

    ``around`` is ``(x, y)`` (numbers, rounded to the nearest cell), a ``(2,)`` or ``(B, 2)`` real tensor, or
    ``None`` (the map's centre cell).
    """
    if around is None:
        values = torch.tensor([[map_shape[1] // 2, map_shape[0] // 2]], dtype=torch.float64, device=device)
    elif isinstance(around, Tensor):
        if around.is_complex() or around.dtype == torch.bool or around.shape not in ((2,), (batch, 2)):
            extra = " (a pose's yaw is not taken: pass pose[:, :2], and the yaws to search as yaws)"
            raise ValueError(
                f"around must be (x, y) or a real tensor of shape (2,) or ({batch}, 2), got {around.dtype} "
                f"{tuple(around.shape)}" + (extra if around.shape[-1:] == (3,) else "")
            )
        values = around.detach().to(device=device, dtype=torch.float64).reshape(-1, 2)
    elif (
        isinstance(around, (tuple, list))
        and len(around) == 2
        and all(isinstance(value, (int, float)) and not isinstance(value, bool) for value in around)
    ):
        values = torch.tensor([list(around)], dtype=torch.float64, device=device)
    else:
        extra = ""
        if isinstance(around, (tuple, list)) and len(around) == 3:
            extra = " (a pose's yaw is not taken: pass (x, y), and the yaws to search as yaws)"
        raise ValueError(f"around must be (x, y) numbers or a (B, 2) tensor, got {around!r}{extra}")
    if not bool(torch.isfinite(values).all()) or bool((values.abs() > MAX_CELL).any()):
        raise ValueError(f"around must be finite map cells (x, y) within +-{MAX_CELL:g}, got {around!r}")
    around_xy = values.round().expand(batch, 2)
    return around_xy.flip(1).long(), around_xy


MAX_CELL = 2.0**52  # a float64 map cell beyond this has no integer neighbour to round to
