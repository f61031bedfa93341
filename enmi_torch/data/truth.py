"""Ground-truth noise variance fields of the synthetic pairs: lidar-like (radial) and camera-like (perspective).

A truth is a variance map ``(H, W)`` with the bool map of where it is defined. The synthetic pairs draw their noise
from it, and the training dashboards compare learned masks with it. Every flavour is one function returning a
:class:`VarianceTruth`; :func:`make_truth` picks one by name and scales it to a given noise level.

Convention:
    Images are bird's-eye grids with the vehicle heading up (row 0 is the front, as in the paper's Fig.
    VarianceMask). Variances are in squared grey levels, float64, NaN where invalid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.geometry.rectify import GroundGrid, visible_cells
from enmi_torch.utils.checks import (
    FLOAT32_MAGNITUDE,
    check_image_shape,
    check_option,
    check_positive_number,
    check_value_range,
)
from enmi_torch.variance.perspective import perspective_variance

FLAVOURS = ("lidar", "camera")


@dataclass(frozen=True)
class VarianceTruth:
    """A known noise variance field.

    Attributes:
        variance: ``(H, W)`` float64, > 0 where ``valid``, NaN elsewhere.
        valid: ``(H, W)`` bool, where the sensor sees the road.
        flavour: name of the model that made it.
    """

    variance: Tensor
    valid: Tensor
    flavour: str

    def __post_init__(self) -> None:
        if self.variance.ndim != 2 or self.valid.shape != self.variance.shape or self.valid.dtype != torch.bool:
            raise ValueError(
                f"variance must be (H, W) and valid a bool map of the same shape, got {tuple(self.variance.shape)} "
                f"and {self.valid.dtype} {tuple(self.valid.shape)}"
            )
        inside = self.variance[self.valid]
        if inside.numel() == 0 or not bool((torch.isfinite(inside) & (inside > 0)).all()):
            raise ValueError("variance must be finite and > 0 where valid, with one valid pixel at least")

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.variance.shape)

    def scaled(self, factor: float) -> VarianceTruth:
        """The same field with every variance multiplied by ``factor`` (> 0)."""
        factor = check_positive_number("factor", factor)
        return VarianceTruth(self.variance * factor, self.valid, self.flavour)

    def mean_variance(self) -> float:
        """Mean variance over the valid pixels."""
        return float(self.variance[self.valid].mean())


def lidar_truth(
    shape: tuple[int, int],
    noise_std_center: float = 6.0,
    noise_std_range: float = 24.0,
    *,
    range_fraction: float = 0.95,
) -> VarianceTruth:
    """Lidar-like field: variance growing with the squared range from the vehicle, invalid beyond the sensor range.

    ``sigma^2(r) = s_c^2 + (s_R^2 - s_c^2) (r / R)^2`` for ``r <= R``: the return density of a spinning lidar falls
    with range, so rasterised intensities get noisier away from the vehicle (image centre); beyond ``R =
    range_fraction * min(H, W) / 2`` there is no return (the black border of the paper's Fig. VarianceMask).

    Example:
        >>> truth = lidar_truth((5, 5), 1.0, 2.0, range_fraction=1.0)
        >>> truth.variance[2].tolist()
        [4.0, 1.75, 1.0, 1.75, 4.0]
        >>> truth.valid[0].tolist()
        [False, False, True, False, False]
    """
    height, width = check_image_shape("shape", shape)
    center_variance = check_positive_number("noise_std_center", noise_std_center) ** 2
    range_variance = check_positive_number("noise_std_range", noise_std_range) ** 2
    if not 0 < check_positive_number("range_fraction", range_fraction) <= 1:
        raise ValueError(f"range_fraction must be in (0, 1], got {range_fraction}")
    rows = torch.arange(height, dtype=torch.float64).unsqueeze(1) - (height - 1) / 2
    cols = torch.arange(width, dtype=torch.float64).unsqueeze(0) - (width - 1) / 2
    radius = torch.sqrt(rows.square() + cols.square())
    sensor_range = range_fraction * min(height - 1, width - 1) / 2 if min(height, width) > 1 else 1.0
    valid = radius <= sensor_range * (1 + 1e-12)
    variance = center_variance + (range_variance - center_variance) * (radius / sensor_range).square()
    return VarianceTruth(torch.where(valid, variance, torch.nan), valid, "lidar")


def camera_truth(
    shape: tuple[int, int],
    noise_power: float,
    *,
    camera: RoadCamera | None = None,
    distance_range: tuple[float, float] = (30.0, 210.0),
) -> VarianceTruth:
    """Camera-like field: the analytic :func:`~enmi_torch.variance.perspective_variance` on a bird's-eye grid.

    The ``(H, W)`` grid has square cells of side ``(d_far - d_near) / H``: rows cover ``distance_range`` (far edge
    at row 0), columns are centred laterally. A cell's variance is ``noise_power / A~`` with ``A~`` the exact
    focal-plane area of its visible part (paper eq. TildeA); cells whose centre the camera does not see
    (:func:`~enmi_torch.geometry.rectify.visible_cells`) are invalid.

    Example:
        >>> truth = camera_truth((8, 8), 1e-5)
        >>> bool(truth.variance[1, 4] > truth.variance[6, 4])
        True
    """
    height, width = check_image_shape("shape", shape)
    noise_power = check_positive_number("noise_power", noise_power)
    camera = RoadCamera.paper() if camera is None else camera
    near, far = check_value_range(distance_range, "distance_range")
    if near <= 0:
        raise ValueError(f"distance_range must be ahead of the camera (> 0), got {distance_range!r}")
    cell_size = (far - near) / height
    grid = GroundGrid((-width * cell_size / 2, width * cell_size / 2), (near, far), cell_size)
    variance = perspective_variance(camera, grid, noise_power)[0, 0]
    valid = visible_cells(camera, grid)
    return VarianceTruth(torch.where(valid, variance, torch.nan), valid, "camera")


# Pairs are float32 images of grey levels 0-255: draws of a few standard deviations, times 256, stay within the
# values the scores accept in float32 (FLOAT32_MAGNITUDE).
MAX_STD = FLOAT32_MAGNITUDE / 1e4


def check_std(name: str, value: object, *, positive: bool = False) -> float:
    """``value`` as a float in ``[0, MAX_STD]`` (``(0, MAX_STD]`` with ``positive``), else ``ValueError``."""
    low = "> 0" if positive else ">= 0"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a finite number {low}, got {value!r}")
    if not (0 < value if positive else 0 <= value) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number {low}, got {value!r}")
    if value > MAX_STD:
        raise ValueError(
            f"{name} must be at most {MAX_STD:.0e} (the pairs are float32 images of grey levels), got {value!r}"
        )
    return float(value)


def make_truth(flavour: str, shape: tuple[int, int], noise_std: float) -> VarianceTruth:
    """The ``flavour`` field (``"lidar"`` or ``"camera"``) scaled to an RMS noise std of ``noise_std`` where valid.

    Example:
        >>> truth = make_truth("camera", (32, 32), 10.0)
        >>> round(truth.mean_variance(), 6)
        100.0
    """
    check_option("flavour", flavour, FLAVOURS)
    noise_std = check_std("noise_std", noise_std, positive=True)
    target = noise_std**2
    shape_only = lidar_truth(shape) if flavour == "lidar" else camera_truth(shape, 1.0)
    return shape_only.scaled(target / shape_only.mean_variance())
