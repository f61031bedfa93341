"""GeoTIFF and Cloud-Optimized GeoTIFF maps (any raster GDAL reads), read by windows with rasterio.

Only the cells a window asks for are read (rasterio's windowed ``read`` and ``read_masks``); the file stays open
until :meth:`GeoTiffRaster.close`. rasterio comes with the ``geo`` extra (``pip install "enmi_torch[geo]"``) and is
imported when a file is opened, never by ``import enmi_torch``.

Invalid cells are the ones GDAL's mask says are (nodata values, an alpha band, an internal mask) and NaN or infinite
values. A band's scale and offset (``value * scale + offset``), when the file states them, are applied.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from enmi_torch.maps.bands import choose_bands
from enmi_torch.maps.transform import GeoTransform

GEO_EXTRA = 'pip install "enmi_torch[geo]"'


def import_rasterio(named: str) -> Any:
    """The rasterio module, or ``ModuleNotFoundError`` naming ``named`` and the extra that installs it."""
    try:
        import rasterio
    except ImportError as error:
        raise ModuleNotFoundError(f"{named}: reading a GeoTIFF needs rasterio: {GEO_EXTRA}", name="rasterio") from error
    return rasterio


class GeoTiffRaster:
    """An open raster: its shape, transform and CRS, and windowed reads of the chosen bands."""

    def __init__(self, path: str, band: Any, source: str) -> None:
        self.name = f"{source} {path!r}"
        rasterio = import_rasterio(self.name)
        try:
            with warnings.catch_warnings():  # a plain TIFF has no georeferencing: said by transform None, not a warning
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                self.dataset = rasterio.open(path)
        except rasterio.errors.RasterioIOError as error:
            raise ValueError(f"{self.name} cannot be read as a raster: {error}") from None
        try:
            self._describe(band)
        except BaseException:
            self.dataset.close()
            raise

    def _describe(self, band: Any) -> None:
        dataset = self.dataset
        self.shape = (dataset.height, dataset.width)
        colours = [interpretation.name.lower() for interpretation in dataset.colorinterp]
        self.bands, self.weights = choose_bands(band, colours, self.name)
        if any(colours[index - 1] == "palette" for index in self.bands):
            raise ValueError(f"{self.name} holds palette indices, not values: expand it first (gdal_translate -expand)")
        if any(np.dtype(dataset.dtypes[index - 1]).kind == "c" for index in self.bands):
            raise ValueError(f"{self.name} holds complex values; the map must hold real ones")
        self.scales = [dataset.scales[index - 1] for index in self.bands]
        self.offsets = [dataset.offsets[index - 1] for index in self.bands]
        georeferenced = not dataset.transform.is_identity or dataset.crs is not None
        if not georeferenced and dataset.gcps[0]:
            raise ValueError(
                f"{self.name} is georeferenced by ground control points only: warp it onto a grid first (gdalwarp)"
            )
        self.transform = GeoTransform.from_affine(dataset.transform) if georeferenced else None
        self.crs = None if dataset.crs is None else dataset.crs.to_string()
        itemsize = max(np.dtype(dataset.dtypes[index - 1]).itemsize for index in self.bands)
        self.bytes_per_cell = len(self.bands) * (itemsize + 8 + 1) + 8 + 1  # bands read, as float64, masks; the sum

    def read(self, top: int, left: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Float64 values and bool validity of rows ``top:top + height``, columns ``left:left + width`` (in the map)."""
        from rasterio.windows import Window

        window = Window(left, top, width, height)
        indexes = list(self.bands)
        planes = self.dataset.read(indexes, window=window)
        valid = (self.dataset.read_masks(indexes, window=window) != 0).all(0)
        values = np.zeros(planes.shape[1:], dtype=np.float64)
        for plane, weight, scale, offset in zip(planes, self.weights, self.scales, self.offsets, strict=True):
            values += weight * (plane.astype(np.float64) * scale + offset)
        valid &= np.isfinite(values)
        return values, valid

    def close(self) -> None:
        """Close the file."""
        self.dataset.close()
