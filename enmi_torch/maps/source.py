"""A prior map as a source of windows: the search gets a window's cells, its valid mask and its transform.

:class:`MapSource` opens a map file (GeoTIFF or COG through rasterio, ``.npy``, PNG or JPEG) or wraps an array, and
cuts :class:`MapWindow` s around a point given in world coordinates (the map's CRS) or in cells. A GeoTIFF is read
by windows: the whole map is never loaded, and a window over the memory budget is refused before it is read.
Cell, world and yaw conventions: :class:`~enmi_torch.maps.GeoTransform`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from enmi_torch.maps.arrays import IMAGE_SUFFIXES, array_raster, read_array_file
from enmi_torch.maps.geotiff import GeoTiffRaster
from enmi_torch.maps.transform import GeoTransform
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import check_option

UNITS = ("world", "cells")


class MapWindow(NamedTuple):
    """A window of a map: its cells, which of them are valid, and where it lies in the map and in the world.

    Window cells are the map's cells less ``offset``: window cell ``(x, y)`` is map cell ``(x + x0, y + y0)``.
    Cells that lie off the map are in the window too (value 0, invalid), so the window's shape and its ``center``
    are those asked for wherever it lies.

    Attributes:
        image: ``(1, 1, h, w)`` the map's values (floating point, 0 where invalid).
        valid_mask: ``(1, 1, h, w)`` bool: ``False`` at nodata, masked, NaN or off-map cells.
        transform: :class:`~enmi_torch.maps.GeoTransform` of the window's cells (rasterio's ``window_transform``),
            or ``None`` for a map without georeferencing.
        offset: ``(x0, y0)``: the map cell of window cell ``(0, 0)`` (negative where the window starts off the map).
        center: ``(x, y)``: the window cell nearest to the point the window was cut around.
        crs: the map's coordinate reference system (``"EPSG:32633"``, else its WKT), or ``None``.
    """

    image: Tensor
    valid_mask: Tensor
    transform: GeoTransform | None
    offset: tuple[int, int]
    center: tuple[int, int]
    crs: str | None

    def to_world(self, poses: Any) -> Tensor:
        """Window-cell poses ``(..., 3)`` ``(x, y, yaw)`` (or points ``(..., 2)``) to world; float64."""
        return _georeferenced(self.transform).to_world(poses)

    def to_cells(self, poses: Any) -> Tensor:
        """World poses ``(..., 3)`` ``(X, Y, yaw)`` (or points ``(..., 2)``) to window cells; float64."""
        return _georeferenced(self.transform).to_cells(poses)

    def to_map_cells(self, poses: Any) -> Tensor:
        """Window-cell poses ``(..., 3)`` (or points ``(..., 2)``) to the whole map's cells; float64."""
        values = torch.as_tensor(poses, dtype=torch.float64).clone()
        values[..., 0] += self.offset[0]
        values[..., 1] += self.offset[1]
        return values


class MapSource:
    """A prior map that yields windows with their transform, so that the search never sees a file or a CRS.

    Open a file with :meth:`open` or wrap an array with :meth:`from_array`; cut windows with :meth:`window`; convert
    poses with :meth:`to_world` and :meth:`to_cells` (conventions: :class:`~enmi_torch.maps.GeoTransform`). A source
    opened from a file holds it open: use it in a ``with`` block or call :meth:`close`.

    Example:
        >>> import tempfile
        >>> from enmi_torch.maps import MapSource, write_geotiff
        >>> path = Path(tempfile.mkdtemp()) / "map.tif"
        >>> image = torch.arange(60.0).reshape(6, 10)  # 6 rows, 10 columns of 2 m cells, north up
        >>> _ = write_geotiff(path, image, (2.0, 0.0, 1000.0, 0.0, -2.0, 5000.0), crs="EPSG:32633")
        >>> with MapSource.open(path) as source:
        ...     window = source.window(around=(1009.0, 4997.0), radius=3.0)  # world metres
        >>> window.image[0, 0]  # 3 m: two cells each way from cell (4, 1); row -1 lies off the map
        tensor([[ 0.,  0.,  0.,  0.,  0.],
                [ 2.,  3.,  4.,  5.,  6.],
                [12., 13., 14., 15., 16.],
                [22., 23., 24., 25., 26.],
                [32., 33., 34., 35., 36.]])
        >>> window.valid_mask[0, 0, :, 0].tolist(), window.offset, window.center
        ([False, True, True, True, True], (2, -1), (2, 2))
        >>> window.to_world((2.0, 2.0, 0.0)).tolist()  # the centre cell's middle, in metres
        [1009.0, 4997.0, 0.0]
    """

    def __init__(self, raster: Any) -> None:
        """Use :meth:`open` or :meth:`from_array`."""
        self._raster = raster

    @classmethod
    def open(cls, path: str | Path, *, band: int | None = None, source: str = "path") -> MapSource:
        """Open a map file: ``.npy``, ``.png``, ``.jpg`` (read whole), anything else through rasterio, by windows.

        Args:
            path: the file (GeoTIFF, COG, or any raster GDAL reads; a URL GDAL reads too, such as a COG over HTTP).
            band: the band to read, numbered from 1; ``None``: the one band, or the luma of red, green and blue
                (:mod:`~enmi_torch.maps.bands`).
            source: where the path came from, named in messages (``"--map"``).

        Raises:
            ModuleNotFoundError: a GeoTIFF without rasterio installed (``pip install "enmi_torch[geo]"``).
            FileNotFoundError, ValueError: naming the file, when it is missing, unreadable or its bands ambiguous.
        """
        text = str(path)
        if Path(text).suffix.lower() in (".npy", *IMAGE_SUFFIXES):
            return cls(read_array_file(Path(text), band, source))
        if "://" not in text and not Path(text).is_file():
            raise FileNotFoundError(f"{source} {text!r}: no such file")
        return cls(GeoTiffRaster(text, band, source))

    @classmethod
    def from_array(
        cls, image: Any, *, transform: Any = None, crs: str | None = None, valid_mask: Any = None
    ) -> MapSource:
        """A map held in memory: a ``(H, W)`` (or ``(1, 1, H, W)``) tensor or array.

        Args:
            image: the map's values.
            transform: a :class:`~enmi_torch.maps.GeoTransform`, rasterio's ``Affine`` or six numbers
                ``(a, b, c, d, e, f)``; ``None``: not georeferenced (windows and poses in cells only).
            crs: the coordinate reference system's name (``"EPSG:32633"``), kept for the caller.
            valid_mask: bool, the map's shape: ``False`` cells are unmapped (NaN and infinite values are too).
        """
        return cls(array_raster(image, transform, crs, valid_mask))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: rows and columns of the whole map."""
        return self._raster.shape

    @property
    def transform(self) -> GeoTransform | None:
        """The map's :class:`~enmi_torch.maps.GeoTransform`, or ``None`` when it is not georeferenced."""
        return self._raster.transform

    @property
    def crs(self) -> str | None:
        """The coordinate reference system (``"EPSG:32633"``, else its WKT), or ``None``."""
        return self._raster.crs

    def to_world(self, poses: Any) -> Tensor:
        """Map-cell poses ``(..., 3)`` ``(x, y, yaw)`` (or points ``(..., 2)``) to world; float64."""
        return _georeferenced(self.transform, self._raster.name).to_world(poses)

    def to_cells(self, poses: Any) -> Tensor:
        """World poses ``(..., 3)`` ``(X, Y, yaw)`` (or points ``(..., 2)``) to map cells; float64."""
        return _georeferenced(self.transform, self._raster.name).to_cells(poses)

    def window(
        self, around: Any, radius: Any, *, units: str = "world", dtype: torch.dtype = torch.float32
    ) -> MapWindow:
        """The window of cells around a point: only these cells are read.

        Args:
            around: ``(x, y)`` or a pose ``(x, y, yaw)`` (the yaw is not used): world coordinates in the map's CRS
                (``units="world"``) or map cells (``units="cells"``). The window is centred on the cell nearest to it.
            radius: ``r`` or ``(rx, ry)``, ``>= 0``: world units along the world's X and Y (the window holds the
                cells of the world box ``around +- (rx, ry)``, rounded out to whole cells; on a rotated map its
                bounding box in cells), or whole cells along the columns and rows.
            units: ``"world"`` or ``"cells"``.
            dtype: floating dtype of :attr:`MapWindow.image`.

        Returns:
            :class:`MapWindow` of ``(2 Ry + 1, 2 Rx + 1)`` cells, ``Rx``, ``Ry`` the radius in cells.

        Raises:
            ValueError: the window lies wholly off the map, or a bad argument (named).
            MemoryBudgetError: the window is larger than the memory budget (nothing was read).
        """
        check_option("units", units, UNITS)
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise TypeError(f"dtype must be a floating torch.dtype, got {dtype!r}")
        point = _point("around", around)
        if units == "world":
            transform = _georeferenced(self.transform, self._raster.name)
            cells = transform.to_cells(point).tolist()
            center = [math.floor(value + 0.5) for value in cells]
            inverse = torch.linalg.inv(transform.matrix[:2, :2]).abs()
            reach = (inverse @ torch.tensor(_radius_pair(radius, whole=False), dtype=torch.float64)).tolist()
            half = [math.ceil(abs(cells[axis] - center[axis]) + reach[axis] - 1e-9) for axis in (0, 1)]
        else:
            center = [math.floor(value + 0.5) for value in point]
            half = list(_radius_pair(radius, whole=True))
        return self._cut(center, half, dtype, f"radius={radius!r}")

    def _cut(self, center: list[int], half: list[int], dtype: torch.dtype, cause: str) -> MapWindow:
        height, width = 2 * half[1] + 1, 2 * half[0] + 1
        x0, y0 = center[0] - half[0], center[1] - half[1]
        check_cells_memory(
            cause,
            height * width,
            self._raster.bytes_per_cell + torch.finfo(dtype).bits // 8 + 1,
            f"the {height} x {width} window of {self._raster.name}",
            "pass a smaller radius",
        )
        rows, cols = self.shape
        top, bottom, left, right = max(y0, 0), min(y0 + height, rows), max(x0, 0), min(x0 + width, cols)
        if top >= bottom or left >= right:
            raise ValueError(
                f"the window around cell (x, y) = ({center[0]}, {center[1]}) lies off the {rows} x {cols} map "
                f"({self._raster.name}): its columns {x0}..{x0 + width - 1}, rows {y0}..{y0 + height - 1}"
            )
        image = np.zeros((height, width), dtype=np.float64)
        valid = np.zeros((height, width), dtype=bool)
        values, inside = self._raster.read(top, left, bottom - top, right - left)
        image[top - y0 : bottom - y0, left - x0 : right - x0] = np.where(inside, values, 0.0)
        valid[top - y0 : bottom - y0, left - x0 : right - x0] = inside
        transform = None if self.transform is None else self.transform.translated(x0, y0)
        return MapWindow(
            torch.from_numpy(image).to(dtype)[None, None],
            torch.from_numpy(valid)[None, None],
            transform,
            (x0, y0),
            (half[0], half[1]),
            self.crs,
        )

    def close(self) -> None:
        """Release the file (a map in memory has none)."""
        self._raster.close()

    def __enter__(self) -> MapSource:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        rows, cols = self.shape
        return f"MapSource({self._raster.name}, {rows} x {cols} cells, crs={self.crs!r})"


def _georeferenced(transform: GeoTransform | None, name: str = "the window") -> GeoTransform:
    if transform is None:
        raise ValueError(
            f"world coordinates need a georeferenced map, and {name} has no geotransform: give points and poses in "
            "cells (units='cells')"
        )
    return transform


def _point(name: str, value: Any) -> list[float]:
    try:
        values = [float(number) for number in value]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (x, y) or (x, y, yaw), numbers, got {value!r}") from None
    if len(values) not in (2, 3) or not all(math.isfinite(number) for number in values):
        raise ValueError(f"{name} must be (x, y) or (x, y, yaw), finite numbers, got {value!r}")
    return values[:2]


def _radius_pair(radius: Any, *, whole: bool) -> tuple[Any, Any]:
    """``(rx, ry)`` from ``r`` or ``(rx, ry)``: whole numbers of cells, or finite world lengths, ``>= 0``."""
    pair = radius if isinstance(radius, (tuple, list)) else (radius, radius)
    kinds = (int,) if whole else (int, float)
    expected = "an int >= 0 (cells)" if whole else "a finite number >= 0 (world units)"
    if len(pair) != 2 or not all(
        isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value) and value >= 0
        for value in pair
    ):
        raise ValueError(f"radius must be {expected} or a pair (rx, ry) of them, got {radius!r}")
    return pair[0], pair[1]
