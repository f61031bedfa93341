"""The score surfaces one filter step reads: over the belief's window, the wide relocalization window, a registration.

Each is one :func:`~enmi_torch.localize` (or :func:`~enmi_torch.register`) per vehicle, run without gradient; a window
without a candidate (off the map, a frame fully masked) reads as a flat log-likelihood. Each vehicle is scored by its
held score where it holds one (fitted at the peak of a frame the tracker trusted, :meth:`FrameSearch.held_fit`,
:class:`~enmi_torch.tracking.TrackerSettings`' ``noise_model``), else by the tracker's score.

The window's surface is the belief's likelihood as it is: its search has no finalist stage
(``SearchStrategy(finalists=0)``; a finalist would choose a pose, which the belief does not take). The wide search
chooses a pose, with localize's finalist stage.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.localization.candidates import rotate_captured
from enmi_torch.localization.peak import NoCandidateError
from enmi_torch.localization.search import localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.registration.refine import register
from enmi_torch.scores import Score
from enmi_torch.tracking.belief import Belief, finite_floor
from enmi_torch.tracking.calibration import grid_temperature
from enmi_torch.tracking.health import peak_z_score
from enmi_torch.utils.layout import variance_map
from enmi_torch.variance.base import VarianceModel

WINDOW_SEARCH = SearchStrategy(finalists=0)  # the window's surface is the likelihood: no pose is chosen from it


class FrameSearch:
    """Score surfaces of the captured images over a belief's window and over the wide relocalization window.

    One per filter step: it holds the frame (``captured`` ``(B, 1, h, w)``, its ``variance`` and ``captured_mask``),
    the map and the scores (``score`` for every vehicle, or ``held[vehicle]`` where that is not ``None``), and counts
    each vehicle's valid pixels once (the log-likelihood is ``score * n_valid``).
    """

    def __init__(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | VarianceModel | None,
        captured_mask: Tensor | None,
        score: Score,
        held: tuple[Score | None, ...] | None = None,
    ) -> None:
        self.captured, self.reference, self.variance, self.mask = captured, reference, variance, captured_mask
        held = held or (None,) * captured.shape[0]
        self.score, self.scores = score, [score if one is None else one for one in held]
        valid = torch.ones_like(captured, dtype=torch.bool)
        if captured_mask is not None:
            valid = valid & self._per_vehicle(captured_mask, slice(None)).expand_as(captured)
        if isinstance(variance, VarianceModel):
            model_mask = variance.valid_mask(captured)
            if model_mask is not None:
                valid = valid & model_mask
        self.valid = valid
        self.valid_count = valid.flatten(1).sum(1).double()

    def _per_vehicle(self, values, vehicle):
        """``values`` for vehicle(s) ``vehicle``: a per-vehicle batch is sliced, a shared one kept."""
        if isinstance(values, Tensor) and values.ndim == 4 and values.shape[0] > 1:
            return values[vehicle]
        return values

    def _localize(self, vehicle: int, center: Tensor, yaws: list[float], shifts: int | tuple[int, int], **options):
        """The one :func:`~enmi_torch.localize` about the belief's ``center`` ``(row, col)``, by the vehicle's score."""
        return localize(
            self.captured[vehicle : vehicle + 1],
            self.reference,
            self._per_vehicle(self.variance, slice(vehicle, vehicle + 1)),
            shifts=shifts,
            around=center.reshape(1, 2).flip(1),
            yaws=yaws,
            captured_mask=self._per_vehicle(self.mask, slice(vehicle, vehicle + 1)),
            score=self.scores[vehicle],
            **options,
        )

    def window(self, belief: Belief, only: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Raw log-likelihood, best score, its robust z-score and grid temperature over the belief's window.

        They are ``score * n_valid`` ``(B, Y, Sy, Sx)`` and ``(B,)`` each (:func:`grid_temperature`).
        A vehicle whose window has no candidate gets a flat log-likelihood (zeros) and NaN for the rest.
        """
        vehicles = range(belief.log_prob.shape[0]) if only is None else [only]
        likelihoods, scores, z_scores, temperatures = [], [], [], []
        yaws = belief.yaws()
        for vehicle in vehicles:
            try:
                if not bool(self.valid_count[vehicle] > 0):
                    raise NoCandidateError(f"captured image {vehicle} has no valid pixel")  # a frame fully masked
                yaw_list = yaws[vehicle].tolist()
                found = self._localize(vehicle, belief.center[vehicle], yaw_list, belief.radius, search=WINDOW_SEARCH)
            except NoCandidateError:
                nothing = torch.tensor(math.nan, dtype=torch.float64, device=belief.log_prob.device)
                likelihoods.append(torch.zeros_like(belief.log_prob[vehicle]))
                scores.append(nothing)
                z_scores.append(nothing)
                temperatures.append(nothing)
                continue
            surface = finite_floor(found.surface[0].double())
            log_likelihood = surface * self.valid_count[vehicle].to(surface.device)
            likelihoods.append(log_likelihood)
            scores.append(surface.max())
            z_scores.append(peak_z_score(log_likelihood, min_spread=1.0))
            temperatures.append(grid_temperature(log_likelihood[None])[0])
        return torch.stack(likelihoods), torch.stack(scores), torch.stack(z_scores), torch.stack(temperatures)

    def refined(self, pose: Tensor, used: Tensor, refined: Tensor) -> Tensor:
        """``refined`` with the used vehicles' rows replaced by :func:`register` from ``pose`` (one batch per score)."""
        rows = used.nonzero()[:, 0].tolist()
        for score in dict.fromkeys(self.scores[row] for row in rows):
            batch = torch.tensor([row for row in rows if self.scores[row] == score], device=pose.device)
            found = register(
                self.captured[batch],
                self.reference,
                self._per_vehicle(self.variance, batch),
                pose=pose[batch].to(torch.float64),
                score=score,
                captured_mask=self._per_vehicle(self.mask, batch),
                margin=1.0,
            )
            refined[batch] = found.pose.to(refined.dtype)
        return refined

    def held_fit(self, vehicle: int, belief: Belief, log_likelihood: Tensor) -> Score:
        """The tracker's score with its noise model fitted at the peak of ``log_likelihood`` ``(Y, Sy, Sx)``, held.

        The peak is the best cell and yaw bin of the belief's window; the pair there is the captured image, its
        variance and mask turned by ``-yaw`` as :func:`~enmi_torch.localize` turns them (nearest neighbour), and the
        map section under it (cells off the map invalid), in float64: :meth:`~enmi_torch.scores.Score.held_fit`.
        """
        yaw_index, row, col = divmod_peak(log_likelihood)
        radius_y, radius_x = belief.radius
        height, width = self.captured.shape[2:]
        top = int(belief.center[vehicle, 0]) + row - radius_y - height // 2
        left = int(belief.center[vehicle, 1]) + col - radius_x - width // 2
        yaw = float(belief.yaws()[vehicle, yaw_index])
        captured = self.captured[vehicle : vehicle + 1]
        valid = self.valid[vehicle : vehicle + 1]
        variance = self.variance
        if isinstance(variance, VarianceModel):
            variance = variance(captured)
        if variance is not None:
            variance = self._per_vehicle(variance, slice(vehicle, vehicle + 1))
            variance = variance_map("variance", variance, captured, captured.dtype, valid.flatten(1)).view_as(captured)
        captured, variance, valid = rotate_captured(captured, variance, valid, [yaw], "nearest")
        section, on_map = map_section(self.reference, top, left, height, width)
        variance = None if variance is None else variance.double()
        return self.score.held_fit(captured.double(), section, variance, valid_mask=valid & on_map)

    def wide(self, vehicle: int, belief: Belief, shifts: int, yaw_bins: int, coarse_factor: int) -> Tensor | None:
        """``(3,)`` pose ``(x, y, yaw)`` of the best match over the wide window around the belief's centre.

        ``None`` where the wide window has no candidate either.
        """
        offsets = (torch.arange(yaw_bins, dtype=torch.float64) - yaw_bins // 2) * belief.yaw_step
        yaws = (belief.yaw_center[vehicle].cpu() + offsets).tolist()
        if not bool(self.valid_count[vehicle] > 0):
            return None
        try:
            found = self._localize(
                vehicle,
                belief.center[vehicle],
                yaws,
                shifts,
                search=SearchStrategy(coarse_factor=coarse_factor),
                min_overlap=0.5,
            )
        except NoCandidateError:
            return None
        return found.pose[0].double()


def divmod_peak(log_likelihood: Tensor) -> tuple[int, int, int]:
    """``(yaw index, row, col)`` of the best value of a ``(Y, Sy, Sx)`` log-likelihood (the first of equal ones)."""
    _, rows, cols = log_likelihood.shape
    yaw_index, rest = divmod(int(log_likelihood.flatten().argmax()), rows * cols)
    return (yaw_index, *divmod(rest, cols))


def map_section(reference: Tensor, top: int, left: int, height: int, width: int) -> tuple[Tensor, Tensor]:
    """``(1, 1, height, width)`` float64 map cells from ``(top, left)`` and whether each lies on the map (0 off it)."""
    section = torch.zeros(1, 1, height, width, dtype=torch.float64, device=reference.device)
    on_map = torch.zeros(1, 1, height, width, dtype=torch.bool, device=reference.device)
    map_rows, map_cols = reference.shape[2:]
    rows = slice(max(top, 0), min(top + height, map_rows))
    cols = slice(max(left, 0), min(left + width, map_cols))
    if rows.start < rows.stop and cols.start < cols.stop:
        inside = (..., slice(rows.start - top, rows.stop - top), slice(cols.start - left, cols.stop - left))
        section[inside] = reference[..., rows, cols].double()
        on_map[inside] = True
    return section, on_map
