"""The filter's belief: a histogram over a window of map cells and yaw bins, and its arithmetic.

The belief over the vehicle's pose is a histogram on a local window of map cells and a few yaw bins around the
predicted pose: the same ``(Y, 2 ry + 1, 2 rx + 1)`` grid as a :func:`~enmi_torch.localize` surface.

* :func:`predict`: each yaw bin's mass moves by the odometry increment turned into the map at that bin's yaw, and is
  blurred by the odometry noise (a convolution with a discrete Gaussian, the sub-cell part of the increment split
  bilinearly so the mean moves by exactly the increment); the window is re-centred on the predicted pose;
* :func:`update`: a log-likelihood over the window is added to the log belief;
* :func:`belief_pose`: pose and covariance are the posterior's moments (sub-cell, plus the within-cell spread
  ``1 / 12``).

Convention:
    A pose is ``(x, y, yaw)``: ``x`` (column) and ``y`` (row) the map cell under the captured image's centre pixel
    ``(h // 2, w // 2)``, in cells, and ``yaw`` in degrees: the captured image is the map section there rotated by
    ``yaw`` counter-clockwise as displayed: the pose :func:`~enmi_torch.localize` returns
    (:meth:`~enmi_torch.Localization.local_to_map` gives the transform).
    Odometry is ``(du, dv, dyaw)``: the move of the captured image's centre along its own columns (``du``) and rows
    (``dv``), in cells, and the change of yaw in degrees, from the previous frame to this one; on the map the move
    is ``(dx, dy) = (cos a du + sin a dv, -sin a du + cos a dv)`` with ``a = -yaw`` (the linear part of
    ``local_to_map``). Beliefs are float64 log probabilities.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import check_floating, check_pose, check_positive_int, check_positive_number, check_shifts

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
    pose = check_pose("pose", pose).double()
    radius = check_shifts(shifts)
    yaw_bins = check_positive_int("yaw_bins", yaw_bins)
    if yaw_bins % 2 == 0:
        raise ValueError(f"yaw_bins must be odd (a middle bin on the predicted yaw), got {yaw_bins}")
    yaw_step = check_positive_number("yaw_step", yaw_step)
    batch = pose.shape[0]
    check_belief_memory(shifts, radius, yaw_bins, batch)
    center = torch.stack([pose[:, 1], pose[:, 0]], 1).round().long()
    shape = (batch, yaw_bins, 2 * radius[0] + 1, 2 * radius[1] + 1)
    log_prob = torch.zeros(shape, dtype=torch.float64, device=pose.device)
    belief = Belief(log_prob, center, pose[:, 2].clone(), yaw_step)
    if std is not None:
        if len(std) != 3 or not all(isinstance(value, (int, float)) and value > 0 for value in std):
            raise ValueError(f"std must be three numbers > 0 (x, y, yaw) or None, got {std!r}")
        x, y, yaw = grid_poses(belief)
        log_prob = -0.5 * (
            ((x - pose[:, 0, None, None, None]) / std[0]) ** 2
            + ((y - pose[:, 1, None, None, None]) / std[1]) ** 2
            + ((yaw - pose[:, 2, None, None, None]) / std[2]) ** 2
        )
    return belief._replace(log_prob=normalized(log_prob))


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
    check_belief(belief)
    batch, yaw_count = belief.log_prob.shape[:2]
    odometry = check_pose("odometry", odometry, batch).double()
    noise = check_noise("noise", noise, batch)
    peak = belief.log_prob.flatten(1).amax(1).clamp_min(-1e300)
    mass = (belief.log_prob - peak[:, None, None, None]).exp()
    # Map increment per yaw bin: local_to_map's linear part at the bin's yaw.
    angle = torch.deg2rad(-belief.yaws())
    cos, sin = angle.cos(), angle.sin()
    step_x = cos * odometry[:, 0, None] + sin * odometry[:, 1, None]
    step_y = -sin * odometry[:, 0, None] + cos * odometry[:, 1, None]
    # Re-centre the window on the predicted mean, in whole cells and yaw bins.
    x, y, yaw = grid_poses(belief)
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
    covariance = _map_covariance(cos, sin, noise)
    _check_blur_memory(mass, covariance, noise[:, 2] / belief.yaw_step, belief.yaw_step)
    translated = _translate(mass, offset_x, offset_y, covariance)
    yaw_offset = odometry[:, 2] / belief.yaw_step - yaw_shift
    mixing = _yaw_mixing(yaw_count, yaw_offset, noise[:, 2] / belief.yaw_step)
    predicted = torch.einsum("bij,bjyx->biyx", mixing, translated)
    log_prob = predicted.clamp_min(torch.finfo(torch.float64).tiny).log() + peak[:, None, None, None]
    return Belief(log_prob, center, yaw_center, belief.yaw_step)


def update(belief: Belief, log_likelihood: Tensor) -> Belief:
    """The measurement step: add ``(B, Y, Sy, Sx)`` log-likelihoods to the log belief and normalise.

    ``-inf`` or NaN likelihoods (candidates a search left out) count as the smallest finite value of the sample;
    ``+inf`` is refused (a certainty: no score gives one, and no weaker cell could be told from another).

    Example:
        >>> belief = initial_belief(torch.zeros(1, 3), shifts=1, yaw_bins=1)
        >>> likelihood = torch.zeros(1, 1, 3, 3)
        >>> likelihood[0, 0, 1, 1] = 2.0  # e^2 against 1 for the 8 other cells
        >>> round(float(update(belief, likelihood).log_prob.exp()[0, 0, 1, 1]), 4)
        0.4802
    """
    check_belief(belief)
    check_floating("log_likelihood", log_likelihood)
    if log_likelihood.shape != belief.log_prob.shape:
        raise ValueError(
            f"log_likelihood must have the belief's shape {tuple(belief.log_prob.shape)}, got "
            f"{tuple(log_likelihood.shape)}"
        )
    # +inf would claim a certainty no score gives, and its logsumexp is inf - inf: NaN for the whole belief.
    infinite = int(torch.isposinf(log_likelihood).sum())
    if infinite:
        raise ValueError(
            f"log_likelihood must be finite, -inf or NaN (a left-out candidate), got {infinite} cell(s) of +inf"
        )
    return belief._replace(log_prob=normalized(belief.log_prob + finite_floor(log_likelihood.double())))


def mixed_with_mismatch(log_likelihood: Tensor, probability: float) -> Tensor:
    """``(B, Y, Sy, Sx)`` log-likelihoods of a frame that matched this place with ``1 - p``, or no place with ``p``.

    Each sample's log-likelihood ``l`` becomes ``log((1 - p) exp(l - max l) + p)``: the frame may be a match of some
    other place (a changed scene, a repeated pattern), whose likelihood does not depend on the pose, and it is taken
    as ``p`` times the best pose's. One frame then puts at most ``log((1 - p) / p + 1) = log(1 / p)`` nats between two
    poses, however sharp its peak; a run of frames that agree still adds up. ``p = 0`` gives ``l - max l``, the same
    belief after :func:`update`. Non-finite values count as the sample's smallest finite one.

    Example:
        >>> log_likelihood = torch.tensor([0.0, -2.0, -30.0]).reshape(1, 1, 1, 3)
        >>> mixed_with_mismatch(log_likelihood, 0.05).flatten().round(decimals=3).tolist()  # -30 floors at log 0.05
        [0.0, -1.723, -2.996]
    """
    check_floating("log_likelihood", log_likelihood)
    if log_likelihood.ndim != 4:
        raise ValueError(f"log_likelihood must be (B, Y, Sy, Sx), got {tuple(log_likelihood.shape)}")
    probability = check_mismatch_probability(probability)
    values = finite_floor(log_likelihood.double())
    relative = values - values.flatten(1).amax(1)[:, None, None, None]
    if probability == 0:
        return relative
    return torch.logaddexp(relative + math.log1p(-probability), torch.full_like(relative, math.log(probability)))


def check_mismatch_probability(probability: object) -> float:
    """``probability`` as a float in ``[0, 1)``, or a ValueError naming ``mismatch_probability``."""
    if isinstance(probability, bool) or not isinstance(probability, (int, float)) or not 0 <= probability < 1:
        raise ValueError(f"mismatch_probability must be a number in [0, 1), got {probability!r}")
    return float(probability)


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
    check_belief(belief)
    log_prob = normalized(belief.log_prob)
    weights = log_prob.exp()
    x, y, yaw = grid_poses(belief)
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


def grid_poses(belief: Belief) -> tuple[Tensor, Tensor, Tensor]:
    """``x (B, 1, 1, Sx)``, ``y (B, 1, Sy, 1)``, ``yaw (B, Y, 1, 1)`` of the grid's bins."""
    radius_y, radius_x = belief.radius
    device = belief.log_prob.device
    cols = torch.arange(-radius_x, radius_x + 1, dtype=torch.float64, device=device)
    rows = torch.arange(-radius_y, radius_y + 1, dtype=torch.float64, device=device)
    x = belief.center[:, 1, None].double() + cols
    y = belief.center[:, 0, None].double() + rows
    return x[:, None, None, :], y[:, None, :, None], belief.yaws()[:, :, None, None]


def normalized(log_prob: Tensor) -> Tensor:
    """``log_prob`` ``(B, ...)`` shifted so that each sample's probabilities sum to 1."""
    return log_prob - log_prob.flatten(1).logsumexp(1)[:, None, None, None]


def finite_floor(values: Tensor) -> Tensor:
    """``values`` with NaN and ``-inf`` replaced by the smallest finite value of each sample (0 if none)."""
    finite = torch.isfinite(values)
    floor = torch.where(finite, values, math.inf).flatten(1).amin(1) if values.ndim > 1 else values[finite].amin()
    if values.ndim > 1:
        floor = torch.where(torch.isfinite(floor), floor, 0.0).reshape(-1, *([1] * (values.ndim - 1)))
    return torch.where(finite, values, floor)


def _reach(sigma: float) -> int:
    """Taps on each side of a discrete Gaussian of ``sigma`` bins: three standard deviations."""
    return math.ceil(3 * sigma)


def _check_blur_memory(mass: Tensor, covariance: Tensor, yaw_sigma: Tensor, yaw_step: float) -> None:
    """Refuse the motion step's blur kernels over the memory budget: they grow with the noise in cells and yaw bins.

    :func:`_translate` holds ``(B Y, size, size)`` kernels (Gaussian, bilinear product, the grid of taps) and a full
    convolution of each plane; :func:`_yaw_mixing` a ``(B, Y, Y, taps)`` split.
    """
    batch, yaw_count, rows, cols = mass.shape
    sigma = float(covariance.diagonal(dim1=-2, dim2=-1).amax().sqrt())
    size = 2 * _reach(sigma) + 2
    yaw_taps = 2 * (_reach(float(yaw_sigma.amax())) if yaw_count > 1 else 0) + 1
    planes = batch * yaw_count
    cells = planes * (3 * size * size + (rows + size) * (cols + size)) + 3 * size * size + planes * yaw_count * yaw_taps
    check_cells_memory(
        f"noise {sigma:.3g} cells and {float(yaw_sigma.amax()):.3g} yaw bins (yaw_step={yaw_step!r})",
        cells,
        8,
        f"the float64 blur kernels of {planes} plane(s) of {rows} x {cols} ({size} x {size} taps, {yaw_taps} in yaw)",
        "lower the motion noise or raise yaw_step (a kernel spans six standard deviations)",
    )


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
    reach = _reach(float(covariance.diagonal(dim1=-2, dim2=-1).amax().sqrt()))
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
    reach = _reach(float(noise.amax())) if yaw_count > 1 else 0
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


def check_belief(belief: object) -> None:
    """Raise unless ``belief`` is a :class:`Belief` whose window has a middle cell."""
    if not isinstance(belief, Belief):
        raise TypeError(
            f"belief must be a Belief (from initial_belief or a previous step), got {type(belief).__name__}"
        )
    if belief.log_prob.ndim != 4 or belief.log_prob.shape[2] % 2 == 0 or belief.log_prob.shape[3] % 2 == 0:
        raise ValueError(f"belief.log_prob must be (B, Y, 2 ry + 1, 2 rx + 1), got {tuple(belief.log_prob.shape)}")


BELIEF_COPIES = 8  # float64 tensors of the belief's size a filter step holds at once (prior, likelihoods, poses)


def check_belief_memory(shifts: object, radius: tuple[int, int], yaw_bins: int, batch: int) -> None:
    """Refuse a belief window (and a filter step's copies of it) over the memory budget, before it is allocated."""
    cells = batch * yaw_bins * (2 * radius[0] + 1) * (2 * radius[1] + 1)
    check_cells_memory(
        f"shifts={shifts!r} with yaw_bins={yaw_bins}",
        cells,
        8 * BELIEF_COPIES,
        f"the belief ({batch}, {yaw_bins}, {2 * radius[0] + 1}, {2 * radius[1] + 1}) in float64 and a filter step's "
        "copies of it",
        "lower shifts or yaw_bins (relocalize_shifts widens the search when the vehicle is lost)",
    )


def check_noise(name: str, noise: object, batch: int) -> Tensor:
    """``(B, 3)`` float64 odometry noise from three standard deviations or ``(B, 3)`` of them; else a ValueError."""
    values = noise if isinstance(noise, Tensor) else torch.tensor(list(noise), dtype=torch.float64)
    values = values.double()
    if values.shape == (3,):
        values = values.expand(batch, 3)
    if values.shape != (batch, 3) or not bool(torch.isfinite(values).all()) or bool((values < 0).any()):
        raise ValueError(
            f"{name} must be three standard deviations >= 0 (du, dv, dyaw) or ({batch}, 3) of them, got {noise!r}"
        )
    return values
