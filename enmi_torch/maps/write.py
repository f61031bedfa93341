"""Writing a map as a GeoTIFF or a Cloud-Optimized GeoTIFF (tiled, compressed, with overviews), with rasterio."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from enmi_torch.maps.geotiff import import_rasterio
from enmi_torch.maps.transform import GeoTransform

_COLOURS = {3: ("red", "green", "blue"), 4: ("red", "green", "blue", "alpha")}


def write_geotiff(
    path: str | Path,
    image: Any,
    transform: Any,
    crs: str | None = None,
    *,
    nodata: float | None = None,
    cog: bool = False,
) -> Path:
    """Write ``image`` as a tiled, deflate-compressed GeoTIFF (a COG with ``cog=True``); returns the path.

    Args:
        path: the file to write (overwritten).
        image: ``(H, W)`` (one band) or ``(C, H, W)`` (``C`` bands; 3 or 4 are marked red, green, blue and alpha),
            a numpy array or a tensor; its dtype is kept (a float64 tensor stays float64).
        transform: a :class:`~enmi_torch.maps.GeoTransform`, rasterio's ``Affine`` or six numbers
            ``(a, b, c, d, e, f)``: pixel corner ``(column, row)`` at world ``(a col + b row + c, d col + e row + f)``.
        crs: the coordinate reference system, as rasterio reads it (``"EPSG:32633"``, WKT), or ``None``.
        nodata: the value that marks cells without data (read back as invalid), or ``None``.
        cog: write a Cloud-Optimized GeoTIFF (GDAL's COG driver: 512-cell tiles and overviews) instead of a
            plain tiled one (256-cell tiles).

    Raises:
        ModuleNotFoundError: without rasterio (``pip install "enmi_torch[geo]"``).
    """
    path = Path(path)
    rasterio = import_rasterio(f"path {str(path)!r}")
    values = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if values.ndim == 2:
        values = values[None]
    if values.ndim != 3 or 0 in values.shape:
        raise ValueError(f"image must be (H, W) or (C, H, W), got shape {values.shape}")
    if values.dtype == np.bool_:
        values = values.astype(np.uint8)
    geo = transform if isinstance(transform, GeoTransform) else GeoTransform.from_affine(transform)
    profile = {
        "driver": "GTiff",
        "width": values.shape[2],
        "height": values.shape[1],
        "count": values.shape[0],
        "dtype": values.dtype.name,
        "crs": crs,
        "transform": rasterio.Affine(*geo.affine),
        "nodata": nodata,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
    }
    colours = [getattr(rasterio.enums.ColorInterp, name) for name in _COLOURS.get(values.shape[0], ())]
    if not cog:
        with rasterio.open(path, "w", **profile) as dataset:
            dataset.write(values)
            if colours:
                dataset.colorinterp = colours
        return path
    from rasterio.shutil import copy

    with rasterio.io.MemoryFile() as memory:
        with memory.open(**profile) as dataset:
            dataset.write(values)
            if colours:
                dataset.colorinterp = colours
        with memory.open() as dataset:
            copy(dataset, path, driver="COG", compress="deflate", blocksize=512)
    return path
