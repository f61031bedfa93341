"""What the searches and :func:`~enmi_torch.register` ask of ECR: its declared traits' methods.

``"two_stage"`` (a binned or shrunk response): :meth:`ECRTraits.rough_score`, :meth:`ECRTraits.rough_surface`,
:meth:`ECRTraits.placement_scores`; ``"least_squares"``: :meth:`ECRTraits.response_basis` and
:meth:`ECRTraits.least_squares_fit` (see :attr:`~enmi_torch.scores.Score.traits`). :class:`~enmi_torch.ECR` takes
them from :class:`ECRTraits`, which reads the score's options and estimates.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.placement.inputs import Surface, check_inputs
from enmi_torch.scores.base import LeastSquaresFit, ResponseBasis, Score
from enmi_torch.scores.ecr_model_variance import MODEL_VARIANCE_ESTIMATE, default_model_variance
from enmi_torch.scores.ecr_placements import cheap_value_range, ecr_placement_scores, rough_ecr_surface
from enmi_torch.utils.checks import check_resolved_by_bins


class ECRTraits:
    """The two-stage search's stages and the least-squares fit of :class:`~enmi_torch.ECR` (a mix-in of it)."""

    def rough_score(self, bins: int, window: Tensor, window_mask: Tensor | None = None) -> Score:
        """This score with ``bins`` bins over the window's 2nd to 98th percentile and their default model variance.

        ``window`` ``(1, 1, Hw, Ww)`` is the map section a two-stage search scores in, ``window_mask`` its valid cells
        (bool, same shape; ``None``: all). Few bins still split the window's values. Raises ``ValueError`` if this
        score's own bins leave every valid cell in one bin (its exact stage could not tell placements apart).
        """
        self._check_two_stage("first stage")
        if window_mask is None:
            window_mask = torch.ones_like(window, dtype=torch.bool)
        flat, flat_valid = window.reshape(1, -1), window_mask.reshape(1, -1)
        check_resolved_by_bins("reference", flat, flat_valid, self.bins, self.value_range)
        value_range = cheap_value_range(window, window_mask)  # its fixed tau^2 has no misfit to shape
        return self.replace(bins=bins, value_range=value_range, model_variance=None, misfit="independent")

    def rough_surface(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Surface:
        """:meth:`surface` ranked by free bin means, with the occupied bins read from the weight sums (a cheap stage).

        See :func:`~enmi_torch.scores.ecr_placements.rough_ecr_surface`.
        """
        self._check_two_stage("rough surface")
        self.check_variance(variance)
        inputs = check_inputs(captured, reference, captured_mask, reference_mask, self.value_range, variance)
        return rough_ecr_surface(inputs, self._options)

    def placement_scores(
        self, placements: Tensor, *, rotations: tuple, window: tuple, min_overlap: float, rough: Tensor
    ) -> Tensor:
        """Exact ECR ``(P,)`` at placements ``(P, 3)``.

        See :func:`~enmi_torch.scores.ecr_placements.ecr_placement_scores`.
        """
        self._check_two_stage("exact rescoring")
        return ecr_placement_scores(placements, rotations, window, min_overlap, rough, self._options)

    def _check_two_stage(self, what: str) -> None:  # the linear response has no bins to rank by
        self.require("two_stage", f"the {what} of a two-stage search")

    def response_basis(self) -> ResponseBasis:
        """A knot on each bin centre over ``value_range`` (the binned and shrunk responses), or the affine response."""
        return ResponseBasis(0) if self.response == "linear" else ResponseBasis(self.bins, self.value_range)

    def least_squares_fit(
        self, captured: Tensor, reference: Tensor, variance: Tensor | None, valid: Tensor
    ) -> LeastSquaresFit:
        """Weights ``1 / (sigma^2 + tau^2)`` and, for the shrunk response, the pull ``1 / delta^2`` toward a line.

        ``tau^2`` and ``delta^2`` are this alignment's estimates (:meth:`model_variance_of`,
        :meth:`response_variance_of`) or the fixed numbers. A ``delta^2`` of 0 (the line) is taken as ``10^-6`` bin
        widths squared: a pull that leaves the knots on a line within round-off.
        """
        batch = captured.shape[0]
        reference = reference.detach()
        noise = torch.as_tensor(variance, dtype=captured.dtype, device=captured.device).expand_as(captured)
        if self.model_variance == MODEL_VARIANCE_ESTIMATE:
            tau2 = self.model_variance_of(captured, reference, noise, valid_mask=valid)
        else:
            fixed = self.model_variance
            if fixed is None:
                fixed = default_model_variance(self.bins, self.value_range)
            tau2 = torch.full((batch,), fixed, dtype=torch.float64, device=captured.device)
        mask = valid.reshape(batch, -1).to(captured.dtype)
        total = noise.reshape(batch, -1) + tau2.to(captured.dtype).reshape(batch, -1)  # (B, 1) or a regional map
        weights = torch.where(mask > 0, mask / total.clamp_min(torch.finfo(captured.dtype).tiny), 0.0)
        if self.response != "shrunk":
            return LeastSquaresFit(weights)
        response_variance = self.response_variance_of(captured, reference, noise, valid_mask=valid)
        floor = 1e-6 * ((self.value_range[1] - self.value_range[0]) / self.bins) ** 2
        return LeastSquaresFit(weights, response_variance.to(captured.dtype).clamp_min(floor).reciprocal())
