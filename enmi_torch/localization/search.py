"""Localization: search a prior map for the pose (x/y shift and yaw) of a captured image with dense score surfaces.

The vehicle's captured image (a rectified camera view or a lidar intensity grid, on the map's cell grid) is compared
with the map at every integer shift of a window around the prior pose and at a few yaw angles; the best candidate is
refined below one cell by a quadratic fit of the surface, and the surface's curvature and its second peak say how
sure the estimate is. Each candidate is scored by the score object's surface (:meth:`~enmi_torch.scores.Score.surface`:
ECR, ENMI, mixture, NMI or NCC over every shift at once); the search knows no score by name.

Run ``enmi-localize --help`` (or ``python -m enmi_torch.localization --help``) for the command-line tool.

Convention:
    Poses are in map cells and degrees. ``center = (row, col)`` is the map cell under the captured image's centre
    pixel ``(h // 2, w // 2)`` at the prior pose; a pose ``(dx, dy, yaw)`` puts that pixel on map cell
    ``(row + dy, col + dx)`` (``dx`` along columns, ``dy`` along rows) and says that the captured image is the map
    section there rotated by ``yaw`` degrees about its centre, counter-clockwise as displayed (kornia's
    :func:`~kornia.geometry.transform.rotate`, y axis down). Each yaw is searched by rotating the captured image, its
    variance and its valid mask by ``-yaw`` (nearest neighbour by default; with ``resample="bilinear"`` a pixel
    stays valid only where all four of its neighbours are); corners that rotate out of the ``(h, w)`` frame are
    lost. Map cells outside the map are invalid. Searches run without gradient.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch
from kornia.geometry.transform import rotate
from torch import Tensor, nn

from enmi_torch.localization.peak import Localization, NoCandidateError, _read_peak, _separated_peaks
from enmi_torch.placement.peaks import rescore_peaks
from enmi_torch.registration.refine import register
from enmi_torch.scores import ECR, Score, as_score
from enmi_torch.scores.ecr import cheap_value_range
from enmi_torch.utils.budget import check_search_memory
from enmi_torch.utils.checks import (
    check_bins,
    check_bool,
    check_captured_in_reference,
    check_mask_not_empty,
    check_non_negative_int,
    check_option,
    check_positive_int,
    check_resolved_by_bins,
    check_same_device,
    check_shifts,
)
from enmi_torch.utils.layout import mask_map, variance_map
from enmi_torch.variance.base import VarianceModel, call_variance, check_variance_model

# A rotated mask pixel is valid when its bilinear value is 1 up to round-off: all four neighbours were valid.
_FULL_SUPPORT = 1 - 1e-3


def localize(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    *,
    score: Score | str = "ecr",
    shifts: int | tuple[int, int] = 16,
    center: tuple[int, int] | Tensor | None = None,
    yaws: Sequence[float] | Tensor | None = None,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    min_overlap: float = 0.5,
    exclusion_radius: int = 3,
    coarse_factor: int = 1,
    coarse_peaks: int = 3,
    resample: str = "nearest",
    search: str = "exhaustive",
    cheap_bins: int = 4,
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
            weighs each pixel's evidence; the best of the library's scores on ``data_tools/yardstick/yardstick.py``),
            :class:`~enmi_torch.ENMI` (the paper's score; a ``(B, bins)`` ``log_prior`` gives each sample its row,
            applied to all of that sample's yaws), :class:`~enmi_torch.Mixture` (shifts that its cheap first stage
            does not rescore are ``-inf`` in ``surface``), :class:`~enmi_torch.NMI` (hard bins) or
            :class:`~enmi_torch.NCC`. Each candidate is scored by ``score.surface``.
        shifts: search radius in cells, ``r`` or ``(ry, rx)``: shifts ``dy`` in ``[-ry, ry]``, ``dx`` in
            ``[-rx, rx]``.
        center: prior pose: map cell ``(row, col)`` under the captured centre pixel, or ``(B, 2)`` integers, one per
            sample; ``None`` for the map's centre cell ``(Hm // 2, Wm // 2)``.
        yaws: yaw angles to search, in degrees; ``None`` for ``[0]``.
        captured_mask: bool, broadcast like ``variance``: ``False`` pixels are unobserved.
        reference_mask: bool ``(Hm, Wm)``, ``(1, 1, Hm, Wm)`` or ``(B, 1, Hm, Wm)``: ``False`` cells are unmapped.
        min_overlap: in ``(0, 1]``: a candidate counts only if at least this fraction of the (rotated) captured image's
            valid pixels land on valid map cells; the others score ``-inf``.
        exclusion_radius: cells around the peak (Chebyshev distance) left out when looking for the second peak.
        coarse_factor: ``1`` searches every shift exhaustively. ``f > 1`` searches first on images averaged over
            ``f x f`` cells (variance divided by ``f^2``), keeps the ``coarse_peaks`` best separated coarse
            candidates and searches every shift within ``f`` cells of each at full resolution (at its yaw and the
            two next ones): for windows much larger than the captured image. Each of these surfaces reads ECR's
            estimated model variance in its own window.
        coarse_peaks: coarse candidates refined when ``coarse_factor > 1``.
        resample: how the captured image, its variance and mask are rotated for a yaw: ``"nearest"`` (default: every
            pixel keeps its own value and noise variance, at most half a cell off) or ``"bilinear"`` (sub-cell
            geometry, but the average of neighbours is less noisy than a pixel of the yaw-0 image, which biases
            noisy searches towards rotated yaws; the variance is propagated as ``sum_k w_k^2 sigma_k^2``).
        search: ``"exhaustive"`` (every shift and yaw scored) or ``"two_stage"`` (an :class:`~enmi_torch.ECR` score with
            the shrunk or binned response, ``coarse_factor=1``): binned ECR with ``cheap_bins`` bins (spanning the 2nd
            to 98th percentile of the map window's valid cells, so that few bins still split the map's values; the
            default model variance of those bins) over every shift and yaw, then the exact score at the 3 x 3 x 3
            (shift, shift, yaw) neighbourhoods of its best 4 peaks; while the exact best lies by a peak of the lower
            half of that cheap ranking, the number of peaks doubles (up to 64), then the exact best's own neighbourhood
            is completed for the sub-cell fit. Rescored candidates score as in the exhaustive surface (up to round-off;
            with ECR's estimated model variance, read at each yaw's cheap peak, when ``cheap_bins=4`` and ``min_overlap
            <= 0.5``, else it may be read elsewhere), the others are ``-inf`` in ``surface``. It misses the exhaustive
            argmax when the cheap score ranks that peak below the ones it rescored and the doubling has stopped
            (``data_tools/benchmarks/bench_search.py`` measures how often: rarely, at extreme noise).
        cheap_bins: bins of the first stage of ``search="two_stage"``, ``2 <= cheap_bins <= bins``.
        refine: move on from the best candidate to the continuous pose that maximises the score, by Gauss-Newton
            (:func:`~enmi_torch.registration.register`, ECR or NCC): ``pose`` is then the refined pose; the surface,
            score, covariance and margin stay those of the search.

    Returns:
        :class:`Localization`.

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
        >>> result = localize(captured, reference, 64.0, score=ECR(bins=16), shifts=6)
        >>> result.pose.round().tolist(), result.surface.shape
        ([[3.0, -2.0, 0.0]], torch.Size([1, 1, 13, 13]))
    """
    score = as_score(score)
    check_bool("refine", refine)
    check_option("resample", resample, RESAMPLING)
    check_same_device("reference", reference, "captured", captured)
    batch = check_captured_in_reference(captured, reference, "Hm, Wm")[0]
    radius = check_shifts(shifts)
    centers = _check_center(center, batch, tuple(reference.shape[2:]), captured.device)
    yaw_list = _check_yaws(yaws)
    _check_search_settings(min_overlap, exclusion_radius, coarse_factor, coarse_peaks, search)
    score.check_variance(variance)
    samples = score.per_sample(batch)
    if search == "two_stage":
        _check_two_stage(score, coarse_factor, cheap_bins)
    check_search_memory(captured, shifts, radius, len(yaw_list), score.options.get("bins"), coarse_factor)
    with torch.no_grad():
        searcher = _Search.prepare(
            captured, reference, variance, captured_mask, reference_mask, centers, radius, yaw_list, samples, resample
        )
        if search == "two_stage":
            surface = searcher.two_stage(min_overlap, cheap_bins)
        elif coarse_factor == 1:
            surface = searcher.exhaustive(min_overlap)
        else:
            surface = searcher.coarse_to_fine(min_overlap, coarse_factor, coarse_peaks, exclusion_radius)
        try:
            found = _read_peak(surface, torch.tensor(yaw_list, dtype=surface.dtype), radius, exclusion_radius)
        except NoCandidateError as error:
            off_map = _windows_off_map(centers, radius, tuple(captured.shape[2:]), tuple(reference.shape[2:]))
            if off_map:
                raise NoCandidateError(
                    f"the search window lies off the map in sample(s) {off_map}: every candidate of center "
                    f"{centers[off_map[0]].tolist()} with shifts {radius} places captured {tuple(captured.shape[2:])} "
                    f"outside the {tuple(reference.shape[2:])} map; move center onto the map"
                ) from None
            raise error from None
    if not refine:
        return found
    return _refined(found, captured, reference, variance, score, centers, captured_mask, reference_mask)


def _refined(found: Localization, captured, reference, variance, score, centers, captured_mask, reference_mask):
    """``found`` with its pose moved on by :func:`~enmi_torch.registration.register` (absolute poses meanwhile)."""
    offset = torch.stack([centers[:, 1], centers[:, 0], torch.zeros_like(centers[:, 0])], 1).to(torch.float64)
    if reference_mask is not None and reference_mask.ndim == 2:
        reference_mask = reference_mask[None, None]
    start = found.pose.double() + offset.to(found.pose.device)
    refined = register(
        captured,
        reference,
        variance,
        pose=start,
        score=score,
        captured_mask=captured_mask,
        reference_mask=reference_mask,
        margin=1.0,  # the search scored the neighbouring cells: the continuous optimum lies within one of its best
    )
    return found._replace(pose=(refined.pose.double() - offset).to(found.pose.dtype))


def _check_search_settings(
    min_overlap: float, exclusion_radius: int, coarse_factor: int, coarse_peaks: int, search: str
) -> None:
    """The search's own settings (the score checks its options itself)."""
    if not isinstance(min_overlap, (int, float)) or isinstance(min_overlap, bool) or not 0 < min_overlap <= 1:
        raise ValueError(f"min_overlap must be a fraction in (0, 1], got {min_overlap!r}")
    check_non_negative_int("exclusion_radius", exclusion_radius)
    check_positive_int("coarse_factor", coarse_factor)
    check_positive_int("coarse_peaks", coarse_peaks)
    check_option("search", search, SEARCHES)


def _check_two_stage(score: Score, coarse_factor: int, cheap_bins: int) -> None:
    """The two-stage search ranks by a cheap binned ECR and rescores with the exact one: it needs a binned ECR."""
    if not isinstance(score, ECR) or score.response == "linear" or coarse_factor != 1:
        raise ValueError(
            "search='two_stage' needs an ECR score with response='shrunk' or 'binned' and coarse_factor=1, got "
            f"score={score!r}, coarse_factor={coarse_factor!r}"
        )
    if check_bins(cheap_bins, "cheap_bins") > score.bins:
        raise ValueError(f"cheap_bins must be at most bins ({score.bins}), got {cheap_bins}")


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
        coarse_factor: see :func:`localize`.
        coarse_peaks: see :func:`localize`.
        resample: see :func:`localize`.
        search: see :func:`localize`.
        cheap_bins: see :func:`localize`.

    Example:
        >>> from enmi_torch import ECR
        >>> from enmi_torch.variance import ConstantVariance
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 40, 40, generator=generator) * 256
        >>> localizer = Localizer(ConstantVariance(16.0), score=ECR(bins=16), shifts=5)
        >>> localizer(reference[..., 15:31, 14:30], reference).pose.round().tolist()
        [[2.0, 3.0, 0.0]]
    """

    def __init__(
        self,
        variance_model: VarianceModel | None = None,
        *,
        score: Score | str = "ecr",
        shifts: int | tuple[int, int] = 16,
        yaws: Sequence[float] | Tensor | None = None,
        min_overlap: float = 0.5,
        exclusion_radius: int = 3,
        coarse_factor: int = 1,
        coarse_peaks: int = 3,
        resample: str = "nearest",
        search: str = "exhaustive",
        cheap_bins: int = 4,
    ) -> None:
        super().__init__()
        self.variance_model = check_variance_model(variance_model)
        self.score = as_score(score)
        self.shifts = check_shifts(shifts)
        self.register_buffer("yaws", torch.tensor(_check_yaws(yaws), dtype=torch.float64), persistent=False)
        self.options = {
            "min_overlap": min_overlap,
            "exclusion_radius": exclusion_radius,
            "coarse_factor": coarse_factor,
            "coarse_peaks": coarse_peaks,
            "resample": check_option("resample", resample, RESAMPLING),
            "search": check_option("search", search, SEARCHES),
            "cheap_bins": check_bins(cheap_bins, "cheap_bins"),
        }
        _check_search_settings(min_overlap, exclusion_radius, coarse_factor, coarse_peaks, search)
        if search == "two_stage":
            _check_two_stage(self.score, coarse_factor, cheap_bins)

    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        center: tuple[int, int] | Tensor | None = None,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Localization:
        """Localize ``captured`` ``(B, 1, h, w)`` in ``reference``; ``variance`` per call unless a model is stored."""
        return localize(
            captured,
            reference,
            call_variance("Localizer", variance, self.variance_model),
            score=self.score,
            shifts=self.shifts,
            center=center,
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


def _check_center(center, batch: int, map_shape: tuple[int, int], device: torch.device) -> Tensor:
    """``(B, 2)`` int64 map cells of the captured centre at the prior pose."""
    if center is None:
        return torch.tensor([[map_shape[0] // 2, map_shape[1] // 2]], device=device).expand(batch, 2)
    if isinstance(center, Tensor):
        if center.is_floating_point() or center.is_complex() or center.shape not in ((2,), (batch, 2)):
            raise ValueError(
                f"center must be (row, col) or an integer tensor of shape (2,) or ({batch}, 2), got "
                f"{center.dtype} {tuple(center.shape)}"
            )
        return center.to(device=device, dtype=torch.int64).reshape(-1, 2).expand(batch, 2)
    if (
        not isinstance(center, (tuple, list))
        or len(center) != 2
        or not all(isinstance(value, int) and not isinstance(value, bool) for value in center)
    ):
        raise ValueError(f"center must be (row, col) integers or a (B, 2) integer tensor, got {center!r}")
    return torch.tensor([list(center)], device=device).expand(batch, 2)


def _captured_valid(captured: Tensor, captured_mask: Tensor | None, variance) -> Tensor:
    """``(B, 1, h, w)`` bool: the given mask and the variance model's, each read by ``utils.layout.mask_map``."""
    valid = torch.ones_like(captured, dtype=torch.bool)
    masks = [("captured_mask", captured_mask)]
    if isinstance(variance, VarianceModel):
        masks.append(("variance.valid_mask", variance.valid_mask(captured)))
    for name, mask in masks:
        if mask is not None:
            valid = valid & mask_map(name, mask, captured).view_as(captured)
    check_mask_not_empty("captured_mask", valid.flatten(1))
    _check_something_to_match(captured, valid)
    return valid


def _check_something_to_match(captured: Tensor, valid: Tensor) -> None:
    """Raise :class:`NoCandidateError` if a sample's valid pixels hold one value (one pixel, a flat image).

    Every placement of such an image scores alike: the surface is flat and its "peak" would be the window's corner.
    """
    values = captured.flatten(1)
    keep = valid.flatten(1)
    large = torch.finfo(values.dtype).max
    flat = torch.where(keep, values, -large).amax(1) <= torch.where(keep, values, large).amin(1)
    if bool(flat.any()):
        samples = flat.nonzero()[:, 0].tolist()
        count = int(keep[samples[0]].sum())
        raise NoCandidateError(
            f"captured sample(s) {samples} hold one value at all their {count} valid pixel(s) (shape "
            f"{tuple(captured.shape[2:])}): every placement scores alike, there is nothing to match; pass an image "
            "with some texture"
        )


def _variance_map(captured: Tensor, variance, valid: Tensor) -> Tensor | None:
    """``(B, 1, h, w)`` variance in the captured dtype (> 0 where ``valid``, 1 elsewhere); ``None`` without one."""
    if variance is None:
        return None
    if isinstance(variance, VarianceModel):
        variance = variance(captured)
    return variance_map("variance", variance, captured, captured.dtype, valid.flatten(1)).view_as(captured)


def _reference_valid(reference: Tensor, reference_mask: Tensor | None) -> Tensor:
    """``(1 or B, 1, Hm, Wm)`` bool, one mask for all references or one per reference."""
    if reference_mask is None:
        return torch.ones_like(reference, dtype=torch.bool)
    return mask_map("reference_mask", reference_mask, reference, "reference").reshape(reference.shape)


RESAMPLING = ("nearest", "bilinear")
SEARCHES = ("exhaustive", "two_stage")
# Peaks of the two-stage search's cheap surface rescored first, and at most.
_CANDIDATES, _MAX_CANDIDATES = 4, 64
MAX_YAW_DEG = 1e6  # a float32 yaw of 1e6 degrees is exact to 1/16 degree; 1e300 would read as inf


def _rotated(captured: Tensor, variance: Tensor | None, valid: Tensor, yaws: list[float], resample: str):
    """Image, variance and mask of one sample ``(1, 1, h, w)`` rotated by ``-yaw`` for each yaw: ``(Y, 1, h, w)``."""
    count = len(yaws)
    captured = torch.where(valid, captured, 0.0)
    if variance is not None:
        variance = torch.where(valid, variance, 1.0)
    if all(math.remainder(yaw, 360.0) == 0 for yaw in yaws):
        expand = (count, 1, *captured.shape[2:])
        return captured.expand(expand), None if variance is None else variance.expand(expand), valid.expand(expand)
    # The turn modulo 360 degrees, exact in float64: 1e300 degrees would be inf in float32 (no pixel left), and
    # 1e10 off by hundreds of degrees.
    turns = [math.remainder(yaw, 360.0) for yaw in yaws]
    angles = -torch.tensor(turns, dtype=torch.float64).to(device=captured.device, dtype=captured.dtype)
    zero = angles == 0
    channels = [captured, valid.to(captured.dtype)]
    if variance is not None:
        channels.append(variance)
        if resample == "bilinear":
            # Bilinear resampling of a linear ramp gives back the source coordinates: their fractions give the weights.
            rows, cols = torch.meshgrid(
                *(torch.arange(size, dtype=captured.dtype, device=captured.device) for size in captured.shape[2:]),
                indexing="ij",
            )
            channels += [cols.expand_as(captured), rows.expand_as(captured)]
    stacked = torch.cat(channels, dim=1)
    turned = rotate(stacked.expand(count, -1, -1, -1), angles, mode=resample)
    # Yaw 0 keeps the exact pixels (no resampling round-off).
    turned = torch.where(zero[:, None, None, None], stacked, turned)
    rotated_valid = turned[:, 1:2] >= (_FULL_SUPPORT if resample == "bilinear" else 0.5)
    rotated_variance = None if variance is None else turned[:, 2:3]
    if variance is not None and resample == "bilinear":
        # A bilinear mix sum_k w_k v_k of independent noise has variance sum_k w_k^2 sigma_k^2 (sigma locally even).
        fraction = turned[:, 3:5] - turned[:, 3:5].floor()
        squares = fraction.square() + (1 - fraction).square()
        rotated_variance = rotated_variance * squares[:, :1] * squares[:, 1:]
    return turned[:, :1], rotated_variance, rotated_valid


def _pooled(images: Tensor, factor: int) -> Tensor:
    return torch.nn.functional.avg_pool2d(images, factor, factor)


class _Search:
    """Windows around the prior poses and the surfaces over them."""

    def __init__(
        self, captured, variance, captured_valid, reference, reference_valid, centers, radius, yaws, samples, resample
    ) -> None:
        self.captured, self.variance, self.captured_valid = captured, variance, captured_valid
        self.resample = resample
        self.reference, self.reference_valid = reference, reference_valid
        self.radius, self.yaws, self.samples = radius, yaws, samples
        height, width = captured.shape[2:]
        # Map cell of the captured top-left pixel at shift (-ry, -rx), per sample.
        self.origins = centers - torch.tensor([height // 2 + radius[0], width // 2 + radius[1]], device=captured.device)

    @classmethod
    def prepare(
        cls, captured, reference, variance, captured_mask, reference_mask, centers, radius, yaws, samples, resample
    ) -> _Search:
        """The search over checked settings: masks combined, the variance as a map; ``samples``: a score per sample."""
        captured_valid = _captured_valid(captured, captured_mask, variance)
        variance = _variance_map(captured, variance, captured_valid)
        reference_valid = _reference_valid(reference, reference_mask)
        return cls(
            captured, variance, captured_valid, reference, reference_valid, centers, radius, yaws, samples, resample
        )

    def _window(self, sample: int, top: int, left: int, rows: int, cols: int, factor: int = 1):
        """Map section ``(1, 1, rows, cols)`` at ``(top, left)`` on the map pooled by ``factor``, and its mask."""
        index = sample if self.reference.shape[0] > 1 else 0
        mask_index = sample if self.reference_valid.shape[0] > 1 else 0
        reference = self.reference[index : index + 1]
        reference_valid = self.reference_valid[mask_index : mask_index + 1]
        if factor > 1:
            reference_valid = _pooled(reference_valid.to(reference.dtype), factor) >= _FULL_SUPPORT
            reference = _pooled(torch.where(self.reference_valid[mask_index : mask_index + 1], reference, 0.0), factor)
        window = reference.new_zeros(1, 1, rows, cols)
        valid = torch.zeros(1, 1, rows, cols, dtype=torch.bool, device=reference.device)
        map_rows, map_cols = reference.shape[2:]
        row_low, row_high = max(top, 0), min(top + rows, map_rows)
        col_low, col_high = max(left, 0), min(left + cols, map_cols)
        if row_low < row_high and col_low < col_high:
            target = (..., slice(row_low - top, row_high - top), slice(col_low - left, col_high - left))
            window[target] = reference[..., row_low:row_high, col_low:col_high]
            valid[target] = reference_valid[..., row_low:row_high, col_low:col_high]
        return window, valid

    def _rotations(self, sample: int, yaws: list[float]):
        variance = None if self.variance is None else self.variance[sample : sample + 1]
        return _rotated(
            self.captured[sample : sample + 1], variance, self.captured_valid[sample : sample + 1], yaws, self.resample
        )

    def _surface(self, sample, captured, variance, valid, window, window_valid, min_overlap, surface_fn=None) -> Tensor:
        """``(Y, Sy, Sx)`` scores of one sample's rotations, by the sample's score or by ``surface_fn``.

        ``-inf`` below the overlap rule, for yaws that lose every pixel, on empty windows. ``surface_fn`` takes
        ``(captured, window, variance, captured_mask, reference_mask)`` and returns a
        :class:`~enmi_torch.placement.Surface`.
        """
        rows, cols = window.shape[2] - captured.shape[2] + 1, window.shape[3] - captured.shape[3] + 1
        result = captured.new_full((captured.shape[0], rows, cols), -math.inf, dtype=self.captured.dtype)
        kept = valid.flatten(1).any(1)
        if not bool(window_valid.any()) or not bool(kept.any()):
            return result
        captured, valid = captured[kept], valid[kept]
        surface_fn = surface_fn or self._score_surface(sample)
        surface = surface_fn(captured, window, None if variance is None else variance[kept], valid, window_valid)
        needed = min_overlap * valid.flatten(1).sum(1).to(surface.overlap.dtype)
        enough = surface.overlap >= needed[:, None, None] - 0.5
        result[kept] = torch.where(enough, surface.score, -math.inf).to(result.dtype)
        return result

    def _score_surface(self, sample: int):
        """The surface function of the sample's score."""
        score = self.samples[sample]

        def surface(captured, window, variance, captured_mask, reference_mask):
            return score.surface(captured, window, variance, captured_mask=captured_mask, reference_mask=reference_mask)

        return surface

    def exhaustive(self, min_overlap: float) -> Tensor:
        """``(B, Y, 2 ry + 1, 2 rx + 1)`` surface over every shift and yaw."""
        height, width = self.captured.shape[2:]
        rows, cols = height + 2 * self.radius[0], width + 2 * self.radius[1]
        surfaces = []
        for sample in range(self.captured.shape[0]):
            window, window_valid = self._window(sample, *self.origins[sample].tolist(), rows, cols)
            captured, variance, valid = self._rotations(sample, self.yaws)
            surfaces.append(self._surface(sample, captured, variance, valid, window, window_valid, min_overlap))
        return torch.stack(surfaces)

    def two_stage(self, min_overlap: float, cheap_bins: int) -> Tensor:
        """``(B, Y, 2 ry + 1, 2 rx + 1)``: a cheap surface over every shift and yaw, exact ECR around its peaks."""
        height, width = self.captured.shape[2:]
        rows, cols = height + 2 * self.radius[0], width + 2 * self.radius[1]
        surfaces = []
        for sample in range(self.captured.shape[0]):
            window, window_valid = self._window(sample, *self.origins[sample].tolist(), rows, cols)
            captured, variance, valid = self._rotations(sample, self.yaws)
            exact = self.samples[sample]
            # The exact stage bins the map by the score's range, as the exhaustive search: refuse a map in one bin.
            flat, flat_valid = window.reshape(1, -1), window_valid.reshape(1, -1)
            check_resolved_by_bins("reference", flat, flat_valid, exact.bins, exact.value_range)
            # The cheap stage: few bins over the window's values, with their own default model variance.
            cheap_range = cheap_value_range(window, window_valid)
            cheap_score = exact.replace(bins=cheap_bins, value_range=cheap_range, model_variance=None)
            cheap_fn = cheap_score._rough_surface
            cheap = self._surface(sample, captured, variance, valid, window, window_valid, min_overlap, cheap_fn)
            scorer = functools.partial(
                exact._placement_scores,
                rotations=(captured, variance, valid),
                window=(window, window_valid),
                min_overlap=min_overlap,
                cheap=cheap,
            )
            surfaces.append(rescore_peaks(cheap, scorer, _CANDIDATES, _MAX_CANDIDATES, complete_best=True))
        return torch.stack(surfaces)

    def coarse_to_fine(self, min_overlap: float, factor: int, peaks: int, exclusion_radius: int) -> Tensor:
        """Coarse surface on ``factor``-pooled images, then full-resolution surfaces around its best peaks."""
        height, width = self.captured.shape[2:]
        if height < factor or width < factor:
            raise ValueError(f"coarse_factor must not exceed the captured image size {(height, width)}, got {factor}")
        radius_y, radius_x = self.radius
        shape = (self.captured.shape[0], len(self.yaws), 2 * radius_y + 1, 2 * radius_x + 1)
        full = self.captured.new_full(shape, -math.inf)
        evaluated = torch.zeros(shape, dtype=torch.bool)
        for sample in range(self.captured.shape[0]):
            rotations = self._rotations(sample, self.yaws)
            captured, variance, valid = rotations
            coarse_local = _pooled(captured * valid, factor)
            coarse_valid = _pooled(valid.to(captured.dtype), factor) >= _FULL_SUPPORT
            coarse_variance = (
                None if variance is None else _pooled(torch.where(valid, variance, 1.0), factor) / factor**2
            )
            # Coarse candidates are the shifts whose captured top-left lands on a multiple of the factor.
            top, left = self.origins[sample].tolist()
            first_row, first_col = -(-top // factor), -(-left // factor)
            last_row, last_col = (top + 2 * radius_y) // factor, (left + 2 * radius_x) // factor
            window, window_valid = self._window(
                sample,
                first_row,
                first_col,
                last_row - first_row + coarse_local.shape[2],
                last_col - first_col + coarse_local.shape[3],
                factor,
            )
            coarse = self._surface(
                sample, coarse_local, coarse_variance, coarse_valid, window, window_valid, min_overlap
            )
            for yaw_index, row, col in _separated_peaks(coarse, peaks, max(1, exclusion_radius // factor)):
                fine_row, fine_col = (first_row + row) * factor - top, (first_col + col) * factor - left
                self._refine(full, evaluated, sample, rotations, yaw_index, fine_row, fine_col, factor, min_overlap)
            # The fine peak needs its 3 x 3 shifts and both neighbouring yaws for the sub-cell fit: fill them in.
            for _ in range(len(self.yaws) + 1):
                if not bool(torch.isfinite(full[sample]).any()):
                    break
                yaw_index, rest = divmod(int(full[sample].flatten().argmax()), shape[2] * shape[3])
                row, col = divmod(rest, shape[3])
                if not self._refine(full, evaluated, sample, rotations, yaw_index, row, col, 1, min_overlap):
                    break
        return full

    def _refine(self, full, evaluated, sample, rotations, yaw_index, row, col, reach, min_overlap) -> bool:
        """Evaluate every shift within ``reach`` of ``(row, col)`` at a yaw and its neighbours; False if all were."""
        height, width = self.captured.shape[2:]
        row_low, row_high = max(row - reach, 0), min(row + reach, full.shape[2] - 1)
        col_low, col_high = max(col - reach, 0), min(col + reach, full.shape[3] - 1)
        region = (slice(row_low, row_high + 1), slice(col_low, col_high + 1))
        yaw_indices = [
            k
            for k in (yaw_index - 1, yaw_index, yaw_index + 1)
            if 0 <= k < full.shape[1] and not bool(evaluated[(sample, k, *region)].all())
        ]
        if not yaw_indices:
            return False
        top, left = self.origins[sample].tolist()
        window, window_valid = self._window(
            sample, top + row_low, left + col_low, row_high - row_low + height, col_high - col_low + width
        )
        captured, variance, valid = rotations
        fine = self._surface(
            sample,
            captured[yaw_indices],
            None if variance is None else variance[yaw_indices],
            valid[yaw_indices],
            window,
            window_valid,
            min_overlap,
        )
        full[(sample, yaw_indices, *region)] = fine
        evaluated[(sample, yaw_indices, *region)] = True
        return True
