"""Reading a pose from score surfaces: the best candidate, its sub-cell refinement, covariance and margin.

The result type :class:`Localization` lives here; :mod:`enmi_torch.localization.search` fills it.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.utils.checks import check_image_shape


class Finalists(NamedTuple):
    """A search's finalists: the best local maxima of its surface, each scored exactly (:meth:`Score.finalists`).

    The surface ranks every placement with a model fitted once (ECR's model variance and response, read at a cheap
    first pass's peak, every reading a Gaussian value); each finalist is scored by the score on its aligned pair,
    with its own fit, and the best one is the search's answer.

    Attributes:
        placements: ``(B, K, 3)`` int64 ``(yaw index, row, col)`` of each finalist in the surface (``surface[b, k,
            row, col]``), best surface value first; ``-1`` where a sample has fewer than ``K`` local maxima.
        scores: ``(B, K)`` their exact scores, ``-inf`` for the padding.
        chosen: ``(B,)`` int64 index of the best finalist (the pose's placement).
    """

    placements: Tensor
    scores: Tensor
    chosen: Tensor

    def best(self) -> Tensor:
        """``(B, 3)`` the chosen finalist's ``(yaw index, row, col)``."""
        return self.placements[torch.arange(self.chosen.shape[0], device=self.chosen.device), self.chosen]


class Localization(NamedTuple):
    """The result of :func:`~enmi_torch.localize`: the pose found, its score surface and how sure it is.

    Read the pose as ``result.pose`` ``(B, 3)`` ``(x, y, yaw)``, absolute in the map (what
    :func:`~enmi_torch.register` and :meth:`~enmi_torch.Tracker.start` take unchanged); the shift from the prior pose
    the search was centred on as ``result.shift`` ``(B, 2)`` (or ``result.dx``, ``result.dy``), the yaw as
    ``result.yaw``; ``result.local_to_map(local_shape)`` gives the ``(B, 3, 3)`` transform from local ``(x, y)``
    pixels to map ``(x, y)`` cells.

    Attributes:
        pose: ``(B, 3)`` ``(x, y, yaw)``: the map column ``x`` and row ``y`` (down) under the captured image's pixel
            ``(h // 2, w // 2)``, in cells, refined below one cell, and the yaw in degrees, counter-clockwise as
            displayed (refined below one yaw step when the yaws are evenly spaced).
        score: ``(B,)`` score of the best searched candidate.
        surface: ``(B, Y, 2 ry + 1, 2 rx + 1)`` score per yaw and shift (``[b, k, ry + dy, rx + dx]``); ``-inf``
            where the candidate was excluded by ``min_overlap`` or not evaluated by the coarse-to-fine search.
        covariance: ``(B, 2, 2)`` covariance of ``(x, y)`` in cells², ``inverse(-H)`` of the Hessian ``H`` of the
            quadratic fitted to the 3 x 3 surface around the peak: the spread of ``exp(score)`` near the peak.
            Scale the scores first if they are not log-likelihoods. ``inf`` on the diagonal when the peak is on the
            window's edge, next to an excluded candidate, or not a maximum of the fit.
        margin: ``(B,)`` best score minus the best score farther than ``exclusion_radius`` cells (both axes) from
            the peak (over all yaws); ``inf`` when no such candidate exists. Small margins mean ambiguous maps.
        yaws: ``(Y,)`` the yaws searched, in degrees.
        around: ``(B, 2)`` ``(x, y)``: the map cell the search window was centred on (the prior pose ``around``
            given to :func:`~enmi_torch.localize`, rounded to a cell); ``None`` (a result built by hand): the map's
            origin, so that :attr:`shift` is the pose's ``(x, y)``.
        finalists: the :class:`Finalists` the pose was chosen among (``None`` where the score's surface is exact,
            :attr:`~enmi_torch.scores.Score.surface_is_exact`, or the strategy scores none). The pose, score,
            covariance and margin are read from the surface at the chosen finalist's placement, which need not be
            the surface's maximum: ``margin`` is then negative.
    """

    pose: Tensor
    score: Tensor
    surface: Tensor
    covariance: Tensor
    margin: Tensor
    yaws: Tensor
    around: Tensor | None = None
    finalists: Finalists | None = None

    @property
    def shift(self) -> Tensor:
        """``(B, 2)`` ``(dx, dy)``: the pose's move from :attr:`around` along the map's columns and rows, in cells."""
        if self.around is None:
            return self.pose[:, :2]
        return self.pose[:, :2] - self.around.to(self.pose)

    @property
    def dx(self) -> Tensor:
        """``(B,)`` shift along the map's columns (x), in cells, from the prior pose (:attr:`around`)."""
        return self.shift[:, 0]

    @property
    def dy(self) -> Tensor:
        """``(B,)`` shift along the map's rows (y, down), in cells, from the prior pose (:attr:`around`)."""
        return self.shift[:, 1]

    @property
    def yaw(self) -> Tensor:
        """``(B,)`` rotation of the captured image against the map, degrees, counter-clockwise as displayed."""
        return self.pose[:, 2]

    def local_to_map(
        self, local_shape: tuple[int, int], deprecated_local_shape: tuple[int, int] | None = None
    ) -> Tensor:
        """``(B, 3, 3)`` transform from captured pixel coordinates ``(x, y)`` to map coordinates ``(x, y)``.

        Points are ``(x, y) = (column, row)`` with y down, as in kornia. A captured pixel ``p`` shows the map at
        ``T @ [x, y, 1]``: the search turns the captured image by ``-yaw`` about its centre
        ``((w - 1) / 2, (h - 1) / 2)`` (kornia's :func:`~kornia.geometry.transform.rotate`) and puts its pixel
        ``(h // 2, w // 2)`` on map cell ``(x, y)`` of :attr:`pose`.

        Args:
            local_shape: ``(h, w)`` of the captured images.
            deprecated_local_shape: the former call ``local_to_map(center, local_shape)`` (deprecated, removed in the
                next release; it warns): ``local_shape`` is then the ``center=(row, col)`` given to
                :func:`~enmi_torch.localize` and the pose is read as ``center + shift``; call
                ``local_to_map(local_shape)``, which needs no center.

        Example:
            >>> pose = torch.tensor([[22.0, 9.0, 90.0]])  # (x, y, yaw): column 22, row 9
            >>> transform = Localization(pose, *(torch.zeros(1),) * 5).local_to_map((5, 5))[0]  # a 90 degree turn
            >>> (transform @ torch.tensor([2.0, 2.0, 1.0])).tolist()  # the centre pixel: column 22, row 9
            [22.0, 9.0, 1.0]
            >>> (transform @ torch.tensor([4.0, 2.0, 1.0])).round().tolist()  # two pixels right: two cells down
            [22.0, 11.0, 1.0]
        """
        pose = self.pose.double()
        if deprecated_local_shape is None:
            height, width = check_image_shape("local_shape", local_shape)
            position = pose[:, :2]
        else:
            warnings.warn(
                "local_to_map(center, local_shape) is deprecated: Localization.pose is absolute now, call "
                "local_to_map(local_shape)",
                DeprecationWarning,
                stacklevel=2,
            )
            height, width = check_image_shape("local_shape", deprecated_local_shape)
            position = _center_xy(local_shape, len(pose), pose.device) + self.shift.double()
        angle = torch.deg2rad(-pose[:, 2])  # the search turns the captured image by -yaw
        cos, sin = angle.cos(), angle.sin()
        middle_x, middle_y = (width - 1) / 2, (height - 1) / 2
        # OpenCV/kornia rotation about the centre (source to destination), then the placement of the centre pixel.
        shift_x = position[:, 0] - width // 2
        shift_y = position[:, 1] - height // 2
        transform = torch.zeros(len(pose), 3, 3, dtype=torch.float64, device=pose.device)
        transform[:, 0, 0], transform[:, 0, 1] = cos, sin
        transform[:, 1, 0], transform[:, 1, 1] = -sin, cos
        transform[:, 0, 2] = (1 - cos) * middle_x - sin * middle_y + shift_x
        transform[:, 1, 2] = sin * middle_x + (1 - cos) * middle_y + shift_y
        transform[:, 2, 2] = 1
        return transform.to(self.pose.dtype)


def _center_xy(center, batch: int, device: torch.device) -> Tensor:
    """``(B, 2)`` float64 ``(x, y)`` of a former ``center=(row, col)`` (or ``(B, 2)`` rows of them)."""
    try:
        centers = torch.as_tensor(center, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError):
        centers = None
    if centers is None or centers.shape not in ((2,), (1, 2), (batch, 2)):
        raise ValueError(f"center must be (row, col) or a ({batch}, 2) tensor of them, got {center!r}")
    return centers.reshape(-1, 2).expand(batch, 2).flip(1)


class NoCandidateError(ValueError):
    """No candidate of a search passes ``min_overlap`` (the window lies off the map or the masks leave too little).

    A :class:`ValueError`; the tracker catches it and coasts on odometry for that frame.
    """


def separated_peaks(surface: Tensor, count: int, radius: int) -> list[tuple[int, int, int]]:
    """Up to ``count`` ``(yaw, row, col)`` maxima of a ``(Y, Sy, Sx)`` surface, each ``radius`` cells from the rest."""
    best_over_yaws, best_yaw = surface.max(0)
    remaining = best_over_yaws.clone()
    peaks = []
    for _ in range(count):
        flat = int(remaining.flatten().argmax())
        row, col = divmod(flat, remaining.shape[1])
        if not math.isfinite(float(remaining[row, col])):
            break
        peaks.append((int(best_yaw[row, col]), row, col))
        remaining[max(row - radius, 0) : row + radius + 1, max(col - radius, 0) : col + radius + 1] = -math.inf
    return peaks


# Least squares fit of f(x, y) = a + b x + c y + d x^2 + e x y + g y^2 on the 3 x 3 grid x, y in {-1, 0, 1}.
_GRID_Y, _GRID_X = torch.meshgrid(torch.arange(-1.0, 2.0), torch.arange(-1.0, 2.0), indexing="ij")
_DESIGN = torch.stack(
    [
        torch.ones(9),
        _GRID_X.flatten(),
        _GRID_Y.flatten(),
        _GRID_X.flatten() ** 2,
        (_GRID_X * _GRID_Y).flatten(),
        _GRID_Y.flatten() ** 2,
    ],
    dim=1,
).double()
_FIT = torch.linalg.pinv(_DESIGN)


def read_peak(
    surface: Tensor,
    yaws: Tensor,
    radius: tuple[int, int],
    exclusion_radius: int,
    around: Tensor | None = None,
    finalists: Finalists | None = None,
) -> Localization:
    """Best candidate, sub-cell quadratic fit, covariance and margin of ``(B, Y, Sy, Sx)`` surfaces.

    ``around``: ``(B, 2)`` ``(x, y)`` map cells of the windows' middle cells (the pose is absolute); ``None``: the
    origin (the pose is the shift). The best candidate is the surface's maximum, or the chosen one of ``finalists``
    (carried into the result).
    """
    device, surface = surface.device, surface.cpu()
    batch, yaw_count, rows, cols = surface.shape
    flat = surface.flatten(1)
    best, index = flat.max(1)
    if finalists is not None:
        chosen = finalists.best().cpu()
        found = (chosen >= 0).all(1)  # a sample without a finite candidate has no finalist: it is refused below
        index = torch.where(found, (chosen[:, 0] * rows + chosen[:, 1]) * cols + chosen[:, 2], index)
        best = flat.gather(1, index[:, None])[:, 0]
    lost = ~torch.isfinite(best)
    if bool(lost.any()):
        raise NoCandidateError(
            f"no candidate passes min_overlap in sample(s) {lost.nonzero()[:, 0].tolist()}: lower min_overlap, move "
            "around, or check the masks"
        )
    poses, covariances, margins = [], [], []
    step = yaws[1:] - yaws[:-1]
    even_yaws = yaw_count >= 3 and bool(torch.allclose(step, step[0].expand_as(step)))
    for sample in range(batch):
        yaw_index, rest = divmod(int(index[sample]), rows * cols)
        row, col = divmod(rest, cols)
        plane = surface[sample, yaw_index]
        offset, covariance = _quadratic_peak(plane, row, col)
        yaw = yaws[yaw_index]
        if even_yaws and 0 < yaw_index < yaw_count - 1:
            profile = surface[sample].flatten(1).amax(1)
            yaw = yaw + step[0] * _parabola_offset(profile[yaw_index - 1 : yaw_index + 2])
        poses.append(torch.stack([offset[0] + col - radius[1], offset[1] + row - radius[0], yaw.to(offset.dtype)]))
        covariances.append(covariance)
        others = surface[sample].amax(0).clone()
        others[
            max(row - exclusion_radius, 0) : row + exclusion_radius + 1,
            max(col - exclusion_radius, 0) : col + exclusion_radius + 1,
        ] = -math.inf
        runner_up = others.max()
        margins.append(best[sample] - runner_up if torch.isfinite(runner_up) else best.new_tensor(math.inf))
    poses = torch.stack(poses)
    if around is not None:
        poses[:, :2] += around.cpu().double()  # in float64: a float32 map position keeps its sub-cell part
        around = around.to(device, surface.dtype)
    return Localization(
        poses.to(device, surface.dtype),
        best.to(device),
        surface.to(device),
        torch.stack(covariances).to(device, surface.dtype),
        torch.stack(margins).to(device),
        yaws.to(device),
        around,
        finalists,
    )


def _quadratic_peak(plane: Tensor, row: int, col: int) -> tuple[Tensor, Tensor]:
    """Sub-cell ``(dx, dy)`` offset and covariance ``inverse(-H)`` from the 3 x 3 neighbourhood of a grid peak.

    When the fitted vertex lies more than half a cell away, the fit is re-centred on the neighbouring cell it points
    to and refitted once (kornia's ``geometry/subpix`` habit). If that vertex is not within half a cell of its own
    centre either, or a fit is not a maximum (a ridge: the surface barely falls along it), the fit failed: the
    covariance is infinite and the offset is the vertex of the parabola through the peak and its two neighbours along
    each axis (0 on an axis where the peak lies on the window's edge or the parabola is not a maximum).
    """
    failed = torch.diag(torch.full((2,), math.inf, dtype=torch.float64))
    fit = _quadratic_fit(plane, row, col)
    if fit is None:
        return _axis_offsets(plane, row, col), failed
    offset, covariance = fit
    if bool((offset.abs() <= 0.5).all()):
        return offset, covariance
    step = offset.sign() * (offset.abs() > 0.5)
    fit = _quadratic_fit(plane, row + int(step[1]), col + int(step[0]))
    if fit is None or not bool((fit[0].abs() <= 0.5).all()):
        return _axis_offsets(plane, row, col), failed
    return fit[0] + step, fit[1]


def _axis_offsets(plane: Tensor, row: int, col: int) -> Tensor:
    """``(dx, dy)``: the vertices of the parabolas through the peak and its neighbours along each axis.

    Each in ``[-0.5, 0.5]``; 0 where a neighbour is off the window or the parabola is not a maximum.
    """
    offsets = torch.zeros(2, dtype=torch.float64)
    if 0 < col < plane.shape[1] - 1:
        offsets[0] = _parabola_offset(plane[row, col - 1 : col + 2])
    if 0 < row < plane.shape[0] - 1:
        offsets[1] = _parabola_offset(plane[row - 1 : row + 2, col])
    return offsets


def _quadratic_fit(plane: Tensor, row: int, col: int) -> tuple[Tensor, Tensor] | None:
    """Vertex offset ``(dx, dy)`` and ``inverse(-H)`` of the quadratic fitted to the 3 x 3 cells around a cell."""
    if not (0 < row < plane.shape[0] - 1 and 0 < col < plane.shape[1] - 1):
        return None
    values = plane[row - 1 : row + 2, col - 1 : col + 2].double().flatten()
    if not bool(torch.isfinite(values).all()):
        return None
    _, slope_x, slope_y, curve_xx, curve_xy, curve_yy = (_FIT @ values).unbind()
    hessian = torch.stack([torch.stack([2 * curve_xx, curve_xy]), torch.stack([curve_xy, 2 * curve_yy])])
    if not (hessian[0, 0] < 0 and torch.linalg.det(hessian) > 0):
        return None
    offset = -torch.linalg.solve(hessian, torch.stack([slope_x, slope_y]))
    return offset, torch.linalg.inv(-hessian)


def _parabola_offset(values: Tensor) -> Tensor:
    """Vertex offset in ``[-0.5, 0.5]`` steps of the parabola through three equally spaced values."""
    left, middle, right = values.double().unbind()
    curvature = left - 2 * middle + right
    if not (torch.isfinite(values).all() and curvature < 0):
        return torch.zeros((), dtype=torch.float64)
    return (0.5 * (left - right) / curvature).clamp(-0.5, 0.5)
