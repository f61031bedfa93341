"""The analytic (perspective) variance map: ``sigma^2 = N0 / A~`` per ground cell, from the camera or a homography.

Convention:
    ``A~`` is the focal-plane area of a cell (paper, eq. TildeA), in the camera's length unit squared, and ``N0`` the
    sensor's noise power spectral density (paper, section "Noise Characterization"), in amplitude squared times
    length squared: a cell's mean amplitude over its footprint then has variance ``N0 / A~`` (amplitude squared).
    With the paper's camera (f = 0.0367 cm) a whole 20 cm tile has ``A~`` from about 7.7e-5 cm^2 (nearest row) to
    4.7e-6 cm^2 (farthest), so ``N0 = 0.01`` gives ``sigma^2`` from about 130 to 2100. Areas are computed in float64
    and the map cast to the caller's dtype.

    A cell is valid when the camera sees its centre (:func:`~enmi_torch.geometry.rectify.visible_cells`, the cells
    :func:`~enmi_torch.geometry.rectify.rectify` fills). A valid cell partly outside the view gets the exact area of its
    visible part (:func:`~enmi_torch.geometry.camera.visible_projected_area`): the mean over what the camera sees. An
    invalid cell holds the finite ``N0 / A~`` of the whole cell, so that gradients stay finite where a mask drops it.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from enmi_torch.geometry.camera import RoadCamera, projected_area, visible_projected_area
from enmi_torch.geometry.rectify import GroundGrid, projected_cell_areas, visible_cells
from enmi_torch.utils.checks import check_floating, check_positive_number
from enmi_torch.variance.base import VarianceModel


def _check_noise_power(noise_power: Any) -> Tensor | float:
    if isinstance(noise_power, Tensor):
        check_floating("noise_power", noise_power)
        if noise_power.ndim != 0:
            raise ValueError(f"noise_power must be a number or a 0-d tensor, got shape {tuple(noise_power.shape)}")
        if noise_power.device.type == "cpu" and not torch.compiler.is_compiling() and not bool(noise_power > 0):
            raise ValueError(f"noise_power must be > 0, got {noise_power.item()}")
        return noise_power
    return check_positive_number("noise_power", noise_power)


def perspective_cell_areas(camera: RoadCamera, grid: GroundGrid) -> tuple[Tensor, Tensor]:
    """Focal-plane areas ``A~`` of the grid cells, float64 ``(H_g, W_g)``, and the bool map of the valid cells.

    Valid cells (centre seen) get the area of their visible part, invalid ones the area of the whole cell.

    Example:
        >>> from enmi_torch.geometry.rectify import GroundGrid
        >>> areas, valid = perspective_cell_areas(RoadCamera.paper(), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0))
        >>> f"{areas[valid].min().item():.2e} {areas[valid].max().item():.2e}"  # the smallest: a partly seen cell
        '3.48e-06 7.72e-05'
    """
    valid = visible_cells(camera, grid)
    lateral, distance = grid.lateral_edges(), grid.distance_edges()
    corners = (lateral[None, :-1], lateral[None, 1:], distance[1:, None], distance[:-1, None])
    visible = visible_projected_area(camera, *corners)
    whole = projected_area(camera, *corners)
    return torch.where(valid, visible, whole), valid


def _variance_from_areas(noise_power: Tensor | float, areas: Tensor, dtype: torch.dtype | None) -> Tensor:
    dtype = dtype or (noise_power.dtype if isinstance(noise_power, Tensor) else areas.dtype)
    return (noise_power / areas).to(dtype)[None, None]


def perspective_variance(
    camera: RoadCamera, grid: GroundGrid, noise_power: Tensor | float = 0.01, *, dtype: torch.dtype | None = None
) -> Tensor:
    """The per-cell noise variance ``N0 / A~`` on the ground grid, ``(1, 1, H_g, W_g)``.

    Args:
        camera: the road camera.
        grid: the ground grid (row 0 farthest).
        noise_power: ``N0 > 0``, a number or a 0-d tensor (differentiable).
        dtype: of the result; default: that of a tensor ``noise_power``, else float64.

    Returns:
        ``(1, 1, H_g, W_g)`` variance, > 0 and finite everywhere; meaningful where
        :func:`~enmi_torch.geometry.rectify.visible_cells` is true (see the module's convention for partly seen cells).

    Example:
        >>> from enmi_torch.geometry.rectify import GroundGrid
        >>> variance = perspective_variance(RoadCamera.paper(), GroundGrid((-10.0, 10.0), (40.0, 200.0), 20.0))
        >>> [round(v) for v in variance.flatten().tolist()]  # far to near
        [2111, 1610, 1195, 858, 591, 387, 235, 130]
    """
    noise_power = _check_noise_power(noise_power)
    areas, _ = perspective_cell_areas(camera, grid)
    if isinstance(noise_power, Tensor):
        areas = areas.to(noise_power.device)
    return _variance_from_areas(noise_power, areas, dtype)


def homography_variance(
    homography: Tensor, shape: tuple[int, int], noise_power: Tensor | float, *, pixel_area: float = 1.0
) -> Tensor:
    """Noise variance ``N0 / A~`` on a raster that a homography maps onto the sensor: the general case.

    For any rectification (another camera model, a lidar grid) given as the homography from the raster's pixels to
    the sensor's pixels, ``A~`` of a raster cell is the exact area of its projected quadrilateral
    (:func:`~enmi_torch.geometry.rectify.projected_cell_areas`) times ``pixel_area``, the sensor area of one pixel. With
    ``pixel_area = 1``, ``N0`` is the noise variance of one sensor pixel and a cell covering ``A`` pixels has
    ``N0 / A``.

    Args:
        homography: ``(3, 3)`` or ``(B, 3, 3)``, raster pixels to sensor pixels.
        shape: ``(H, W)`` of the raster.
        noise_power: ``N0 > 0``, a number or a 0-d tensor.
        pixel_area: sensor area of one pixel (e.g. ``p_y * p_x`` of
            :attr:`~enmi_torch.geometry.camera.RoadCamera.pixel_size`).

    Returns:
        ``(1 or B, 1, H, W)`` in the dtype of ``homography``.

    Example:
        >>> two_by_two_pixels_per_cell = torch.diag(torch.tensor([2.0, 2.0, 1.0]))
        >>> homography_variance(two_by_two_pixels_per_cell, (1, 2), 8.0)
        tensor([[[[2., 2.]]]])
    """
    noise_power = _check_noise_power(noise_power)
    pixel_area = check_positive_number("pixel_area", pixel_area)
    check_floating("homography", homography)
    if homography.ndim not in (2, 3):
        raise ValueError(f"homography must have shape (3, 3) or (B, 3, 3), got {tuple(homography.shape)}")
    areas = projected_cell_areas(homography.reshape(-1, 3, 3), shape) * pixel_area
    return (noise_power / areas).to(homography.dtype).unsqueeze(1)


class PerspectiveVariance(VarianceModel):
    """The analytic road-camera variance map ``N0 / A~`` on a ground grid, for :class:`~enmi_torch.ENMILoss`.

    Args:
        camera: the road camera.
        grid: the ground grid of the (rectified) captured images.
        noise_power: ``N0 > 0``.
        learnable: fit ``log(N0)`` as a parameter.

    Convention:
        ``forward(captured)`` takes ``(B, 1, H_g, W_g)`` on ``grid`` and returns :func:`perspective_variance`,
        ``(1, 1, H_g, W_g)`` in the dtype of ``captured``; :meth:`valid_mask` is
        :func:`~enmi_torch.geometry.rectify.visible_cells`. ``log(N0)`` is a float64 parameter (or buffer), the cell
        areas float64 non-persistent buffers; the map is cast to the dtype of ``captured`` at the end.

    Example:
        >>> from enmi_torch.geometry.rectify import GroundGrid
        >>> model = PerspectiveVariance(RoadCamera.paper(), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0), 0.01)
        >>> captured = torch.zeros(2, 1, 8, 15)
        >>> model(captured).shape, int(model.valid_mask(captured).sum())
        (torch.Size([1, 1, 8, 15]), 74)
    """

    def __init__(
        self, camera: RoadCamera, grid: GroundGrid, noise_power: float = 0.01, learnable: bool = False
    ) -> None:
        super().__init__()
        noise_power = check_positive_number("noise_power", noise_power)
        log_noise_power = torch.tensor(noise_power, dtype=torch.float64).log()
        if learnable:
            self.log_noise_power = nn.Parameter(log_noise_power)
        else:
            self.register_buffer("log_noise_power", log_noise_power)
        areas, valid = perspective_cell_areas(camera, grid)
        self.camera, self.grid = camera, grid
        self.register_buffer("areas", areas, persistent=False)
        self.register_buffer("valid", valid, persistent=False)

    @property
    def noise_power(self) -> Tensor:
        """``N0``."""
        return self.log_noise_power.exp()

    def _check_captured(self, captured: Tensor) -> None:
        check_floating("captured", captured)
        if captured.ndim != 4 or captured.shape[1] != 1 or tuple(captured.shape[-2:]) != self.grid.shape:
            rows, cols = self.grid.shape
            raise ValueError(
                f"captured must have shape (B, 1, {rows}, {cols}) (the grid's shape), got {tuple(captured.shape)}"
            )

    def forward(self, captured: Tensor) -> Tensor:
        """The variance ``(1, 1, H_g, W_g)`` for a captured batch ``(B, 1, H_g, W_g)`` on the grid."""
        self._check_captured(captured)
        return _variance_from_areas(self.noise_power, self.areas, captured.dtype)

    def valid_mask(self, captured: Tensor) -> Tensor:
        """Bool ``(1, 1, H_g, W_g)``: the cells the camera sees."""
        self._check_captured(captured)
        return self.valid[None, None]

    def extra_repr(self) -> str:
        """The grid shape and ``N0``, for ``repr``."""
        return f"grid_shape={self.grid.shape}, noise_power={self.noise_power.item():.4g}"
