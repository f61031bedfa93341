"""The example pair bundled with the library: one place seen by Landsat 5 on two dates, with its change map.

Two grey images of the same 512 x 512 cells of 30 m over Nanjing, China (the Yangtze, the city and its airport):
Landsat 5 TM on 3 May 2000 (scene ``LT51200382000124BJC00``) and on 12 July 2002 (``LT51200382002193BJC00``),
co-registered to within about 0.1 cell, with the map of where the land changed between them; georeferenced in
UTM zone 50N (EPSG:32650). A map of one date and an image captured on the other is the library's problem at its
simplest: the same ground, another season, another sensor state. ``enmi-example`` (:mod:`enmi_torch.cli.example`)
turns it into files to try the commands on: a GeoTIFF map, a captured image and training pairs.

Each grey image is the luma ``0.299 R + 0.587 G + 0.114 B`` of TM bands 3, 2, 1, stretched by one linear map for both
dates (the 2000 image's 0.5 and 99.5 percentiles to 0 and 255, clipped, rounded), so a grey level is the same luma on
both dates. Landsat data are public domain (U.S. Geological Survey); the subsets and the change map come from
`ChangeDetectionRepository <https://github.com/ChenHongruixuan/ChangeDetectionRepository>`_ (MIT): cite C. Wu,
B. Du, L. Zhang, *Slow feature analysis for change detection in multispectral imagery*, IEEE TGRS 52(5), 2014.
The files are package data (``enmi_torch/data/nanjing/``: three 8-bit PNGs and ``nanjing.json``, which records all
this and the crop's transform); ``data_tools/make_example_pair.py`` makes them from the raw files. Reading them
needs Pillow (the ``train`` extra).
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from enmi_torch.maps.transform import GeoTransform
from enmi_torch.utils.files import read_image

FOLDER = "nanjing"  # the package data's folder, beside this module
SIDECAR = "nanjing.json"
FILES = {"earlier": "nanjing_2000.png", "later": "nanjing_2002.png", "change": "nanjing_change.png"}


class ExamplePair(NamedTuple):
    """The bundled pair (see the module): two dates of the same cells, where they differ, and where they lie.

    Attributes:
        earlier: ``(1, 1, H, W)`` grey levels in ``[0, 255]`` of 3 May 2000 (whole numbers; the map of the examples).
        later: ``(1, 1, H, W)`` the same cells on 12 July 2002, through the same grey-level map.
        change: ``(1, 1, H, W)`` bool: the land changed between the dates here (the source's change map).
        transform: :class:`~enmi_torch.maps.GeoTransform` of the cells (north up, 30 m), in ``crs``.
        crs: ``"EPSG:32650"`` (WGS 84 / UTM zone 50N).
        info: the sidecar ``nanjing.json``: ``dates``, ``scenes``, ``source``, ``licence``, ``citation``, ``grey``
            (how the grey levels were made) and the rest.
    """

    earlier: Tensor
    later: Tensor
    change: Tensor
    transform: GeoTransform
    crs: str
    info: dict


def example_pair(dtype: torch.dtype = torch.float32) -> ExamplePair:
    """The bundled Landsat pair over Nanjing (2000 and 2002), as tensors with their transform and CRS.

    Args:
        dtype: floating dtype of ``earlier`` and ``later``.

    Returns:
        :class:`ExamplePair`; new tensors on every call.

    Raises:
        ValueError: when the package data are missing or damaged (reinstall enmi_torch), or Pillow is missing.

    Example:
        >>> pair = example_pair()
        >>> tuple(pair.earlier.shape), pair.crs, pair.info["dates"]
        ((1, 1, 512, 512), 'EPSG:32650', {'earlier': '2000-05-03', 'later': '2002-07-12'})
        >>> pair.transform.to_world((0.0, 0.0)).tolist()  # the top-left cell's centre: easting, northing (metres)
        [660600.0, 3551280.0]
        >>> round(pair.change.float().mean().item(), 4)  # share of the cells that changed
        0.004
    """
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    folder = data_folder()
    info = _read_sidecar(folder / SIDECAR)
    shape = tuple(info["shape"])
    images = {}
    for role, name in FILES.items():
        image = read_image(folder / name, "the example pair")
        if image.shape != shape or image.dtype != np.uint8:
            raise ValueError(
                f"the example pair's {folder / name} holds {image.dtype} {image.shape}, expected uint8 {shape} "
                "as nanjing.json says: reinstall enmi_torch"
            )
        images[role] = torch.from_numpy(image)[None, None]
    return ExamplePair(
        earlier=images["earlier"].to(dtype),
        later=images["later"].to(dtype),
        change=images["change"] > 0,
        transform=GeoTransform(*(float(value) for value in info["transform"])),
        crs=str(info["crs"]),
        info=info,
    )


def data_folder() -> Path:
    """The folder of the bundled files (in the package: a clone's ``enmi_torch/data/nanjing`` or the install's)."""
    return Path(str(resources.files("enmi_torch.data"))) / FOLDER


def _read_sidecar(path: Path) -> dict:
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"the example pair's {path} cannot be read ({error}): reinstall enmi_torch") from None
    missing = [key for key in ("shape", "transform", "crs", "dates") if key not in info]
    if missing:
        raise ValueError(f"the example pair's {path} lacks {missing}: reinstall enmi_torch")
    return info
