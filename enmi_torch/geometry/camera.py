"""The paper's road camera: a pinhole at height ``h`` above a flat road, tilted down by ``theta``.

Convention:
    Lengths are in one unit of the user's choice (the paper uses cm) for ``focal_length``, ``height``, ground
    coordinates and focal-plane coordinates alike. A ground point is ``(x, d)``: lateral offset ``x`` (right
    positive) and horizontal distance ``d`` ahead of the camera. Its camera depth is ``z = d cos(theta) + h
    sin(theta)`` and its focal-plane coordinates are ``x~ = f x / z``, ``y~ = f tan(theta) - f h sec(theta) / z``
    (eqs. perspTransformation and yTildeFunctionOfZ; ``y~`` grows towards the horizon). Functions take tensors or
    numbers and broadcast; Python numbers become float64 tensors.

    Pixels: ``(u, v)`` with ``u`` the column (right, with ``x~``) and ``v`` the row (down, against ``y~``), pixel
    centres at integers. The sensor (the two fields of view) spans ``u`` in ``[-0.5, W - 0.5]`` and ``v`` in
    ``[-0.5, H - 0.5]``: ``u = x~ / p_x + (W - 1) / 2`` and ``v = (H - 1) / 2 - y~ / p_y`` with ``(p_y, p_x)`` the
    pixel pitch :attr:`RoadCamera.pixel_size`. These are the pixel coordinates kornia's ``warp_perspective`` uses
    with ``align_corners=True``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from enmi_torch.utils.checks import check_image_shape, check_positive_number
from enmi_torch.utils.config import check_config_keys, load_yaml_section


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

    A camera described by its sensor size instead of its fields of view: :meth:`from_sensor_size`; from a
    configuration file: :meth:`from_yaml` (e.g. ``configs/camera/paper.yaml``).

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
        object.__setattr__(self, "image_size", check_image_shape("image_size", self.image_size))

    @classmethod
    def paper(cls, image_size: tuple[int, int] = (480, 640)) -> RoadCamera:
        """The camera of the paper's simulation: f = 0.0367 cm, theta = 35.9020 deg, h = 58.3095 cm, 39.3 x 70.5 deg."""
        return cls(0.0367, 58.3095, 35.9020, 39.3, 70.5, image_size)

    @classmethod
    def from_sensor_size(
        cls,
        focal_length: float,
        height: float,
        tilt_deg: float,
        sensor_size: tuple[float, float],
        image_size: tuple[int, int] = (480, 640),
    ) -> RoadCamera:
        """A camera given by its sensor ``(height, width)`` in length units instead of its fields of view.

        Example:
            >>> paper = RoadCamera.paper()
            >>> same = RoadCamera.from_sensor_size(0.0367, 58.3095, 35.9020, paper.sensor_size)
            >>> round(same.horizontal_fov_deg, 6)
            70.5
        """
        f = check_positive_number("focal_length", focal_length)
        try:
            sensor_height, sensor_width = (check_positive_number("sensor_size", float(s)) for s in sensor_size)
        except (TypeError, ValueError) as error:
            raise ValueError(
                f"sensor_size must be (height, width), two numbers > 0, got {sensor_size!r} ({error})"
            ) from None
        return cls(
            f,
            height,
            tilt_deg,
            math.degrees(2 * math.atan(sensor_height / (2 * f))),
            math.degrees(2 * math.atan(sensor_width / (2 * f))),
            tuple(image_size),
        )

    @classmethod
    def from_dict(cls, config: Mapping[str, Any]) -> RoadCamera:
        """A camera from a mapping (a YAML section): the constructor's arguments by name.

        Keys: ``focal_length``, ``height``, ``tilt_deg``, optional ``image_size``, and either ``vertical_fov_deg`` and
        ``horizontal_fov_deg`` or ``sensor_size: [height, width]``.

        Example:
            >>> RoadCamera.from_dict({"focal_length": 1.0, "height": 2.0, "tilt_deg": 30.0,
            ...                       "vertical_fov_deg": 20.0, "horizontal_fov_deg": 40.0}).image_size
            (480, 640)
        """
        fields = ("focal_length", "height", "tilt_deg")
        by_fov = ("vertical_fov_deg", "horizontal_fov_deg")
        check_config_keys("camera", config, required=fields, optional=(*by_fov, "sensor_size", "image_size"))
        image_size = tuple(config.get("image_size", (480, 640)))
        if "sensor_size" in config:
            if any(key in config for key in by_fov):
                raise ValueError("camera config must give either sensor_size or the two fields of view, not both")
            return cls.from_sensor_size(*(config[key] for key in fields), config["sensor_size"], image_size)
        missing = [key for key in by_fov if key not in config]
        if missing:
            raise ValueError(f"camera config must give sensor_size or both fields of view, missing {missing}")
        return cls(*(config[key] for key in (*fields, *by_fov)), image_size)

    @classmethod
    def from_yaml(cls, path: str | Path, key: str = "camera") -> RoadCamera:
        """The camera in section ``key`` of a YAML file (see :meth:`from_dict`), e.g. ``configs/camera/paper.yaml``.

        Raises:
            ValueError: naming the file, when it is not readable YAML (a syntax error, a binary file, a tag such as
                ``!!python/object``, which is refused without running anything) or lacks the section; naming the
                key, when a value is wrong.
        """
        return cls.from_dict(load_yaml_section(path, key, "camera config file"))

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

    @property
    def pixel_size(self) -> tuple[float, float]:
        """``(p_y, p_x)``: height and width of one pixel on the focal plane, in length units."""
        (sensor_height, sensor_width), (rows, cols) = self.sensor_size, self.image_size
        return sensor_height / rows, sensor_width / cols

    def visible_distance_range(self) -> tuple[float, float]:
        """Nearest and farthest road distance ``d`` seen by the vertical field of view."""
        half = math.radians(self.vertical_fov_deg) / 2
        return self.height / math.tan(self.tilt + half), self.height / math.tan(self.tilt - half)

    def visible_half_width(self, distance: Tensor | float) -> Tensor:
        """Largest ``|x|`` seen at road distance ``distance`` (the horizontal view: ``|x~| <= f tan(hfov / 2)``)."""
        return camera_depth(self, distance) * math.tan(math.radians(self.horizontal_fov_deg) / 2)


def _as_tensor(value: Tensor | float) -> Tensor:
    return value if isinstance(value, Tensor) else torch.tensor(float(value), dtype=torch.float64)


def _area_scale(camera: RoadCamera) -> float:
    """``f^2 h sec(theta)``: the constant of det J and of every focal-plane area (eqs. Jacobian and TildeA)."""
    return camera.focal_length**2 * camera.height / math.cos(camera.tilt)


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
    """``det J = f^2 h sec(theta) / z^3`` of the map ``(x, z) -> (x~, y~)`` (eq. Jacobian).

    The paper prints ``-f^2 h sec(theta) / z^3``; ``d y~ / d z`` of ``y~ = f tan(theta) - f h sec(theta) / z`` is
    ``+f h sec(theta) / z^2``, so the determinant is positive (``y~`` and ``z`` both grow towards the horizon). Only
    ``|det J|``, the local area scale, enters eq. TildeA.
    """
    return _area_scale(camera) / _as_tensor(depth) ** 3


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
    near, far = camera_depth(camera, distance_near), camera_depth(camera, distance_far)
    width = _as_tensor(lateral_high) - _as_tensor(lateral_low)
    return _area_scale(camera) * width / 2 * (1 / near**2 - 1 / far**2)


def visible_projected_area(
    camera: RoadCamera,
    lateral_low: Tensor | float,
    lateral_high: Tensor | float,
    distance_near: Tensor | float,
    distance_far: Tensor | float,
) -> Tensor:
    r"""Focal-plane area of the part of the road rectangle ``[x_l, x_u] x [d_near, d_far]`` that the camera sees.

    The rectangle is clipped to the view: ``d`` within :meth:`RoadCamera.visible_distance_range` and ``|x| <= z
    tan(hfov / 2)`` (the sensor's width). Where it lies inside the view this is :func:`projected_area`; where it
    lies outside, 0. Exact: the visible width ``w(z)`` is linear in the camera depth ``z`` between the depths where
    the view's side edges cross ``x_l`` or ``x_u``, and on each such piece ``f^2 h sec(theta) \int w(z) / z^3 dz``
    has the closed form ``f^2 h sec(theta) (z_b - z_a) (w_a z_b + w_b z_a) / (2 z_a^2 z_b^2)``.

    Convention:
        Broadcasts its tensor arguments; float64 for Python numbers; differentiable in the ground coordinates.
        Needs ``x_l <= x_u`` and ``d_near <= d_far`` (an empty rectangle gives 0).

    Example:
        >>> camera = RoadCamera.paper()
        >>> inside = visible_projected_area(camera, -10.0, 10.0, 40.0, 60.0)
        >>> bool(torch.isclose(inside, projected_area(camera, -10.0, 10.0, 40.0, 60.0)))
        True
        >>> f"{visible_projected_area(camera, 30.0, 50.0, 40.0, 60.0).item():.3e}"  # a corner is out of view
        '7.530e-05'
    """
    slope = math.tan(math.radians(camera.horizontal_fov_deg) / 2)
    lateral_low, lateral_high = _as_tensor(lateral_low), _as_tensor(lateral_high)
    view_near, view_far = camera.visible_distance_range()
    near = camera_depth(camera, torch.clamp(_as_tensor(distance_near), min=view_near))
    far = torch.maximum(camera_depth(camera, torch.clamp(_as_tensor(distance_far), max=view_far)), near)
    # The visible width is piecewise linear in z with kinks where slope * z meets |x_l| or |x_u|.
    kinks = [torch.minimum(torch.maximum(edge.abs() / slope, near), far) for edge in (lateral_low, lateral_high)]
    depths = torch.sort(torch.stack(torch.broadcast_tensors(near, *kinks, far), dim=-1), dim=-1).values
    width = torch.clamp(
        torch.minimum(lateral_high.unsqueeze(-1), slope * depths)
        - torch.maximum(lateral_low.unsqueeze(-1), -slope * depths),
        min=0,
    )
    z_a, z_b, w_a, w_b = depths[..., :-1], depths[..., 1:], width[..., :-1], width[..., 1:]
    pieces = (z_b - z_a) * (w_a * z_b + w_b * z_a) / (2 * z_a**2 * z_b**2)
    return _area_scale(camera) * pieces.sum(dim=-1)


def ground_to_focal_matrix(camera: RoadCamera, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """The ``3 x 3`` homography from road points ``(x, d, 1)`` to focal-plane points ``(x~, y~, 1)``.

    Rows ``(f, 0, 0)``, ``(0, f sin(theta), -f h cos(theta))``, ``(0, cos(theta), h sin(theta))``: the third
    coordinate is the camera depth ``z``, so ``x~ = f x / z`` and ``y~ = f (d sin(theta) - h cos(theta)) / z``
    (eq. perspTransformation with the road's ``y``).
    """
    f, h, theta = camera.focal_length, camera.height, camera.tilt
    rows = [
        [f, 0.0, 0.0],
        [0.0, f * math.sin(theta), -f * h * math.cos(theta)],
        [0.0, math.cos(theta), h * math.sin(theta)],
    ]
    return torch.tensor(rows, dtype=dtype, device=device)


def focal_to_pixel_matrix(camera: RoadCamera, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """The ``3 x 3`` affine map from focal-plane points ``(x~, y~, 1)`` to pixels ``(u, v, 1)`` (module convention)."""
    (pitch_y, pitch_x), (rows, cols) = camera.pixel_size, camera.image_size
    matrix = [[1 / pitch_x, 0.0, (cols - 1) / 2], [0.0, -1 / pitch_y, (rows - 1) / 2], [0.0, 0.0, 1.0]]
    return torch.tensor(matrix, dtype=dtype, device=device)


def focal_to_pixel(camera: RoadCamera, focal_x: Tensor | float, focal_y: Tensor | float) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``(u, v)`` of focal-plane points ``(x~, y~)``.

    Module convention: ``u`` right, ``v`` down, pixel centres at integers.

    Example:
        >>> camera = RoadCamera.paper()
        >>> [round(c.item(), 6) for c in focal_to_pixel(camera, 0.0, camera.sensor_size[0] / 2)]
        [319.5, -0.5]
    """
    (pitch_y, pitch_x), (rows, cols) = camera.pixel_size, camera.image_size
    return _as_tensor(focal_x) / pitch_x + (cols - 1) / 2, (rows - 1) / 2 - _as_tensor(focal_y) / pitch_y


def pixel_to_focal(camera: RoadCamera, u: Tensor | float, v: Tensor | float) -> tuple[Tensor, Tensor]:
    """Focal-plane coordinates ``(x~, y~)`` of pixels ``(u, v)``; the inverse of :func:`focal_to_pixel`."""
    (pitch_y, pitch_x), (rows, cols) = camera.pixel_size, camera.image_size
    return (_as_tensor(u) - (cols - 1) / 2) * pitch_x, ((rows - 1) / 2 - _as_tensor(v)) * pitch_y


def ground_to_pixel(camera: RoadCamera, lateral: Tensor | float, distance: Tensor | float) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``(u, v)`` of road points ``(x, d)``: :func:`project_ground` then :func:`focal_to_pixel`.

    Example:
        >>> camera = RoadCamera.paper()
        >>> near, far = camera.visible_distance_range()
        >>> [round(ground_to_pixel(camera, 0.0, d)[1].item(), 6) for d in (near, far)]
        [479.5, -0.5]
    """
    return focal_to_pixel(camera, *project_ground(camera, lateral, distance))


def pixel_to_ground(camera: RoadCamera, u: Tensor | float, v: Tensor | float) -> tuple[Tensor, Tensor]:
    """Road points ``(x, d)`` seen at pixels ``(u, v)`` (depth from eq. z); the inverse of :func:`ground_to_pixel`.

    Rows above the horizon have no road point: they give a depth ``z <= 0``, i.e. ``d <= -h tan(theta)``.
    """
    focal_x, focal_y = pixel_to_focal(camera, u, v)
    depth = depth_from_focal_plane_y(camera, focal_y)
    theta = camera.tilt
    return focal_x * depth / camera.focal_length, (depth - camera.height * math.sin(theta)) / math.cos(theta)


def signal_to_noise_ratio(amplitude: Tensor | float, noise_power: Tensor | float, area: Tensor | float) -> Tensor:
    """``SNR = a^2 A~ / N0`` of a uniform road tile of amplitude ``a`` and focal-plane area ``A~`` (eq. SNR)."""
    return _as_tensor(amplitude) ** 2 * _as_tensor(area) / _as_tensor(noise_power)


def tile_noise_variance(noise_power: Tensor | float, area: Tensor | float) -> Tensor:
    """Per-tile noise variance ``sigma^2 = N0 / A~`` of the area-normalised tile amplitude."""
    return _as_tensor(noise_power) / _as_tensor(area)
