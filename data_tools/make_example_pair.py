r"""Make the example pair bundled with the library (``enmi_torch.data.example_pair``) from the raw Landsat files.

    python -m data_tools.make_example_pair --source /work/data/landsat --out enmi_torch/data/nanjing

The source is the Nanjing pair of `ChangeDetectionRepository <https://github.com/ChenHongruixuan/ChangeDetectionRepository>`_
(``Dataset/Landsat/Nanjing``): two Landsat 5 TM subsets of 800 x 800 cells of 30 m, ENVI BSQ files of 6 uint8 bands
(TM bands 1, 2, 3, 4, 5, 7) without their headers (``LT51200382000124BJC00_Nanjing``, 3 May 2000;
``LT51200382002193BJC00_Nanjing``, 12 July 2002), and ``change.bmp`` (255 where the land changed). Both headers state
``map info = {UTM, 1, 1, 660585, 3551295, 30, 30, 50, North, WGS-84}``: pixel (1, 1)'s top-left corner at
660585 E, 3551295 N of UTM zone 50N (EPSG:32650).

Each date's grey image is the luma ``0.299 R + 0.587 G + 0.114 B`` of bands 3, 2, 1, stretched by one linear map for
both dates: the 2000 image's 0.5 and 99.5 percentiles (over the whole 800 x 800 subset) to 0 and 255, clipped, rounded
to uint8; the 2002 image through the same map, so that a grey level means the same luma on both dates. The crop
(``--size`` cells from ``--offset``, the top-left 512 x 512 by default: the Yangtze, the city and the airport) is
written as three 8-bit grey PNGs and ``nanjing.json``, which records the source, the licence and citation, the crop's
exact transform and CRS, how the grey levels were made and each file's SHA-256. Landsat data are public domain (USGS);
the repository is MIT-licensed; cite Wu, Du & Zhang 2014 for the change map. Needs Pillow (the ``train`` extra).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from enmi_torch.data.example import FILES, SIDECAR
from enmi_torch.maps import GeoTransform
from enmi_torch.utils.command import ArgumentParser, run_command

PROG = "python -m data_tools.make_example_pair"
SCENES = {"earlier": "LT51200382000124BJC00", "later": "LT51200382002193BJC00"}
DATES = {"earlier": "2000-05-03", "later": "2002-07-12"}
SHAPE, BANDS = (800, 800), (1, 2, 3, 4, 5, 7)  # the subsets' lines, samples and TM bands, as their headers state
CORNER, CELL = (660585.0, 3551295.0), 30.0  # ENVI map info: pixel (1, 1)'s top-left corner, metres
CRS = "EPSG:32650"
LUMA = {3: 0.299, 2: 0.587, 1: 0.114}  # TM band 3 red, 2 green, 1 blue (ITU-R BT.601)
PERCENTILES = (0.5, 99.5)
SOURCE = "https://github.com/ChenHongruixuan/ChangeDetectionRepository (Dataset/Landsat/Nanjing)"
CITATION = (
    "C. Wu, B. Du, L. Zhang, Slow feature analysis for change detection in multispectral imagery, "
    "IEEE Transactions on Geoscience and Remote Sensing 52(5):2858-2874, 2014, doi:10.1109/TGRS.2013.2266673"
)
LICENCE = (
    "Landsat 5 TM data: U.S. Geological Survey, public domain (courtesy of the USGS); the subsets and the change map "
    "from ChangeDetectionRepository (MIT licence, Copyright (c) Hongruixuan Chen); cite Wu, Du & Zhang 2014"
)


def read_bands(path: Path) -> np.ndarray:
    """``(6, 800, 800)`` uint8: the bands of one raw ENVI BSQ subset (no header offset, byte order irrelevant)."""
    expected = len(BANDS) * SHAPE[0] * SHAPE[1]
    if not path.is_file():
        raise FileNotFoundError(f"--source: no file {str(path)!r}")
    size = path.stat().st_size
    if size != expected:
        raise ValueError(f"{path} holds {size} bytes, expected {expected} (6 uint8 bands of 800 x 800, BSQ)")
    return np.fromfile(path, dtype=np.uint8).reshape(len(BANDS), *SHAPE)


def luma(bands: np.ndarray) -> np.ndarray:
    """``(800, 800)`` float64 luma of TM bands 3, 2 and 1."""
    return sum(weight * bands[BANDS.index(band)].astype(np.float64) for band, weight in LUMA.items())


def grey_images(earlier: np.ndarray, later: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Both dates' luma through the earlier one's percentile stretch, uint8; and the stretch's ``(low, high)``."""
    low, high = (float(value) for value in np.percentile(earlier, PERCENTILES))
    stretched = [np.clip((image - low) / (high - low) * 255, 0, 255) for image in (earlier, later)]
    return np.rint(stretched[0]).astype(np.uint8), np.rint(stretched[1]).astype(np.uint8), (low, high)


def read_change(path: Path) -> np.ndarray:
    """``(800, 800)`` uint8, 255 where the land changed, of ``change.bmp``."""
    from PIL import Image

    if not path.is_file():
        raise FileNotFoundError(f"--source: no file {str(path)!r}")
    with Image.open(path) as opened:
        change = np.asarray(opened.convert("L"))
    if change.shape != SHAPE:
        raise ValueError(f"{path} has shape {change.shape}, expected {SHAPE}")
    return np.where(change > 0, 255, 0).astype(np.uint8)


def _parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", default="/work/data/landsat", help="the folder of the raw files and change.bmp")
    parser.add_argument("--out", default="runs/example_pair", help="the folder to write (enmi_torch/data/nanjing)")
    parser.add_argument("--size", type=int, default=512, help="side of the square crop, in cells")
    parser.add_argument("--offset", type=int, nargs=2, default=[0, 0], metavar=("X", "Y"), help="its top-left cell")
    return parser


def make_example_pair(argv: list[str]) -> dict:
    """The command: write the crop's PNGs and sidecar; returns the sidecar."""
    args = _parser().parse_args(argv)
    x0, y0 = args.offset
    if args.size < 1 or x0 < 0 or y0 < 0 or x0 + args.size > SHAPE[1] or y0 + args.size > SHAPE[0]:
        raise ValueError(f"--size {args.size} from --offset {x0} {y0} must fit in the 800 x 800 subsets")
    source = Path(args.source)
    bands = {role: read_bands(source / f"{scene}_Nanjing") for role, scene in SCENES.items()}
    change = read_change(source / "change.bmp")
    earlier, later, (low, high) = grey_images(luma(bands["earlier"]), luma(bands["later"]))
    crop = np.s_[y0 : y0 + args.size, x0 : x0 + args.size]
    images = {"earlier": earlier[crop], "later": later[crop], "change": change[crop]}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    digests = {}
    for role, image in images.items():
        path = out / FILES[role]
        Image.fromarray(image).save(path, optimize=True)
        digests[role] = hashlib.sha256(path.read_bytes()).hexdigest()
    transform = GeoTransform(CELL, 0.0, CORNER[0], 0.0, -CELL, CORNER[1]).translated(x0, y0)
    sidecar = {
        "name": "Landsat 5 TM over Nanjing, China: 3 May 2000 and 12 July 2002",
        "files": dict(FILES),
        "sha256": digests,
        "shape": [args.size, args.size],
        "dates": DATES,
        "scenes": SCENES,
        "crs": CRS,
        "crs_name": "WGS 84 / UTM zone 50N",
        "transform": list(transform.affine),
        "transform_meaning": "rasterio's Affine(a, b, c, d, e, f): the corner of cell (column, row) lies at "
        "(a column + b row + c, d column + e row + f) metres; cell (0, 0)'s top-left corner at (c, f)",
        "crop": f"{args.size} x {args.size} cells from column {x0}, row {y0} of the 800 x 800 subsets, whose ENVI map "
        "info puts pixel (1, 1)'s top-left corner at 660585 E, 3551295 N with 30 m cells",
        "grey": "luma 0.299 B3 + 0.587 B2 + 0.114 B1 of each date (TM red, green, blue), stretched by one linear map "
        "for both dates: the 2000 image's 0.5 and 99.5 percentiles over the whole 800 x 800 subset to 0 and 255, "
        "clipped, rounded to uint8",
        "stretch": {"low": round(low, 6), "high": round(high, 6)},
        "change": "change.bmp of the source: 255 where the land changed between the dates, else 0",
        "co_registration": "measured within 0.1 cell on 15 of 16 tiles of 200 x 200 "
        "(data_tools/experiments/yardstick/prepare_scene_change.py)",
        "source": SOURCE,
        "licence": LICENCE,
        "citation": CITATION,
        "made_by": f"{PROG} --size {args.size} --offset {x0} {y0}",
    }
    (out / SIDECAR).write_text(json.dumps(sidecar, indent=2) + "\n")
    kilobytes = sum((out / name).stat().st_size for name in FILES.values()) / 1024
    print(
        f"wrote {out}: {args.size} x {args.size} cells of both dates, the change map ({kilobytes:.0f} KiB), {SIDECAR}"
    )
    return sidecar


def main(argv: list[str] | None = None) -> None:
    """Console form: one-line errors, exit code 2."""
    run_command(PROG, make_example_pair, argv)


if __name__ == "__main__":
    main(sys.argv[1:])
