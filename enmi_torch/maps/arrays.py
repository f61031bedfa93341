"""Maps held in memory: an array, a ``.npy`` file or an image (PNG, JPEG), read whole and cut into windows.

A ``.npy`` file is read with its header checked against the memory budget (:func:`~enmi_torch.utils.files.read_npy`);
a grey image keeps its 8 or 16 bits; a colour image is read by :mod:`~enmi_torch.maps.bands` (its luma, or one band),
its alpha marking cells invalid where 0. NaN and infinite values are invalid cells.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from enmi_torch.maps.bands import choose_bands
from enmi_torch.maps.transform import GeoTransform
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.files import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# Pillow's modes of one grey channel, read as they are (8, 16 or 32 bits).
_GREY_MODES = ("L", "I;16", "I;16B", "I", "1", "F")
_COLOUR_NAMES = {"R": "red", "G": "green", "B": "blue", "A": "alpha", "L": "gray", "I": "gray", "F": "gray"}


class ArrayRaster:
    """A ``(H, W)`` map in memory with its valid cells, its transform (or none) and its CRS (or none)."""

    def __init__(
        self, values: np.ndarray, valid: np.ndarray, transform: GeoTransform | None, crs: str | None, name: str
    ) -> None:
        self.values, self.valid = values, valid & np.isfinite(values)
        self.transform, self.crs, self.name = transform, crs, name
        self.shape = tuple(values.shape)
        self.bytes_per_cell = 8 + 1  # a float64 window and its mask

    def read(self, top: int, left: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Float64 values and bool validity of rows ``top:top + height``, columns ``left:left + width`` (in the map)."""
        rows, cols = slice(top, top + height), slice(left, left + width)
        return self.values[rows, cols].astype(np.float64), self.valid[rows, cols].copy()

    def close(self) -> None:
        """Nothing to release."""


def array_raster(image: Any, transform: Any, crs: Any, valid_mask: Any) -> ArrayRaster:
    """An :class:`ArrayRaster` of a ``(H, W)`` array or tensor (``(1, 1, H, W)`` too), checked."""
    values = _as_numpy("image", image)
    if values.ndim == 4 and values.shape[:2] == (1, 1):
        values = values[0, 0]
    if values.ndim != 2 or 0 in values.shape:
        raise ValueError(f"image must be a (H, W) or (1, 1, H, W) map, got shape {values.shape}")
    if not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
        raise TypeError(f"image must hold real numbers, got dtype {values.dtype}")
    valid = np.ones(values.shape, dtype=bool)
    if valid_mask is not None:
        mask = _as_numpy("valid_mask", valid_mask)
        mask = mask[0, 0] if mask.ndim == 4 and mask.shape[:2] == (1, 1) else mask
        if mask.dtype != np.bool_ or mask.shape != values.shape:
            raise ValueError(f"valid_mask must be a bool map of shape {values.shape}, got {mask.dtype} {mask.shape}")
        valid = mask.copy()
    if crs is not None and not isinstance(crs, str):
        raise TypeError(f"crs must be a string (e.g. 'EPSG:32633') or None, got {type(crs).__name__}")
    geo = None if transform is None else _as_transform(transform)
    return ArrayRaster(values, valid, geo, crs, "image")


def read_array_file(path: Path, band: Any, source: str) -> ArrayRaster:
    """The map of a ``.npy`` file or an image file, read whole; not georeferenced (world coordinates are refused)."""
    named = f"{source} {str(path)!r}"
    if not path.is_file():
        raise FileNotFoundError(f"{named}: no such file")
    if path.suffix.lower() == ".npy":
        if band is not None:
            raise ValueError(f"band is for multi-band images and GeoTIFFs; {named} is a (H, W) .npy array")
        values = read_image(path, source)
        if not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
            raise ValueError(f"{named} must hold real numbers, got dtype {values.dtype}")
        return ArrayRaster(values, np.ones(values.shape, dtype=bool), None, None, named)
    values, valid = _read_picture(path, band, named, source)
    return ArrayRaster(values, valid, None, None, named)


def _read_picture(path: Path, band: Any, named: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Values and validity of a PNG or JPEG: grey as it is, colour by :func:`choose_bands`, alpha as validity."""
    try:
        from PIL import Image
    except ImportError as error:
        raise ValueError(f"{named}: reading images needs Pillow (pip install 'enmi_torch[train]')") from error
    try:
        with Image.open(path) as opened:
            mode, (width, height) = opened.mode, opened.size
            check_cells_memory(named, width * height, 8 * 5, "its planes", "crop or downsample the image")
            if mode in _GREY_MODES:
                converted = opened
            else:
                converted = opened.convert("RGBA" if mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV") else mode)
            planes = np.asarray(converted, dtype=np.float64)
            colours = [_COLOUR_NAMES.get(letter, "undefined") for letter in converted.getbands()]
    except (ValueError, OSError) as error:
        raise ValueError(f"{named} is not a readable image: {error}") from None
    planes = planes[..., None] if planes.ndim == 2 else planes
    valid = np.ones(planes.shape[:2], dtype=bool)
    if colours[-1] == "alpha":
        valid = planes[..., -1] > 0
        if band is None:
            colours, planes = colours[:-1], planes[..., :-1]
    bands, weights = choose_bands(band, colours, named)
    values = sum(weight * planes[..., index - 1] for index, weight in zip(bands, weights, strict=True))
    return values, valid


def _as_numpy(name: str, value: Any) -> np.ndarray:
    if hasattr(value, "detach"):  # a tensor: its values on the host
        return value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value
    raise TypeError(f"{name} must be a numpy array or a torch.Tensor, got {type(value).__name__}")


def _as_transform(transform: Any) -> GeoTransform:
    return transform if isinstance(transform, GeoTransform) else GeoTransform.from_affine(transform)
