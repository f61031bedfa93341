"""One stage of :func:`~enmi_torch.registration.register`: its images, the pixels that count, Levenberg-Marquardt.

A stage compares the captured images and the map's samples under them, both blurred by one Gaussian (``sigma``
cells; 0: none) on the captured image's grid, over the pixels that count: the same normalised kernel for both, so the
two stay the same blur of the scene for any pose and yaw, up to the image's border and around masked pixels. The
captured pixels' noise variance goes through the same blur (``sum_k g_k^2 sigma_k^2 / (sum_k g_k)^2``). The pixels
that count and the score's weights are read once, at the registration's start pose; the response is refitted at every
pose (the profiled, variable-projection fit) and the pose moves by Levenberg-Marquardt steps on the Gauss-Newton
normal equations, evaluating only the images still moving.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.registration.response_fit import ResponseFit
from enmi_torch.registration.warp import PreparedMap, gaussian_taps, separable, yaw_motion
from enmi_torch.scores import Score


def check_counting(valid: Tensor, pose: Tensor, map_shape, margin: float, masked: bool) -> None:
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


class Stage:
    """The (blurred) images of one stage and the pixels of the captured images that may count.

    Args:
        captured: ``(B, 1, h, w)`` in the compute dtype; non-finite pixels do not count.
        reference: ``(1 or B, 1, Hm, Wm)`` in the compute dtype; non-finite cells are unobserved.
        noise: the captured pixels' noise variance (a number or broadcastable to ``captured``), or ``None`` (NCC).
        captured_mask, reference_mask: bool, broadcastable: ``False`` pixels or cells do not count.
        score: a least-squares score (ECR, NCC).
        sigma: the stage's Gaussian blur on the captured grid, cells (0: none).
        margin: cells a counting sample keeps from the map's border and unobserved cells; the largest move.
        interpolation: how the map is sampled between its cells.
    """

    def __init__(
        self, captured, reference, noise, captured_mask, reference_mask, score: Score, sigma, margin, interpolation
    ) -> None:
        self.score_, self.margin, self.sigma = score, margin, sigma
        self.shape = tuple(captured.shape[-2:])
        self.masked = captured_mask is not None
        valid = torch.isfinite(captured)
        if captured_mask is not None:
            valid = valid & captured_mask.expand_as(captured)
        self.captured, self.captured_valid = torch.where(valid, captured, 0.0), valid
        self.noise = None if noise is None else torch.as_tensor(noise, dtype=captured.dtype, device=captured.device)
        self.map = PreparedMap(reference, reference_mask, interpolation)
        self.map_shape = reference.shape[-2:]
        self.kernel = gaussian_taps(sigma, captured) if sigma > 0 else None

    def setup(self, pose: Tensor) -> ResponseFit:
        """The score's fit with the pixels that count at ``pose`` and the weights read there.

        Sets the stage's captured values, blurred over the pixels that count at ``pose`` (pixels off the map or on
        unobserved cells there must not bleed into the others), and the blur's weights for the map's samples.
        """
        warped, valid, _ = self.map.warp(pose.to(self.captured.dtype), self.shape, self.margin)
        valid = valid & self.captured_valid
        check_counting(valid, pose, self.map_shape, self.margin, self.masked)
        self.counted = valid.to(self.captured.dtype)
        values, noise = self.captured, self.noise
        if self.kernel is not None:
            self.mass = separable(self.counted, self.kernel).clamp_min(1e-12)
            values = self.blurred(values)
            if noise is not None:
                spread = separable(noise.expand_as(values) * self.counted, self.kernel.square())
                noise = torch.where(valid, spread / self.mass.square(), 1.0)
            warped = self.blurred(warped)
        self.values = torch.where(valid, values, 0.0)
        return ResponseFit.of(self.score_, self.values, warped, noise, valid)

    def blurred(self, images: Tensor, rows: Tensor | None = None) -> Tensor:
        """``images`` ``(K, C, h, w)`` blurred over the pixels that count (of the images ``rows``; ``None``: all)."""
        if self.kernel is None:
            return images
        counted, mass = (self.counted, self.mass) if rows is None else (self.counted[rows], self.mass[rows])
        batch, channels = images.shape[:2]
        spread = separable((images * counted).reshape(batch * channels, 1, *self.shape), self.kernel)
        return spread.view(batch, channels, *self.shape) / mass

    def score_with(self, fit: ResponseFit, pose: Tensor) -> Tensor:
        """``(B,)`` the score at ``pose`` with the pixels and weights of ``fit`` (differentiable in ``pose``)."""
        warped, _, _ = self.map.warp(pose.to(self.captured.dtype), self.shape, None)
        return fit.solve(self.values.flatten(1), self.blurred(warped).flatten(1))[2]

    def residuals(self, fit: ResponseFit, pose: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Weighted residuals ``(K, N)``, their Jacobian ``(K, N, 3)`` in the pose ``(x, y, yaw)`` ``(K, 3)``, scores.

        ``rows``: ``(K,)`` the images the poses are of (``fit`` is theirs); ``None``: all, in order. The score (float64
        ``(K,)``) is what a step must raise: the residuals' sum of squares and, for the shrunk response, its pull.
        """
        at = pose.to(self.captured.dtype)
        warped, _, slopes = self.map.warp(at, self.shape, None, gradient=True, rows=rows)
        x_per_yaw, y_per_yaw = yaw_motion(at, self.shape)
        slope_x, slope_y = slopes[:, 0, ..., 0], slopes[:, 0, ..., 1]
        # d sample / d (x, y, yaw) per pixel, blurred like the samples (the blur is linear).
        per_pose = self.blurred(torch.stack([slope_x, slope_y, slope_x * x_per_yaw + slope_y * y_per_yaw], 1), rows)
        values = self.values.flatten(1) if rows is None else self.values.flatten(1)[rows]
        residual, slope, score = fit.solve(values, self.blurred(warped, rows).flatten(1))
        jacobian = -(fit.weights.sqrt() * slope)[..., None] * per_pose.flatten(2).transpose(1, 2)
        return residual, jacobian, score.double()

    def run(
        self, fit: ResponseFit, pose: Tensor, start: Tensor, iterations: int, tolerance: float
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Levenberg-Marquardt from ``pose`` (float64 ``(B, 3)``): pose, steps, converged, the scores at both ends.

        The scores (float64 ``(B,)``, with ``fit``) are those at the pose returned and at ``pose``. A step that would
        move ``(x, y)`` more than ``margin`` cells from ``start`` ends that image's refinement (not converged): its
        pixels were read at ``start``. Each step evaluates the images still moving only.
        """
        batch = pose.shape[0]
        pose = pose.clone()
        damping = torch.full((batch,), 1e-3, dtype=torch.float64, device=pose.device)
        steps = torch.zeros(batch, dtype=torch.int64, device=pose.device)
        done = torch.zeros(batch, dtype=torch.bool, device=pose.device)
        converged = torch.zeros(batch, dtype=torch.bool, device=pose.device)
        residual, jacobian, score = self.residuals(fit, pose)
        first = score.clone()
        for _ in range(iterations):
            active = (~done).nonzero()[:, 0]
            if len(active) == 0:
                break
            normal = (jacobian[active].transpose(1, 2) @ jacobian[active]).double()
            gradient = (jacobian[active].transpose(1, 2) @ residual[active, :, None])[..., 0].double()
            diagonal = normal.diagonal(dim1=1, dim2=2).clamp_min(1e-12)
            damped = normal + torch.diag_embed(damping[active, None] * diagonal)
            step = -torch.linalg.solve(damped, gradient)
            trial = pose[active] + step
            left = ((trial[:, :2] - start[active, :2]).abs() > self.margin).any(1)
            new_residual, new_jacobian, new_score = self.residuals(fit.rows(active), trial, active)
            better = (new_score >= score[active]) & ~left
            gain = new_score - score[active]
            stalled = better & (gain <= 1e-10 * score[active].abs().clamp_min(1e-300))  # the fit no longer improves
            kept = active[better]
            pose[kept], score[kept] = trial[better], new_score[better]
            residual[kept], jacobian[kept] = new_residual[better], new_jacobian[better]
            damping[active] = torch.where(better, damping[active] / 10, damping[active] * 10).clamp(1e-9, 1e9)
            steps[active] += 1
            small = step.abs().amax(1) < tolerance
            converged[active] = (small & ~left) | stalled
            done[active] = small | stalled | left | (damping[active] >= 1e9)
        held = converged & ~((pose[:, :2] - start[:, :2]).abs() > self.margin).any(1)
        return pose, steps, held, score, first
