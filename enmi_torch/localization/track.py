"""Sequential localization over a drive: a Bayes (histogram) filter on the score surfaces of :func:`localize`.

The belief over the vehicle's pose is a histogram on a local window of map cells and a few yaw bins around the
predicted pose: the same ``(Y, 2 ry + 1, 2 rx + 1)`` grid as a :func:`~enmi_torch.localize` surface. One
step of the filter:

* predict: each yaw bin's mass moves by the odometry increment turned into the map at that bin's yaw, and is blurred
  by the odometry noise (a convolution with a discrete Gaussian, the sub-cell part of the increment split
  bilinearly so the mean moves by exactly the increment); the window is re-centred on the predicted pose;
* update: the score surface over the window, turned into a log-likelihood ``score * n_valid / temperature``
  (``n_valid`` the captured image's valid pixels: ECR is a Gaussian log-likelihood ratio per pixel, so
  ``temperature = 1`` is its own scale; :func:`calibrate_temperature` fits it on held-out frames for any score),
  is added to the log belief;
* read: pose and covariance are the posterior's moments (sub-cell, plus the within-cell spread ``1 / 12``);
* health: a frame whose surface has no clear peak (the best score's robust z-score below ``min_peak_z``, or below
  ``z_drop`` times the recent matches'), or whose peak the prediction rules out (more than ``max_surprise`` nats
  below the prediction's best), is not used; after ``patience`` such frames the filter searches a wider window
  (a coarse-to-fine :func:`~enmi_torch.localize`): if that search lands on the window's own peak the frame
  is used after all, and if it finds a match better than the window's by ``relocalize_odds`` nats the filter
  restarts there (relocalization).

Convention:
    A pose is ``(x, y, yaw)``: ``x`` (column) and ``y`` (row) the map cell under the captured image's centre pixel
    ``(h // 2, w // 2)``, in cells, and ``yaw`` in degrees: the captured image is the map section there rotated by
    ``yaw`` counter-clockwise as displayed, as in :func:`~enmi_torch.localize` with ``center = (y, x)``
    rounded and ``pose`` the rest (:meth:`~enmi_torch.Localization.local_to_map` gives the transform).
    Odometry is ``(du, dv, dyaw)``: the move of the captured image's centre along its own columns (``du``) and rows
    (``dv``), in cells, and the change of yaw in degrees, from the previous frame to this one; on the map the move
    is ``(dx, dy) = (cos a du + sin a dv, -sin a du + cos a dv)`` with ``a = -yaw`` (the linear part of
    ``local_to_map``). Beliefs are float64 log probabilities; searches run without gradient.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from enmi_torch._checks import check_floating, check_non_negative_int, check_option, check_positive_int, check_shifts
from enmi_torch.localization.search import localize
from enmi_torch.scores import Score, as_score, score_names
from enmi_torch.variance.base import VarianceModel

# Chi-square quantile with 2 degrees of freedom at 95 %: the (x, y) ellipse radius squared.
CHI2_95_2D = 5.991464547107979


class Belief(NamedTuple):
    """The filter's belief: a histogram over a window of map cells and yaw bins.

    Attributes:
        log_prob: ``(B, Y, 2 ry + 1, 2 rx + 1)`` float64 log probability per yaw bin and cell, laid out like a
            :class:`~enmi_torch.Localization` surface: ``[b, k, ry + i, rx + j]`` is the pose
            ``x = center[b, 1] + j``, ``y = center[b, 0] + i``, ``yaw = yaw_center[b] + (k - Y // 2) * yaw_step``.
        center: ``(B, 2)`` int64 map cell ``(row, col)`` of the window's middle cell.
        yaw_center: ``(B,)`` float64 yaw of the middle yaw bin, degrees.
        yaw_step: spacing of the yaw bins, degrees.
    """

    log_prob: Tensor
    center: Tensor
    yaw_center: Tensor
    yaw_step: float

    @property
    def radius(self) -> tuple[int, int]:
        """``(ry, rx)`` of the window."""
        return (self.log_prob.shape[2] - 1) // 2, (self.log_prob.shape[3] - 1) // 2

    def yaws(self) -> Tensor:
        """``(B, Y)`` yaw of every bin, degrees."""
        count = self.log_prob.shape[1]
        offsets = (torch.arange(count, dtype=torch.float64, device=self.log_prob.device) - count // 2) * self.yaw_step
        return self.yaw_center[:, None] + offsets


class TrackOutput(NamedTuple):
    """What one filter step reports per vehicle.

    Attributes:
        pose: ``(B, 3)`` posterior mean ``(x, y, yaw)``: map column and row in cells, yaw in degrees.
        covariance: ``(B, 3, 3)`` posterior covariance of ``(x, y, yaw)`` (cells², cells x degrees, degrees²).
        healthy: ``(B,)`` bool: this frame's match was used (a clear peak that the prediction allows).
        relocalized: ``(B,)`` bool: the filter searched the wide window this frame and restarted there.
        score: ``(B,)`` best score of the frame's surface.
        peak_z: ``(B,)`` the best score's robust z-score over the surface (``(best - median) / (1.4826 MAD)``).
    """

    pose: Tensor
    covariance: Tensor
    healthy: Tensor
    relocalized: Tensor
    score: Tensor
    peak_z: Tensor


def initial_belief(
    pose: Tensor,
    *,
    shifts: int | tuple[int, int] = 8,
    yaw_bins: int = 5,
    yaw_step: float = 1.0,
    std: tuple[float, float, float] | None = None,
) -> Belief:
    """A belief centred on ``pose``: a Gaussian of standard deviations ``std = (x, y, yaw)`` or flat (``None``).

    Args:
        pose: ``(B, 3)`` ``(x, y, yaw)`` (see the module's convention); the window's middle cell is its rounded
            position and the middle yaw bin its yaw.
        shifts: window radius ``r`` or ``(ry, rx)`` in cells.
        yaw_bins: odd number of yaw bins.
        yaw_step: yaw bin spacing in degrees.
        std: standard deviations of the Gaussian in cells and degrees, or ``None`` for a flat belief.

    Example:
        >>> belief = initial_belief(torch.tensor([[10.0, 20.0, 3.0]]), shifts=(2, 3), yaw_bins=3)
        >>> belief.log_prob.shape, belief.center.tolist(), belief.yaws().tolist()
        (torch.Size([1, 3, 5, 7]), [[20, 10]], [[2.0, 3.0, 4.0]])
    """
    pose = _check_pose("pose", pose)
    radius = check_shifts(shifts)
    yaw_bins = check_positive_int("yaw_bins", yaw_bins)
    if yaw_bins % 2 == 0:
        raise ValueError(f"yaw_bins must be odd (a middle bin on the predicted yaw), got {yaw_bins}")
    yaw_step = _check_positive("yaw_step", yaw_step)
    batch = pose.shape[0]
    center = torch.stack([pose[:, 1], pose[:, 0]], 1).round().long()
    shape = (batch, yaw_bins, 2 * radius[0] + 1, 2 * radius[1] + 1)
    log_prob = torch.zeros(shape, dtype=torch.float64, device=pose.device)
    belief = Belief(log_prob, center, pose[:, 2].clone(), yaw_step)
    if std is not None:
        if len(std) != 3 or not all(isinstance(value, (int, float)) and value > 0 for value in std):
            raise ValueError(f"std must be three numbers > 0 (x, y, yaw) or None, got {std!r}")
        x, y, yaw = _grid_poses(belief)
        log_prob = -0.5 * (
            ((x - pose[:, 0, None, None, None]) / std[0]) ** 2
            + ((y - pose[:, 1, None, None, None]) / std[1]) ** 2
            + ((yaw - pose[:, 2, None, None, None]) / std[2]) ** 2
        )
    return belief._replace(log_prob=_normalized(log_prob))


def predict(belief: Belief, odometry: Tensor, noise: Sequence[float] | Tensor) -> Belief:
    """The motion step: move the belief by the odometry increment and blur it by the odometry noise.

    Args:
        belief: the current :class:`Belief`.
        odometry: ``(B, 3)`` increment ``(du, dv, dyaw)`` in the captured image's axes (cells) and degrees (see the
            module's convention).
        noise: standard deviations ``(du, dv, dyaw)`` of the increment's error, three numbers or ``(B, 3)``.

    Returns:
        The predicted :class:`Belief`, its window re-centred on the predicted mean (whole cells and yaw bins).
        Probability is conserved up to the mass that leaves the window (not renormalised).

    Convention:
        Each yaw bin's mass moves by its own map increment (the odometry turned by that bin's yaw). The sub-cell
        part of a move is split bilinearly between the four neighbouring cells (the mean moves by exactly the
        increment) and convolved with a discrete Gaussian of the noise covariance turned into the map (point
        symmetric, so it does not move the mean); yaw likewise along the yaw bins.

    Example:
        >>> belief = initial_belief(torch.tensor([[10.0, 20.0, 0.0]]), shifts=4, yaw_bins=1, std=(0.5, 0.5, 1.0))
        >>> moved = predict(belief, torch.tensor([[2.5, -1.0, 0.0]]), (0.1, 0.1, 0.1))
        >>> pose, _ = belief_pose(moved)
        >>> pose.round(decimals=6).tolist(), round(float(moved.log_prob.exp().sum()), 6)
        ([[12.5, 19.0, 0.0]], 1.0)
    """
    _check_belief(belief)
    batch, yaw_count = belief.log_prob.shape[:2]
    odometry = _check_pose("odometry", odometry, batch)
    noise = _check_noise(noise, batch)
    peak = belief.log_prob.flatten(1).amax(1).clamp_min(-1e300)
    mass = (belief.log_prob - peak[:, None, None, None]).exp()
    # Map increment per yaw bin: local_to_map's linear part at the bin's yaw.
    angle = torch.deg2rad(-belief.yaws())
    cos, sin = angle.cos(), angle.sin()
    step_x = cos * odometry[:, 0, None] + sin * odometry[:, 1, None]
    step_y = -sin * odometry[:, 0, None] + cos * odometry[:, 1, None]
    # Re-centre the window on the predicted mean, in whole cells and yaw bins.
    x, y, yaw = _grid_poses(belief)
    total = mass.flatten(1).sum(1).clamp_min(1e-300)
    weights = mass / total[:, None, None, None]
    moved_x = ((x + step_x[:, :, None, None]) * weights).flatten(1).sum(1)
    moved_y = ((y + step_y[:, :, None, None]) * weights).flatten(1).sum(1)
    moved_yaw = ((yaw + odometry[:, 2, None, None, None]) * weights).flatten(1).sum(1)
    center = torch.stack([moved_y, moved_x], 1).round().long()
    yaw_shift = ((moved_yaw - belief.yaw_center) / belief.yaw_step).round()
    yaw_center = belief.yaw_center + yaw_shift * belief.yaw_step
    # Grid offsets of each bin's move: the increment minus the window's own move.
    offset_x = step_x - (center[:, 1] - belief.center[:, 1]).double()[:, None]
    offset_y = step_y - (center[:, 0] - belief.center[:, 0]).double()[:, None]
    translated = _translate(mass, offset_x, offset_y, _map_covariance(cos, sin, noise))
    yaw_offset = odometry[:, 2] / belief.yaw_step - yaw_shift
    mixing = _yaw_mixing(yaw_count, yaw_offset, noise[:, 2] / belief.yaw_step)
    predicted = torch.einsum("bij,bjyx->biyx", mixing, translated)
    log_prob = predicted.clamp_min(torch.finfo(torch.float64).tiny).log() + peak[:, None, None, None]
    return Belief(log_prob, center, yaw_center, belief.yaw_step)


def update(belief: Belief, log_likelihood: Tensor) -> Belief:
    """The measurement step: add ``(B, Y, Sy, Sx)`` log-likelihoods to the log belief and normalise.

    ``-inf`` or NaN likelihoods (candidates a search left out) count as the smallest finite value of the sample.

    Example:
        >>> belief = initial_belief(torch.zeros(1, 3), shifts=1, yaw_bins=1)
        >>> likelihood = torch.zeros(1, 1, 3, 3)
        >>> likelihood[0, 0, 1, 1] = 2.0  # e^2 against 1 for the 8 other cells
        >>> round(float(update(belief, likelihood).log_prob.exp()[0, 0, 1, 1]), 4)
        0.4802
    """
    _check_belief(belief)
    check_floating("log_likelihood", log_likelihood)
    if log_likelihood.shape != belief.log_prob.shape:
        raise ValueError(
            f"log_likelihood must have the belief's shape {tuple(belief.log_prob.shape)}, got "
            f"{tuple(log_likelihood.shape)}"
        )
    return belief._replace(log_prob=_normalized(belief.log_prob + _finite_floor(log_likelihood.double())))


def belief_pose(belief: Belief) -> tuple[Tensor, Tensor]:
    """Posterior pose ``(B, 3)`` ``(x, y, yaw)`` and covariance ``(B, 3, 3)`` of a belief.

    The pose is the mean of the bins, or, when one bin holds at least half of the mass, that bin refined below one
    bin by a parabola through the log belief and its neighbours along each axis. The covariance is then the Laplace
    approximation, the inverse of the parabolas' curvatures (diagonal, at most one bin² per axis); otherwise the bins'
    second moment plus the spread of a pose uniform within its cell and yaw bin (``1 / 12`` cell², ``step² / 12``).
    With a calibrated temperature (:func:`calibrate_temperature`) both are honest uncertainties.

    Example:
        >>> belief = initial_belief(torch.tensor([[5.0, 7.0, 0.0]]), shifts=2, yaw_bins=1)
        >>> log_prob = torch.tensor([-8.0, -2.0, 0.0, -4.0, -10.0]).reshape(1, 1, 1, 5) + torch.zeros(1, 1, 5, 1)
        >>> log_prob[:, :, [0, 1, 3, 4]] -= 50.0  # all but the middle row ruled out
        >>> pose, covariance = belief_pose(belief._replace(log_prob=log_prob))
        >>> pose.round(decimals=3).tolist()  # the parabola through -2, 0, -4 peaks 1/6 cell left of column 5
        [[4.833, 7.0, 0.0]]
    """
    _check_belief(belief)
    log_prob = _normalized(belief.log_prob)
    weights = log_prob.exp()
    x, y, yaw = _grid_poses(belief)
    values = torch.stack(torch.broadcast_tensors(x, y, yaw), -1).flatten(1, 3)
    flat = weights.flatten(1)[..., None]
    mean = (values * flat).sum(1)
    peak_mass, index = weights.flatten(1).max(1)
    rows, cols = log_prob.shape[2:]
    yaw_index, rest = index // (rows * cols), index % (rows * cols)
    row, col = rest // cols, rest % cols
    batch = torch.arange(log_prob.shape[0], device=log_prob.device)
    peak = values[batch, index]
    fits = [_parabola(log_prob, batch, (yaw_index, row, col), axis) for axis in (2, 1, 0)]
    offsets = torch.stack([fit[0] for fit in fits], 1)
    curvatures = torch.stack([fit[1] for fit in fits], 1)
    steps = torch.tensor([1.0, 1.0, belief.yaw_step], dtype=torch.float64, device=mean.device)
    sharp = peak_mass >= 0.5
    pose = torch.where(sharp[:, None], peak + offsets * steps, mean)
    centred = values - mean[:, None]
    moments = torch.einsum("bni,bnj->bij", centred * flat, centred) + torch.diag(steps.square() / 12)
    # Laplace: the inverse curvature of the log belief at its peak, per axis (a bin's width where it is flat).
    laplace = torch.diag_embed(steps.square() / (-curvatures).clamp_min(1.0))
    covariance = torch.where(sharp[:, None, None], laplace, moments)
    return pose, covariance


def _parabola(
    log_prob: Tensor, batch: Tensor, index: tuple[Tensor, Tensor, Tensor], axis: int
) -> tuple[Tensor, Tensor]:
    """Vertex offset in ``[-0.5, 0.5]`` bins and curvature (< 0, or -1 if none) of the parabola through the peak."""
    size = log_prob.shape[1 + axis]
    middle = index[axis]
    inside = (middle > 0) & (middle < size - 1)
    neighbours = []
    for step in (-1, 1):
        moved = list(index)
        moved[axis] = (middle + step).clamp(0, size - 1)
        neighbours.append(log_prob[batch, moved[0], moved[1], moved[2]])
    centre = log_prob[batch, index[0], index[1], index[2]]
    left, right = neighbours
    curvature = left - 2 * centre + right
    fitted = inside & (curvature < 0)
    curvature = torch.where(fitted, curvature, -1.0)
    offset = 0.5 * (left - right) / curvature
    return torch.where(fitted, offset.clamp(-0.5, 0.5), 0.0), curvature


def calibrate_temperature(
    log_likelihoods: Tensor, truth: Tensor, *, bounds: tuple[float, float] = (1e-3, 1e4)
) -> float:
    """The temperature that makes ``softmax(log_likelihood / T)`` a calibrated posterior on held-out frames.

    Args:
        log_likelihoods: ``(N, Y, Sy, Sx)`` raw log-likelihoods (``score * n_valid``) of ``N`` held-out frames
            searched around their poses; ``-inf`` where a candidate was left out.
        truth: ``(N, 3)`` true ``(row, col, yaw)`` index of each frame on the grid (real numbers: the nearest bin
            counts).
        bounds: the search range of ``T``.

    Returns:
        ``T`` minimising the mean negative log probability of the true bin (a proper scoring rule), by golden
        section search over ``log T``.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> scale = 4.0  # a log-likelihood 4 times too sharp
        >>> truth = torch.randint(2, 7, (400, 2), generator=generator).double()
        >>> offsets = torch.randn(400, 2, generator=generator)  # the true peak's distance from the measured one
        >>> rows, cols = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing="ij")
        >>> peaks = truth + offsets
        >>> log_likelihood = -0.5 * scale * ((rows - peaks[:, :1, None]) ** 2 + (cols - peaks[:, 1:, None]) ** 2)
        >>> index = torch.cat([truth, torch.zeros(400, 1)], 1)[:, [0, 1, 2]]
        >>> 2.5 < calibrate_temperature(log_likelihood[:, None], index) < 6.5
        True
    """
    check_floating("log_likelihoods", log_likelihoods)
    check_floating("truth", truth)
    if log_likelihoods.ndim != 4 or truth.shape != (log_likelihoods.shape[0], 3):
        raise ValueError(
            "log_likelihoods must be (N, Y, Sy, Sx) and truth (N, 3), got "
            f"{tuple(log_likelihoods.shape)} and {tuple(truth.shape)}"
        )
    low, high = (_check_positive("bounds", value) for value in bounds)
    yaw_count, rows, cols = log_likelihoods.shape[1:]
    index = truth.round().long()
    limits = torch.tensor([rows, cols, yaw_count], device=index.device)
    inside = ((index >= 0) & (index < limits[[0, 1, 2]])).all(1)
    if not bool(inside.any()):
        raise ValueError("truth must put at least one frame's true pose inside its grid, got none")
    values = _finite_floor(log_likelihoods.double())[inside].flatten(1)
    index = index[inside]
    true_flat = (index[:, 2] * rows + index[:, 0]) * cols + index[:, 1]

    def loss(log_temperature: float) -> float:
        scaled = values / math.exp(log_temperature)
        return float((scaled.logsumexp(1) - scaled.gather(1, true_flat[:, None])[:, 0]).mean())

    left, right = math.log(low), math.log(high)
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(80):
        first, second = right - ratio * (right - left), left + ratio * (right - left)
        if loss(first) < loss(second):
            right = second
        else:
            left = first
    return math.exp((left + right) / 2)


class Calibration(NamedTuple):
    """The score's likelihood scale and health threshold, saved next to a map.

    Attributes:
        score: the name of the score they belong to (:func:`~enmi_torch.as_score`).
        temperature: divide ``score * n_valid`` by it to get a log-likelihood.
        min_peak_z: the smallest robust z-score of a surface's peak that counts as a match.
    """

    score: str
    temperature: float
    min_peak_z: float

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON (e.g. ``map_calibration.json`` next to the map)."""
        path = Path(path)
        path.write_text(json.dumps(self._asdict(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration written by :meth:`save` (files that name the score ``metric`` too)."""
        values = json.loads(Path(path).read_text())
        if "metric" in values and "score" not in values:
            values["score"] = values.pop("metric")
        if set(values) != set(cls._fields):
            raise ValueError(f"{path}: a calibration needs keys {list(cls._fields)}, got {sorted(values)}")
        return cls(
            check_option("score", values["score"], score_names()),
            float(values["temperature"]),
            float(values["min_peak_z"]),
        )


def track_step(
    belief: Belief,
    captured: Tensor,
    reference: Tensor,
    odometry: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    captured_mask: Tensor | None = None,
    *,
    motion_noise: Sequence[float] | Tensor = (0.5, 0.5, 0.5),
    score: Score | str = "ecr",
    temperature: float = 1.0,
    min_peak_z: float = 3.0,
    max_surprise: float = 30.0,
    z_drop: float = 0.3,
    health: Health | None = None,
    patience: int = 2,
    relocalize_shifts: int = 32,
    relocalize_yaw_bins: int = 9,
    coarse_factor: int = 4,
    relocalize_odds: float = 10.0,
) -> tuple[Belief, TrackOutput, Health]:
    """One frame of the filter: predict by ``odometry``, update by the frame's score surface, read the pose.

    Args:
        belief: the belief after the previous frame (:func:`initial_belief` for the first).
        captured: ``(B, 1, h, w)`` captured images on the map's cell grid, one per vehicle.
        reference: ``(1, 1, Hm, Wm)`` the map.
        odometry: ``(B, 3)`` increment since the previous frame (see :func:`predict`).
        variance: the captured images' noise variance for a score that uses one (ECR, ENMI, mixture): a number,
            ``(h, w)``, ``(1 or B, 1, h, w)`` or a :class:`~enmi_torch.variance.VarianceModel`; ``None`` for NMI and
            NCC.
        captured_mask: bool, like ``variance``: ``False`` pixels are unobserved.
        motion_noise: standard deviations of the odometry's error ``(du, dv, dyaw)`` per frame.
        score: the score of the surfaces, a :class:`~enmi_torch.scores.Score` or its name (see
            :func:`~enmi_torch.localize`).
        temperature: ``score * n_valid / temperature`` is the log-likelihood (:func:`calibrate_temperature`).
        min_peak_z: a surface whose best score's robust z-score is below this is no match.
        max_surprise: a peak whose predicted log probability is more than this many nats below the prediction's best
            is no match (the prediction rules it out).
        z_drop: a peak z-score below this fraction of the recent matches' (:class:`Health`) is no match.
        health: the :class:`Health` from the previous step (``None`` at the start).
        patience: relocalize after this many consecutive frames without a match.
        relocalize_shifts: radius in cells of the relocalization search.
        relocalize_yaw_bins: yaw bins (of the belief's spacing) of the relocalization search.
        coarse_factor: pooling factor of the coarse-to-fine relocalization search.
        relocalize_odds: the relocalization moves the belief only if its match beats the window's best by this
            many nats of log-likelihood, or lands within 1.5 cells of the window's own peak.

    Returns:
        ``(belief, output, health)``: the posterior :class:`Belief`, the :class:`TrackOutput` and the :class:`Health`
        for the next step.
    """
    _check_belief(belief)
    score = as_score(score)
    check_floating("captured", captured)
    if captured.ndim != 4 or captured.shape[1] != 1 or captured.shape[0] != belief.log_prob.shape[0]:
        raise ValueError(
            f"captured must be (B, 1, h, w) with B = {belief.log_prob.shape[0]} (the belief's vehicles), got "
            f"{tuple(captured.shape)}"
        )
    check_floating("reference", reference)
    if reference.ndim != 4 or reference.shape[:2] != (1, 1):
        raise ValueError(f"reference must be one map (1, 1, Hm, Wm), got {tuple(reference.shape)}")
    temperature = _check_positive("temperature", temperature)
    _check_positive("min_peak_z", min_peak_z)
    _check_positive("max_surprise", max_surprise)
    _check_positive("relocalize_odds", relocalize_odds)
    _check_positive("z_drop", z_drop)
    patience = check_positive_int("patience", patience)
    relocalize_shifts = check_non_negative_int("relocalize_shifts", relocalize_shifts)
    relocalize_yaw_bins = check_positive_int("relocalize_yaw_bins", relocalize_yaw_bins)
    batch = captured.shape[0]
    health = _check_health(health, batch, captured.device)
    search = _Searcher(captured, reference, variance, captured_mask, score, temperature)
    prior = predict(belief, odometry, motion_noise)
    log_likelihood, score, peak_z = search.window(prior)
    surprise = _surprise(prior.log_prob, log_likelihood)
    # A peak far weaker than the recent matches' is a match of some other place (a kidnap, a wrong window).
    typical = torch.where(torch.isfinite(health.typical_z), health.typical_z, peak_z)
    healthy = (peak_z >= min_peak_z) & (peak_z >= z_drop * typical) & (surprise <= max_surprise)
    weak_frames = torch.where(healthy, 0, health.weak_frames + 1)
    relocalized = torch.zeros_like(healthy)
    log_prob = prior.log_prob.clone()
    center, yaw_center = prior.center.clone(), prior.yaw_center.clone()
    for vehicle in (weak_frames >= patience).nonzero()[:, 0].tolist():
        found = search.wide(vehicle, prior, relocalize_shifts, relocalize_yaw_bins, coarse_factor)
        window_peak = _peak_position(prior, log_likelihood, vehicle)
        if bool((window_peak - found[:2].to(window_peak)).abs().max() <= 1.5) and bool(peak_z[vehicle] >= min_peak_z):
            healthy[vehicle] = True  # the wide search confirms the window's own peak: use the frame
            continue
        fresh = _restart(prior, vehicle, found)
        fresh_likelihood, fresh_score, fresh_z = search.window(fresh, vehicle)
        # A jump needs a much better match than the window's, in calibrated nats.
        gain = fresh_likelihood[0].max() - log_likelihood[vehicle].max()
        if bool(fresh_z[0] >= min_peak_z) and bool(gain >= relocalize_odds):
            log_prob[vehicle] = _normalized(fresh_likelihood)[0]
            center[vehicle], yaw_center[vehicle] = fresh.center[vehicle], fresh.yaw_center[vehicle]
            score[vehicle], peak_z[vehicle], relocalized[vehicle] = fresh_score[0], fresh_z[0], True
    used = healthy & ~relocalized
    log_prob = torch.where(used[:, None, None, None], _normalized(log_prob + log_likelihood), log_prob)
    healthy = healthy | relocalized
    weak_frames = torch.where(healthy, 0, weak_frames)
    typical_z = torch.where(
        relocalized | ~torch.isfinite(health.typical_z),
        torch.where(healthy, peak_z, health.typical_z),
        torch.where(healthy, 0.7 * health.typical_z + 0.3 * peak_z, health.typical_z),
    )
    posterior = Belief(log_prob, center, yaw_center, prior.yaw_step)
    pose, covariance = belief_pose(posterior)
    output = TrackOutput(pose, covariance, healthy, relocalized, score, peak_z)
    return posterior, output, Health(weak_frames, typical_z)


class Health(NamedTuple):
    """The filter's running health per vehicle.

    Attributes:
        weak_frames: ``(B,)`` int64 consecutive frames without a usable match.
        typical_z: ``(B,)`` float64 running mean of the used matches' peak z-scores (NaN before the first).
    """

    weak_frames: Tensor
    typical_z: Tensor


def _check_health(health: object, batch: int, device: torch.device) -> Health:
    if health is None:
        return Health(
            torch.zeros(batch, dtype=torch.int64, device=device),
            torch.full((batch,), math.nan, dtype=torch.float64, device=device),
        )
    if not isinstance(health, Health) or health.weak_frames.shape != (batch,) or health.typical_z.shape != (batch,):
        raise ValueError(
            f"health must be a Health of ({batch},) tensors from the previous step or None, got {health!r}"
        )
    return health


class Tracker(nn.Module):
    """Module form of :func:`track_step`: stores the map, the settings and the running belief (streaming).

    Args:
        reference: ``(1, 1, Hm, Wm)`` or ``(Hm, Wm)`` map (a non-persistent buffer).
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` of the captured images' noise.
        calibration: optional :class:`Calibration` (sets ``score`` by name, ``temperature`` and ``min_peak_z``).
        shifts: belief window radius ``r`` or ``(ry, rx)``.
        yaw_bins: odd number of yaw bins.
        yaw_step: yaw bin spacing in degrees.
        **settings: the keyword arguments of :func:`track_step` (``motion_noise``, ``score``, ``temperature``, ...).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 64, 96, generator=generator) * 256
        >>> from enmi_torch import ECR
        >>> tracker = Tracker(reference, score=ECR(bins=16), shifts=4, yaw_bins=1, motion_noise=(0.3, 0.3, 0.1))
        >>> tracker.start(torch.tensor([[40.0, 30.0, 0.0]]))
        >>> for x in (42, 44, 46):  # the vehicle drives 2 cells per frame along the map's columns
        ...     output = tracker(reference[..., 22:38, x - 8 : x + 8], torch.tensor([[2.0, 0.0, 0.0]]), 1.0)
        >>> output.pose.round().tolist(), bool(output.healthy)
        ([[46.0, 30.0, 0.0]], True)
    """

    def __init__(
        self,
        reference: Tensor,
        variance_model: VarianceModel | None = None,
        *,
        calibration: Calibration | None = None,
        shifts: int | tuple[int, int] = 8,
        yaw_bins: int = 5,
        yaw_step: float = 1.0,
        **settings,
    ) -> None:
        super().__init__()
        check_floating("reference", reference)
        if reference.ndim == 2:
            reference = reference[None, None]
        self.register_buffer("reference", reference, persistent=False)
        if variance_model is not None and not isinstance(variance_model, VarianceModel):
            raise TypeError(f"variance_model must be a VarianceModel or None, got {type(variance_model).__name__}")
        self.variance_model = variance_model
        self.shifts = check_shifts(shifts)
        self.yaw_bins, self.yaw_step = yaw_bins, yaw_step
        if calibration is not None:
            if not isinstance(calibration, Calibration):
                raise TypeError(f"calibration must be a Calibration or None, got {type(calibration).__name__}")
            settings = {**calibration._asdict(), **settings}
        unknown = set(settings) - set(_STEP_SETTINGS)
        if unknown:
            raise TypeError(f"Tracker got unknown setting(s) {sorted(unknown)}; known: {list(_STEP_SETTINGS)}")
        self.settings = settings
        self.belief: Belief | None = None
        self.health: Health | None = None

    def start(self, pose: Tensor, std: tuple[float, float, float] | None = None) -> None:
        """Start (or restart) the filter at ``(B, 3)`` poses ``(x, y, yaw)``: a flat or Gaussian belief."""
        self.belief = initial_belief(pose, shifts=self.shifts, yaw_bins=self.yaw_bins, yaw_step=self.yaw_step, std=std)
        self.health = None

    def forward(
        self,
        captured: Tensor,
        odometry: Tensor,
        variance: Tensor | float | None = None,
        captured_mask: Tensor | None = None,
    ) -> TrackOutput:
        """One frame in, one pose out: :func:`track_step` on the stored belief, which it replaces."""
        if self.belief is None:
            raise RuntimeError("Tracker has no belief yet: call start(pose) first")
        if variance is not None and self.variance_model is not None:
            raise ValueError("variance must be None when Tracker has a variance_model; pass one or the other")
        variance = self.variance_model if variance is None else variance
        self.belief, output, self.health = track_step(
            self.belief,
            captured,
            self.reference,
            odometry,
            variance,
            captured_mask,
            health=self.health,
            **self.settings,
        )
        return output


_STEP_SETTINGS = (
    "motion_noise",
    "score",
    "temperature",
    "min_peak_z",
    "max_surprise",
    "z_drop",
    "patience",
    "relocalize_shifts",
    "relocalize_yaw_bins",
    "coarse_factor",
    "relocalize_odds",
)


class _Searcher:
    """Score surfaces of the captured images over a belief's window and over the wide relocalization window."""

    def __init__(self, captured, reference, variance, captured_mask, score: Score, temperature) -> None:
        self.captured, self.reference, self.variance, self.mask = captured, reference, variance, captured_mask
        self.score = score
        self.temperature = temperature
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
        """The one call of :func:`~enmi_torch.localize` (its mask keyword in one place)."""
        return localize(
            self.captured[vehicle : vehicle + 1],
            self.reference,
            self._per_vehicle(self.variance, slice(vehicle, vehicle + 1)),
            shifts=shifts,
            center=center.reshape(1, 2),
            yaws=yaws,
            captured_mask=self._per_vehicle(self.mask, slice(vehicle, vehicle + 1)),
            score=self.score,
            **options,
        )

    def window(self, belief: Belief, only: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Log-likelihood ``(B, Y, Sy, Sx)`` over the belief's window, best score ``(B,)`` and its robust z-score."""
        vehicles = range(belief.log_prob.shape[0]) if only is None else [only]
        likelihoods, scores, z_scores = [], [], []
        yaws = belief.yaws()
        for vehicle in vehicles:
            surface = self._localize(vehicle, belief.center[vehicle], yaws[vehicle].tolist(), belief.radius).surface
            surface = _finite_floor(surface[0].double())
            likelihoods.append(surface * self.valid_count[vehicle] / self.temperature)
            scores.append(surface.max())
            z_scores.append(_peak_z(surface))
        return torch.stack(likelihoods), torch.stack(scores), torch.stack(z_scores)

    def wide(self, vehicle: int, belief: Belief, shifts: int, yaw_bins: int, coarse_factor: int) -> Tensor:
        """``(3,)`` pose ``(x, y, yaw)`` of the best match over the wide window around the belief's centre."""
        offsets = (torch.arange(yaw_bins, dtype=torch.float64) - yaw_bins // 2) * belief.yaw_step
        yaws = (belief.yaw_center[vehicle].cpu() + offsets).tolist()
        found = self._localize(
            vehicle, belief.center[vehicle], yaws, shifts, coarse_factor=coarse_factor, min_overlap=0.5
        )
        pose = found.pose[0].double()
        center = belief.center[vehicle].double()
        return torch.stack([center[1] + pose[0], center[0] + pose[1], pose[2]])


def _restart(belief: Belief, vehicle: int, pose: Tensor) -> Belief:
    """The belief with vehicle ``vehicle``'s window moved to ``pose`` (yaw on the belief's yaw lattice)."""
    center, yaw_center = belief.center.clone(), belief.yaw_center.clone()
    center[vehicle] = torch.stack([pose[1], pose[0]]).round().long().to(center.device)
    steps = ((pose[2].to(yaw_center.device) - yaw_center[vehicle]) / belief.yaw_step).round()
    yaw_center[vehicle] = yaw_center[vehicle] + steps * belief.yaw_step
    return belief._replace(center=center, yaw_center=yaw_center)


def _peak_z(surface: Tensor) -> Tensor:
    """Robust z-score of the best value of a surface: ``(best - median) / (1.4826 MAD)``."""
    values = surface.flatten()
    median = values.median()
    spread = 1.4826 * (values - median).abs().median()
    return (values.max() - median) / spread.clamp_min(1e-12 * values.abs().max().clamp_min(1e-300))


def _surprise(log_prior: Tensor, log_likelihood: Tensor) -> Tensor:
    """``(B,)`` nats by which the prediction puts the likelihood's peak below the prediction's own best."""
    flat_likelihood, flat_prior = log_likelihood.flatten(1), log_prior.flatten(1)
    index = flat_likelihood.argmax(1, keepdim=True)
    return flat_prior.amax(1) - flat_prior.gather(1, index)[:, 0]


def _peak_position(belief: Belief, log_likelihood: Tensor, vehicle: int) -> Tensor:
    """``(2,)`` ``(x, y)`` of the best cell of a vehicle's log-likelihood on the belief's grid."""
    _, rows, cols = log_likelihood.shape[1:]
    rest = int(log_likelihood[vehicle].flatten().argmax()) % (rows * cols)
    row, col = divmod(rest, cols)
    radius_y, radius_x = belief.radius
    center = belief.center[vehicle].double()
    return torch.stack([center[1] + col - radius_x, center[0] + row - radius_y])


def _grid_poses(belief: Belief) -> tuple[Tensor, Tensor, Tensor]:
    """``x (B, 1, 1, Sx)``, ``y (B, 1, Sy, 1)``, ``yaw (B, Y, 1, 1)`` of the grid's bins."""
    radius_y, radius_x = belief.radius
    device = belief.log_prob.device
    cols = torch.arange(-radius_x, radius_x + 1, dtype=torch.float64, device=device)
    rows = torch.arange(-radius_y, radius_y + 1, dtype=torch.float64, device=device)
    x = belief.center[:, 1, None].double() + cols
    y = belief.center[:, 0, None].double() + rows
    return x[:, None, None, :], y[:, None, :, None], belief.yaws()[:, :, None, None]


def _normalized(log_prob: Tensor) -> Tensor:
    return log_prob - log_prob.flatten(1).logsumexp(1)[:, None, None, None]


def _finite_floor(values: Tensor) -> Tensor:
    """``values`` with NaN and ``-inf`` replaced by the smallest finite value of each sample (0 if none)."""
    finite = torch.isfinite(values)
    floor = torch.where(finite, values, math.inf).flatten(1).amin(1) if values.ndim > 1 else values[finite].amin()
    if values.ndim > 1:
        floor = torch.where(torch.isfinite(floor), floor, 0.0).reshape(-1, *([1] * (values.ndim - 1)))
    return torch.where(finite, values, floor)


def _map_covariance(cos: Tensor, sin: Tensor, noise: Tensor) -> Tensor:
    """``(B, Y, 2, 2)`` covariance of the map move ``(dx, dy)`` from the odometry's ``(du, dv)`` noise per yaw bin."""
    rotation = torch.stack([torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)], -2)
    local = torch.diag_embed(noise[:, :2].square())[:, None]
    return rotation @ local @ rotation.transpose(-1, -2)


def _translate(mass: Tensor, offset_x: Tensor, offset_y: Tensor, covariance: Tensor) -> Tensor:
    """Move each ``(b, k)`` plane of ``mass`` by ``(offset_x, offset_y)[b, k]`` cells and blur it by ``covariance``.

    The kernel is the bilinear split of the sub-cell offset convolved with a point-symmetric discrete Gaussian; the
    whole-cell offset is a shift of the full convolution with zero fill.
    """
    batch, yaw_count, rows, cols = mass.shape
    reach = math.ceil(3 * float(covariance.diagonal(dim1=-2, dim2=-1).amax().sqrt()))
    taps = torch.arange(-reach, reach + 1, dtype=torch.float64, device=mass.device)
    grid_y, grid_x = torch.meshgrid(taps, taps, indexing="ij")
    points = torch.stack([grid_x, grid_y], -1)
    precision = torch.linalg.inv(covariance + 1e-9 * torch.eye(2, dtype=torch.float64, device=mass.device))
    gaussian = (-0.5 * torch.einsum("yxi,bkij,yxj->bkyx", points, precision, points)).exp()
    gaussian = gaussian / gaussian.flatten(2).sum(2)[..., None, None]
    whole_x, whole_y = offset_x.floor(), offset_y.floor()
    fraction_x, fraction_y = offset_x - whole_x, offset_y - whole_y
    bilinear = torch.stack(
        [
            torch.stack([(1 - fraction_y) * (1 - fraction_x), (1 - fraction_y) * fraction_x], -1),
            torch.stack([fraction_y * (1 - fraction_x), fraction_y * fraction_x], -1),
        ],
        -2,
    )
    size = 2 * reach + 2
    kernel = F.conv_transpose2d(
        gaussian.reshape(1, batch * yaw_count, size - 1, size - 1),
        bilinear.reshape(batch * yaw_count, 1, 2, 2),
        groups=batch * yaw_count,
    ).reshape(batch * yaw_count, 1, size, size)
    # Full convolution: full[r] = sum_t kernel[t] mass[r - t]; the result at q is full[q - (whole - reach)].
    full = F.conv_transpose2d(mass.reshape(1, batch * yaw_count, rows, cols), kernel, groups=batch * yaw_count)[0]
    result = mass.new_zeros(batch * yaw_count, rows, cols)
    for plane, (shift_y, shift_x) in enumerate(
        zip((whole_y.flatten() - reach).long().tolist(), (whole_x.flatten() - reach).long().tolist(), strict=True)
    ):
        row_low, row_high = max(shift_y, 0), min(shift_y + full.shape[1], rows)
        col_low, col_high = max(shift_x, 0), min(shift_x + full.shape[2], cols)
        if row_low < row_high and col_low < col_high:
            result[plane, row_low:row_high, col_low:col_high] = full[
                plane, row_low - shift_y : row_high - shift_y, col_low - shift_x : col_high - shift_x
            ]
    return result.reshape(batch, yaw_count, rows, cols)


def _yaw_mixing(yaw_count: int, offset: Tensor, noise: Tensor) -> Tensor:
    """``(B, Y, Y)`` transfer ``[b, target, source]`` of mass between yaw bins moved by ``offset`` bins."""
    reach = math.ceil(3 * float(noise.amax())) if yaw_count > 1 else 0
    taps = torch.arange(-reach, reach + 1, dtype=torch.float64, device=offset.device)
    gaussian = (-0.5 * (taps / noise.clamp_min(1e-6)[:, None]).square()).exp()
    gaussian = gaussian / gaussian.sum(1, keepdim=True)
    whole = offset.floor()
    fraction = offset - whole
    bins = torch.arange(yaw_count, dtype=torch.float64, device=offset.device)
    # target - source - whole - tap in {0, 1}: the bilinear split of the fractional move.
    distance = bins[None, :, None, None] - bins[None, None, :, None] - whole[:, None, None, None] - taps
    split = torch.where(
        distance == 0,
        1 - fraction[:, None, None, None],
        torch.where(distance == 1, fraction[:, None, None, None], 0.0),
    )
    return (split * gaussian[:, None, None, :]).sum(-1)


def _check_belief(belief: object) -> None:
    if not isinstance(belief, Belief):
        raise TypeError(
            f"belief must be a Belief (from initial_belief or a previous step), got {type(belief).__name__}"
        )
    if belief.log_prob.ndim != 4 or belief.log_prob.shape[2] % 2 == 0 or belief.log_prob.shape[3] % 2 == 0:
        raise ValueError(f"belief.log_prob must be (B, Y, 2 ry + 1, 2 rx + 1), got {tuple(belief.log_prob.shape)}")


def _check_pose(name: str, pose: object, batch: int | None = None) -> Tensor:
    check_floating(name, pose)
    expected = "(B, 3)" if batch is None else f"({batch}, 3)"
    if pose.ndim != 2 or pose.shape[1] != 3 or (batch is not None and pose.shape[0] != batch):
        raise ValueError(f"{name} must have shape {expected}, got {tuple(pose.shape)}")
    if not bool(torch.isfinite(pose).all()):
        raise ValueError(f"{name} must be finite, got NaN or inf")
    return pose.double()


def _check_noise(noise: object, batch: int) -> Tensor:
    values = noise if isinstance(noise, Tensor) else torch.tensor(list(noise), dtype=torch.float64)
    values = values.double()
    if values.shape == (3,):
        values = values.expand(batch, 3)
    if values.shape != (batch, 3) or not bool(torch.isfinite(values).all()) or bool((values < 0).any()):
        raise ValueError(
            f"noise must be three standard deviations >= 0 (du, dv, dyaw) or ({batch}, 3) of them, got {noise!r}"
        )
    return values


def _check_positive(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)
