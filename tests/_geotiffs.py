"""GeoTIFFs written with rasterio itself (not the library's writer), with transforms that tell conventions apart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")  # the geo extra; the tests' own rasterio names come from here
from rasterio.io import DatasetReader  # noqa: E402
from rasterio.transform import Affine, rowcol, xy  # noqa: E402
from rasterio.windows import Window  # noqa: E402
from rasterio.windows import transform as window_transform  # noqa: E402

__all__ = ["Affine", "DatasetReader", "Window", "rasterio", "rowcol", "window_transform", "xy"]

CRS = "EPSG:32633"
EAST, NORTH = 500000.0, 5400000.0
CELL = 0.5
# The three kinds of geotransform: rows run south (north up), rows run north (flipped), the grid turned 30 degrees.
TRANSFORMS = {
    "north_up": Affine.translation(EAST, NORTH) @ Affine.scale(CELL, -CELL),
    "flipped": Affine.translation(EAST, NORTH - 100.0) @ Affine.scale(CELL, CELL),
    "rotated": Affine.translation(EAST, NORTH) @ Affine.rotation(30.0) @ Affine.scale(CELL, -CELL),
}
# World yaw of a cell yaw on each map, in closed form (see enmi_torch.maps.transform).
WORLD_YAW = {"north_up": lambda yaw: yaw, "flipped": lambda yaw: 180.0 - yaw, "rotated": lambda yaw: yaw - 30.0}


def texture(rows: int = 200, cols: int = 260) -> np.ndarray:
    """A non-square ``(rows, cols)`` float64 section of scikit-image's gravel photograph, with a painted stripe."""
    from skimage import data

    section = data.gravel()[:rows, :cols].astype(np.float64)
    section[:, 40:44] = 235.0
    return section


def write_raster(path: Path, planes: np.ndarray, transform: Affine, **options) -> Path:
    """``planes`` ``(H, W)`` or ``(C, H, W)`` as a tiled, deflate-compressed GeoTIFF (rasterio's own writer).

    ``options`` go to ``rasterio.open`` (``nodata=``, ``photometric=``, ``crs=``...); ``driver="COG"`` writes a
    Cloud-Optimized GeoTIFF with overviews through GDAL's COG driver.
    """
    planes = planes[None] if planes.ndim == 2 else planes
    cog = options.pop("driver", "GTiff") == "COG"
    profile = {
        "driver": "GTiff",
        "width": planes.shape[2],
        "height": planes.shape[1],
        "count": planes.shape[0],
        "dtype": planes.dtype.name,
        "crs": options.pop("crs", CRS),
        "transform": transform,
        "tiled": True,
        "blockxsize": 64,
        "blockysize": 64,
        "compress": "deflate",
        **options,
    }
    target = path.with_suffix(".plain.tif") if cog else path
    with rasterio.open(target, "w", **profile) as dataset:
        dataset.write(planes)
    if cog:
        from rasterio.shutil import copy

        copy(target, path, driver="COG", blocksize=128, overview_resampling="average")
    return path
