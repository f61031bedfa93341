"""World coordinates of a map's cells: the affine geotransform, and poses ``(x, y, yaw)`` converted both ways.

The conventions (cells, world coordinates, the world yaw) are :class:`GeoTransform`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True)
class GeoTransform:
    """The affine map from a raster's pixel corners to world coordinates, and poses converted with it.

    Convention:
        **Cells.** A pose ``(x, y, yaw)`` in cells has ``x`` the map column and ``y`` the map row (down), whole
        numbers at a cell's centre (cell ``(0, 0)`` is the top-left one), and ``yaw`` in degrees counter-clockwise
        as displayed: the captured image is the map section rotated by ``yaw`` about its centre, so its top points
        ``yaw`` degrees clockwise from the map's up (the library's one pose convention; heading east on a north-up
        map is yaw 90).

        **World.** ``(X, Y)`` in the map's coordinate reference system (easting and northing of a projected CRS).
        The coefficients are rasterio's ``Affine(a, b, c, d, e, f)`` (GDAL's geotransform ``(c, a, b, f, d, e)``),
        which maps *pixel corners*: corner ``(column, row)`` lies at ``(a column + b row + c, d column + e row + f)``.
        A cell's centre is half a cell in: ``X = a (x + 0.5) + b (y + 0.5) + c``,
        ``Y = d (x + 0.5) + e (y + 0.5) + f``, which is rasterio's ``transform @ (x + 0.5, y + 0.5)`` and
        ``rasterio.transform.xy(transform, y, x)``. A north-up map has ``b = d = 0`` and ``e < 0``; a flipped one
        ``e > 0`` (rows run north); a rotated one ``b, d != 0``.

        **World yaw.** The heading of the captured image's top in the world: degrees clockwise from the world's
        ``+Y`` axis (north) towards ``+X`` (east), wrapped to ``(-180, 180]``. The top's direction
        ``(sin yaw, -cos yaw)`` in cells is carried into the world by the linear part ``[[a, b], [d, e]]``, and read
        back the same way. So on a north-up map the world yaw *is* the cell yaw; on a flipped map it is
        ``180 - yaw``; on a map whose cell axes are turned ``theta`` degrees counter-clockwise in the world
        (rasterio's ``Affine.rotation(theta)``) it is ``yaw - theta``. The conversion is exact both ways for any
        invertible transform. The search turns images on the square cell grid: on a map whose cells are not
        square in the world (``|a| != |e|``) it turns captured images in cells, not in metres.

    Attributes:
        a, b, c, d, e, f: the coefficients, finite, with ``a e - b d != 0``.

    Example:
        >>> north_up = GeoTransform(0.5, 0.0, 500000.0, 0.0, -0.5, 5400000.0)  # 0.5 m cells, top-left corner
        >>> north_up.to_world((10.0, 20.0, 90.0)).tolist()  # cell column 10, row 20, heading east
        [500005.25, 5399989.75, 90.0]
        >>> north_up.to_cells((500005.25, 5399989.75, 90.0)).tolist()
        [10.0, 20.0, 90.0]
        >>> flipped = GeoTransform(0.5, 0.0, 500000.0, 0.0, 0.5, 5390000.0)  # rows run north
        >>> flipped.to_world((10.0, 20.0, 30.0)).tolist()
        [500005.25, 5390010.25, 150.0]
    """

    a: float
    b: float
    c: float
    d: float
    e: float
    f: float

    def __post_init__(self) -> None:
        values = (self.a, self.b, self.c, self.d, self.e, self.f)
        if not all(isinstance(value, (int, float)) and not isinstance(value, bool) for value in values):
            raise TypeError(f"GeoTransform takes six numbers (a, b, c, d, e, f), got {values!r}")
        if not all(math.isfinite(value) for value in values):
            raise ValueError(f"GeoTransform must have finite coefficients, got {values!r}")
        if self.a * self.e - self.b * self.d == 0:
            raise ValueError(
                f"GeoTransform must be invertible (a e - b d != 0), got a={self.a}, b={self.b}, d={self.d}, e={self.e}"
            )

    @classmethod
    def from_affine(cls, affine: Any) -> GeoTransform:
        """From rasterio's ``Affine`` (or any sequence whose first six values are ``a, b, c, d, e, f``)."""
        try:
            values = [float(value) for value in list(affine)[:6]]
        except (TypeError, ValueError):
            raise TypeError(f"transform must be an Affine or six numbers (a, b, c, d, e, f), got {affine!r}") from None
        if len(values) != 6:
            raise ValueError(f"transform must hold six numbers (a, b, c, d, e, f), got {affine!r}")
        return cls(*values)

    @classmethod
    def from_gdal(cls, geotransform: Any) -> GeoTransform:
        """From GDAL's geotransform ``(c, a, b, f, d, e)`` (``dataset.GetGeoTransform()``)."""
        c, a, b, f, d, e = (float(value) for value in geotransform)
        return cls(a, b, c, d, e, f)

    @property
    def affine(self) -> tuple[float, float, float, float, float, float]:
        """``(a, b, c, d, e, f)``, as ``rasterio.Affine(*transform.affine)`` takes them."""
        return (self.a, self.b, self.c, self.d, self.e, self.f)

    @property
    def matrix(self) -> Tensor:
        """``(3, 3)`` float64: cell centre ``[x, y, 1]`` to world ``[X, Y, 1]`` (the half cell included)."""
        linear = torch.tensor([[self.a, self.b], [self.d, self.e]], dtype=torch.float64)
        offset = torch.tensor([self.c, self.f], dtype=torch.float64) + linear @ torch.tensor([0.5, 0.5]).double()
        matrix = torch.eye(3, dtype=torch.float64)
        matrix[:2, :2], matrix[:2, 2] = linear, offset
        return matrix

    @property
    def cell_size(self) -> tuple[float, float]:
        """World length of one cell step along the columns and along the rows (positive, map units)."""
        return math.hypot(self.a, self.d), math.hypot(self.b, self.e)

    def translated(self, x0: int, y0: int) -> GeoTransform:
        """The transform of a window whose cell ``(0, 0)`` is this map's cell ``(x0, y0)`` (``window_transform``)."""
        return GeoTransform(
            self.a, self.b, self.c + self.a * x0 + self.b * y0, self.d, self.e, self.f + self.d * x0 + self.e * y0
        )

    def to_world(self, poses: Any) -> Tensor:
        """Cell poses ``(..., 3)`` ``(x, y, yaw)`` or points ``(..., 2)`` ``(x, y)`` to world ``(X, Y[, yaw])``.

        Returns float64 of the same shape (on the device of a tensor given); yaws wrapped to ``(-180, 180]``.
        """
        values = _as_poses("poses", poses)
        linear = torch.tensor([[self.a, self.b], [self.d, self.e]], dtype=torch.float64, device=values.device)
        corner = torch.tensor([self.c, self.f], dtype=torch.float64, device=values.device)
        world = (values[..., :2] + 0.5) @ linear.T + corner
        if values.shape[-1] == 2:
            return world
        radians = torch.deg2rad(values[..., 2])
        top = torch.stack([radians.sin(), -radians.cos()], -1) @ linear.T  # the image's top, in the world
        return torch.cat([world, _heading(top[..., 0], top[..., 1])[..., None]], -1)

    def to_cells(self, poses: Any) -> Tensor:
        """World poses ``(..., 3)`` ``(X, Y, yaw)`` or points ``(..., 2)`` to cells; the inverse of :meth:`to_world`."""
        values = _as_poses("poses", poses)
        linear = torch.tensor([[self.a, self.b], [self.d, self.e]], dtype=torch.float64, device=values.device)
        corner = torch.tensor([self.c, self.f], dtype=torch.float64, device=values.device)
        inverse = torch.linalg.inv(linear)
        cells = (values[..., :2] - corner) @ inverse.T - 0.5
        if values.shape[-1] == 2:
            return cells
        radians = torch.deg2rad(values[..., 2])
        top = torch.stack([radians.sin(), radians.cos()], -1) @ inverse.T  # the image's top, in cells
        return torch.cat([cells, _heading(top[..., 0], -top[..., 1])[..., None]], -1)


def _heading(towards_x: Tensor, towards_up: Tensor) -> Tensor:
    """Degrees clockwise from "up" to the direction ``(towards_x, towards_up)``, in ``(-180, 180]``."""
    degrees = torch.rad2deg(torch.atan2(towards_x, towards_up))
    return torch.where(degrees <= -180, degrees + 360, degrees)


def _as_poses(name: str, poses: Any) -> Tensor:
    """``poses`` as a float64 tensor ``(..., 2)`` or ``(..., 3)`` of finite values."""
    try:
        values = torch.as_tensor(poses, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name} must be numbers (x, y) or (x, y, yaw), or a tensor of them, got {poses!r}") from None
    if values.ndim == 0 or values.shape[-1] not in (2, 3):
        raise ValueError(f"{name} must have shape (..., 2) (x, y) or (..., 3) (x, y, yaw), got {tuple(values.shape)}")
    if not bool(torch.isfinite(values).all()):
        raise ValueError(f"{name} must be finite, got {values.tolist()}")
    return values
