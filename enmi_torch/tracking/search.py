"""The score surfaces one filter step reads: over the belief's window, the wide relocalization window, a registration.

Each is one :func:`~enmi_torch.localize` (or :func:`~enmi_torch.register`) per vehicle, run without gradient; a window
without a candidate (off the map, a frame fully masked) reads as a flat log-likelihood.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.localization.peak import NoCandidateError
from enmi_torch.localization.search import localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.registration.refine import register
from enmi_torch.scores import Score
from enmi_torch.tracking.belief import Belief, finite_floor
from enmi_torch.tracking.calibration import grid_temperature
from enmi_torch.tracking.health import peak_z_score
from enmi_torch.variance.base import VarianceModel


class FrameSearch:
    """Score surfaces of the captured images over a belief's window and over the wide relocalization window.

    One per filter step: it holds the frame (``captured`` ``(B, 1, h, w)``, its ``variance`` and ``captured_mask``),
    the map and the score, and counts each vehicle's valid pixels once (the log-likelihood is ``score * n_valid``).
    """

    def __init__(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | VarianceModel | None,
        captured_mask: Tensor | None,
        score: Score,
    ) -> None:
        self.captured, self.reference, self.variance, self.mask = captured, reference, variance, captured_mask
        self.score = score
        valid = torch.ones_like(captured, dtype=torch.bool)
        if captured_mask is not None:
            valid = valid & self._per_vehicle(captured_mask, slice(None)).expand_as(captured)
        if isinstance(variance, VarianceModel):
            model_mask = variance.valid_mask(captured)
            if model_mask is not None:
                valid = valid & model_mask
        self.valid_count = valid.flatten(1).sum(1).double()

    def _per_vehicle(self, values, vehicle):
        """``values`` for vehicle(s) ``vehicle``: a per-vehicle batch is sliced, a shared one kept."""
        if isinstance(values, Tensor) and values.ndim == 4 and values.shape[0] > 1:
            return values[vehicle]
        return values

    def _localize(self, vehicle: int, center: Tensor, yaws: list[float], shifts: int | tuple[int, int], **options):
        """The one call of :func:`~enmi_torch.localize` around the belief's ``center`` ``(row, col)``."""
        return localize(
            self.captured[vehicle : vehicle + 1],
            self.reference,
            self._per_vehicle(self.variance, slice(vehicle, vehicle + 1)),
            shifts=shifts,
            around=center.reshape(1, 2).flip(1),
            yaws=yaws,
            captured_mask=self._per_vehicle(self.mask, slice(vehicle, vehicle + 1)),
            score=self.score,
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
                found = self._localize(vehicle, belief.center[vehicle], yaws[vehicle].tolist(), belief.radius)
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
        """``refined`` with the used vehicles' rows replaced by :func:`register` from ``pose`` (one batch)."""
        rows = used.nonzero()[:, 0]
        if len(rows) == 0:
            return refined
        found = register(
            self.captured[rows],
            self.reference,
            self._per_vehicle(self.variance, rows),
            pose=pose[rows].to(torch.float64),
            score=self.score,
            captured_mask=self._per_vehicle(self.mask, rows),
            margin=1.0,
        )
        refined[rows] = found.pose.to(refined.dtype)
        return refined

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
