"""The paper's road camera: a pinhole at height ``h`` above a flat road, tilted down by ``theta``.

Convention:
    Lengths are in one unit of the user's choice (the paper uses cm) for ``focal_length``, ``height``, ground
    coordinates and focal-plane coordinates alike. A ground point is ``(x, d)``: lateral offset ``x`` (right
    positive) and horizontal distance ``d`` ahead of the camera. Its camera depth is ``z = d cos(theta) + h
    sin(theta)`` and its focal-plane coordinates are ``x~ = f x / z``, ``y~ = f tan(theta) - f h sec(theta) / z``
    (eqs. perspTransformation and yTildeFunctionOfZ; ``y~`` grows towards the horizon). Functions take tensors or
    numbers and broadcast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from enmi_torch._checks import check_positive_number


@dataclass(frozen=True)
class RoadCamera:
    """A pinhole camera above a flat road (paper, section "Problem Formulation").

    Args:
        focal_length: ``f``.
        height: ``h``, height of the pinhole above the road.
        tilt_deg: ``theta``, downward tilt of the optical axis from the horizontal, in degrees, in (0, 90).
        vertical_fov_deg: full vertical field of view, in degrees.
        horizontal_fov_deg: full horizontal field of view, in degrees.
        image_size: ``(H, W)`` of the sensor in pixels.

    Example:
        >>> camera = RoadCamera.paper()
        >>> [round(d, 1) for d in camera.visible_distance_range()]
        [40.0, 200.0]
    """

    focal_length: float
    height: float
    tilt_deg: float
    vertical_fov_deg: float
    horizontal_fov_deg: float
    image_size: tuple[int, int] = (480, 640)

    def __post_init__(self) -> None:
        check_positive_number("focal_length", self.focal_length)
        check_positive_number("height", self.height)
        for name in ("tilt_deg", "vertical_fov_deg", "horizontal_fov_deg"):
            value = check_positive_number(name, getattr(self, name))
            if value >= (90 if name == "tilt_deg" else 180):
                raise ValueError(f"{name} must be in (0, {90 if name == 'tilt_deg' else 180}) degrees, got {value}")
        if self.tilt_deg - self.vertical_fov_deg / 2 <= 0:
            raise ValueError(
                "tilt_deg must exceed half of vertical_fov_deg so that the whole view meets the road, got "
                f"tilt_deg={self.tilt_deg}, vertical_fov_deg={self.vertical_fov_deg}"
            )
        if len(self.image_size) != 2 or any(int(size) < 1 for size in self.image_size):
            raise ValueError(f"image_size must be (H, W) with positive sizes, got {self.image_size!r}")

    @classmethod
    def paper(cls, image_size: tuple[int, int] = (480, 640)) -> RoadCamera:
        """The camera of the paper's simulation: f = 0.0367 cm, theta = 35.9020 deg, h = 58.3095 cm, 39.3 x 70.5 deg."""
        return cls(0.0367, 58.3095, 35.9020, 39.3, 70.5, image_size)

    @property
    def tilt(self) -> float:
        """``theta`` in radians."""
        return math.radians(self.tilt_deg)

    @property
    def sensor_size(self) -> tuple[float, float]:
        """``(height, width)`` of the focal plane covered by the fields of view, in length units."""
        return (
            2 * self.focal_length * math.tan(math.radians(self.vertical_fov_deg) / 2),
            2 * self.focal_length * math.tan(math.radians(self.horizontal_fov_deg) / 2),
        )

    def visible_distance_range(self) -> tuple[float, float]:
        """Nearest and farthest road distance ``d`` seen by the vertical field of view."""
        half = math.radians(self.vertical_fov_deg) / 2
        return self.height / math.tan(self.tilt + half), self.height / math.tan(self.tilt - half)

    def visible_half_width(self, distance: Tensor | float) -> Tensor:
        """Largest ``|x|`` seen at road distance ``distance`` (the horizontal view: ``|x~| <= f tan(hfov / 2)``)."""
        return camera_depth(self, distance) * math.tan(math.radians(self.horizontal_fov_deg) / 2)


def _as_tensor(value: Tensor | float) -> Tensor:
    return value if isinstance(value, Tensor) else torch.tensor(float(value), dtype=torch.float64)


def camera_depth(camera: RoadCamera, distance: Tensor | float) -> Tensor:
    """Camera depth ``z = d cos(theta) + h sin(theta)`` of road points at distance ``d`` ahead.

    Example:
        >>> round(camera_depth(RoadCamera.paper(), 40.0).item(), 3)
        66.594
    """
    return _as_tensor(distance) * math.cos(camera.tilt) + camera.height * math.sin(camera.tilt)


def focal_plane_y(camera: RoadCamera, depth: Tensor | float) -> Tensor:
    """``y~ = f tan(theta) - f h sec(theta) / z`` (eq. yTildeFunctionOfZ) of road points at camera depth ``z``."""
    f, theta = camera.focal_length, camera.tilt
    return f * math.tan(theta) - f * camera.height / (math.cos(theta) * _as_tensor(depth))


def depth_from_focal_plane_y(camera: RoadCamera, focal_y: Tensor | float) -> Tensor:
    """Camera depth ``z = f h / (f sin(theta) - y~ cos(theta))`` of the road seen at ``y~`` (eq. z)."""
    f, theta = camera.focal_length, camera.tilt
    return f * camera.height / (f * math.sin(theta) - _as_tensor(focal_y) * math.cos(theta))


def project_ground(camera: RoadCamera, lateral: Tensor | float, distance: Tensor | float) -> tuple[Tensor, Tensor]:
    """Focal-plane coordinates ``(x~, y~)`` of road points ``(x, d)`` (eq. perspTransformation)."""
    depth = camera_depth(camera, distance)
    return camera.focal_length * _as_tensor(lateral) / depth, focal_plane_y(camera, depth)


def jacobian_determinant(camera: RoadCamera, depth: Tensor | float) -> Tensor:
    """``det J = -f^2 h sec(theta) / z^3`` of the map ``(x, z) -> (x~, y~)`` (eq. Jacobian)."""
    f = camera.focal_length
    return -(f**2) * camera.height / math.cos(camera.tilt) / _as_tensor(depth) ** 3


def projected_area(
    camera: RoadCamera,
    lateral_low: Tensor | float,
    lateral_high: Tensor | float,
    distance_near: Tensor | float,
    distance_far: Tensor | float,
) -> Tensor:
    """Focal-plane area ``A~`` of the road rectangle ``[x_l, x_u] x [d_near, d_far]`` (eq. TildeA, exact).

    ``A~ = f^2 h sec(theta) (x_u - x_l) / 2 (1 / z_l^2 - 1 / z_u^2)`` with ``z_l``, ``z_u`` the camera depths of the
    near and far edges.

    Example:
        >>> area = projected_area(RoadCamera.paper(), -10.0, 10.0, 40.0, 60.0)
        >>> f"{area.item():.3e}"
        '7.719e-05'
    """
    f = camera.focal_length
    near, far = camera_depth(camera, distance_near), camera_depth(camera, distance_far)
    width = _as_tensor(lateral_high) - _as_tensor(lateral_low)
    return f**2 * camera.height / math.cos(camera.tilt) * width / 2 * (1 / near**2 - 1 / far**2)


def signal_to_noise_ratio(amplitude: Tensor | float, noise_power: Tensor | float, area: Tensor | float) -> Tensor:
    """``SNR = a^2 A~ / N0`` of a uniform road tile of amplitude ``a`` and focal-plane area ``A~`` (eq. SNR)."""
    return _as_tensor(amplitude) ** 2 * _as_tensor(area) / _as_tensor(noise_power)


def tile_noise_variance(noise_power: Tensor | float, area: Tensor | float) -> Tensor:
    """Per-tile noise variance ``sigma^2 = N0 / A~`` of the area-normalised tile amplitude."""
    return _as_tensor(noise_power) / _as_tensor(area)
