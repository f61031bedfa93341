"""The scores of a search's candidate poses: map windows, rotated captured images and the surfaces over them.

The windows lie around the prior poses, the captured images are rotated for each yaw, and the surfaces are those that
:class:`~enmi_torch.localization.strategy.SearchStrategy` asks for.

Every surface is ``(B, Y, 2 ry + 1, 2 rx + 1)``, ``-inf`` where a candidate is below ``min_overlap`` or not scored;
each candidate is scored by the score object (:meth:`~enmi_torch.scores.Score.surface`, or, in two stages,
:meth:`~enmi_torch.scores.Score.rough_surface` and :meth:`~enmi_torch.scores.Score.placement_scores`). Conventions as
:mod:`~enmi_torch.localization.search`'s.
"""

from __future__ import annotations

import functools
import math

import torch
from kornia.geometry.transform import rotate
from torch import Tensor

from enmi_torch.localization.peak import Finalists, NoCandidateError, separated_peaks
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.placement.peaks import local_maxima, rescore_peaks
from enmi_torch.utils.checks import check_mask_not_empty
from enmi_torch.utils.layout import mask_map, variance_map
from enmi_torch.variance.base import VarianceModel

# A rotated mask pixel is valid when its bilinear value is 1 up to round-off: all four neighbours were valid.
_FULL_SUPPORT = 1 - 1e-3
RESAMPLING = ("nearest", "bilinear")
# Peaks of the two-stage search's cheap surface rescored first, and at most.
_CANDIDATES, _MAX_CANDIDATES = 4, 64


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
    """Raise :class:`~enmi_torch.localization.peak.NoCandidateError` if a sample's valid pixels hold one value.

    One pixel or a flat image: every placement of such an image scores alike, the surface is flat and its "peak"
    would be the window's corner.
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


def rotate_captured(captured: Tensor, variance: Tensor | None, valid: Tensor, yaws: list[float], resample: str):
    """Image, variance and mask of one sample ``(1, 1, h, w)`` rotated by ``-yaw`` for each yaw: ``(Y, 1, h, w)``.

    ``variance`` may be ``None`` (it is returned so); ``resample``: ``"nearest"`` or ``"bilinear"`` (see
    :func:`~enmi_torch.localize`). Invalid pixels enter as 0 (variance 1); yaws that are multiples of 360 degrees keep
    the pixels as they are.
    """
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


class CandidateSurfaces:
    """The map windows around the prior poses of a search, and the surfaces of its candidates over them.

    Build it with :meth:`prepare`; :meth:`run` gives the surface of a
    :class:`~enmi_torch.localization.strategy.SearchStrategy`.
    """

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
    ) -> CandidateSurfaces:
        """The search over checked settings: masks combined, the variance as a map; ``samples``: a score per sample."""
        captured_valid = _captured_valid(captured, captured_mask, variance)
        variance = _variance_map(captured, variance, captured_valid)
        reference_valid = _reference_valid(reference, reference_mask)
        return cls(
            captured, variance, captured_valid, reference, reference_valid, centers, radius, yaws, samples, resample
        )

    def run(self, strategy: SearchStrategy, min_overlap: float, exclusion_radius: int) -> Tensor:
        """The ``(B, Y, 2 ry + 1, 2 rx + 1)`` surface that ``strategy`` asks for."""
        if strategy.method == "two_stage":
            return self.two_stage(min_overlap, strategy.cheap_bins)
        if strategy.coarse_factor == 1:
            return self.exhaustive(min_overlap)
        return self.coarse_to_fine(min_overlap, strategy.coarse_factor, strategy.coarse_peaks, exclusion_radius)

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
        return rotate_captured(
            self.captured[sample : sample + 1], variance, self.captured_valid[sample : sample + 1], yaws, self.resample
        )

    def _surface(self, sample, captured, variance, valid, window, window_valid, min_overlap, surface_of=None) -> Tensor:
        """``(Y, Sy, Sx)`` scores of one sample's rotations, by the sample's score's surface or by ``surface_of``.

        ``-inf`` below the overlap rule, for yaws that lose every pixel, on empty windows. ``surface_of`` takes the
        arguments of :meth:`~enmi_torch.scores.Score.surface` (a score's ``rough_surface``, say).
        """
        rows, cols = window.shape[2] - captured.shape[2] + 1, window.shape[3] - captured.shape[3] + 1
        result = captured.new_full((captured.shape[0], rows, cols), -math.inf, dtype=self.captured.dtype)
        kept = valid.flatten(1).any(1)
        if not bool(window_valid.any()) or not bool(kept.any()):
            return result
        captured, valid = captured[kept], valid[kept]
        surface_of = surface_of or self.samples[sample].surface
        variance = None if variance is None else variance[kept]
        surface = surface_of(captured, window, variance, captured_mask=valid, reference_mask=window_valid)
        needed = min_overlap * valid.flatten(1).sum(1).to(surface.overlap.dtype)
        enough = surface.overlap >= needed[:, None, None] - 0.5
        result[kept] = torch.where(enough, surface.score, -math.inf).to(result.dtype)
        return result

    def _full_windows(self):
        """Per sample, in order: ``(sample, (window, window_valid), (captured, variance, valid))``.

        The map window that holds every shift of the search and the sample's rotations for every yaw.
        """
        height, width = self.captured.shape[2:]
        rows, cols = height + 2 * self.radius[0], width + 2 * self.radius[1]
        for sample in range(self.captured.shape[0]):
            window = self._window(sample, *self.origins[sample].tolist(), rows, cols)
            yield sample, window, self._rotations(sample, self.yaws)

    def exhaustive(self, min_overlap: float) -> Tensor:
        """``(B, Y, 2 ry + 1, 2 rx + 1)`` surface over every shift and yaw."""
        surfaces = []
        for sample, window, rotations in self._full_windows():
            surfaces.append(self._surface(sample, *rotations, *window, min_overlap))
        return torch.stack(surfaces)

    def two_stage(self, min_overlap: float, cheap_bins: int) -> Tensor:
        """``(B, Y, 2 ry + 1, 2 rx + 1)``: a rough surface over every shift and yaw, exact scores around its peaks."""
        surfaces = []
        for sample, (window, window_valid), (captured, variance, valid) in self._full_windows():
            exact = self.samples[sample]
            rough_of = exact.rough_score(cheap_bins, window, window_valid).rough_surface
            cheap = self._surface(sample, captured, variance, valid, window, window_valid, min_overlap, rough_of)
            scorer = functools.partial(
                exact.placement_scores,
                rotations=(captured, variance, valid),
                window=(window, window_valid),
                min_overlap=min_overlap,
                rough=cheap,
            )
            surfaces.append(rescore_peaks(cheap, scorer, _CANDIDATES, _MAX_CANDIDATES, complete_best=True))
        return torch.stack(surfaces)

    def finalists(self, surface: Tensor, count: int) -> Finalists:
        """The best ``count`` local maxima of each sample's ``(Y, Sy, Sx)`` surface, scored exactly by its score.

        Each sample's rotations for the yaws of its finalists and its full map window go to the score's
        :meth:`~enmi_torch.scores.Score.finalists`; the chosen finalist is the best exact score (the best-ranked one
        of equal scores).
        """
        batch = surface.shape[0]
        placements = torch.full((batch, count, 3), -1, dtype=torch.int64, device=surface.device)
        scores = surface.new_full((batch, count), -math.inf, dtype=torch.float64)
        height, width = self.captured.shape[2:]
        rows, cols = height + 2 * self.radius[0], width + 2 * self.radius[1]
        for sample in range(batch):
            peaks = local_maxima(surface[sample])[:count]
            if peaks.numel() == 0:
                continue
            _, size_y, size_x = surface.shape[1:]
            found = torch.stack([peaks // (size_y * size_x), peaks // size_x % size_y, peaks % size_x], 1)
            yaw_indices, index = torch.unique(found[:, 0], return_inverse=True)
            captured, variance, valid = self._rotations(sample, [self.yaws[k] for k in yaw_indices.tolist()])
            window, window_valid = self._window(sample, *self.origins[sample].tolist(), rows, cols)
            exact = self.samples[sample].finalists(
                captured,
                window,
                torch.cat([index[:, None], found[:, 1:]], 1),
                variance,
                captured_mask=valid,
                window_mask=window_valid,
            )
            placements[sample, : len(found)] = found
            scores[sample, : len(found)] = exact.to(torch.float64)
        return Finalists(placements, scores, scores.argmax(1))

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
            for yaw_index, row, col in separated_peaks(coarse, peaks, max(1, exclusion_radius // factor)):
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
