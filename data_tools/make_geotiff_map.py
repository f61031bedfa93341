r"""Make a GeoTIFF map from a photograph, and optionally a noisy crop of it to localize, for trying ``enmi-localize``.

    python -m data_tools.make_geotiff_map skimage:gravel runs/geo/map.tif --origin 500000 5400000 \
        --pixel-size 0.5 --crs EPSG:32633 --crop-world 500095 5399884 --crop-size 64 80 --crop runs/geo/local.npy

``PHOTO`` is an image file or ``skimage:NAME``, a photograph bundled with scikit-image (``gravel``, ``camera``,
``brick``, ``grass``, ``astronaut``, ...: no download). A colour photograph keeps its red, green and blue bands (the
map reader takes their luma). The map's top-left corner lies at ``--origin`` (easting, northing) with square cells of
``--pixel-size`` map units, north up, or turned ``--rotation`` degrees counter-clockwise. ``--crop`` writes the luma
of the cells around ``--crop-world`` with Gaussian noise as a ``.npy`` captured image and prints where its centre
pixel lies in world coordinates and cells: the answer ``enmi-localize`` should find. Needs the ``geo`` and ``train``
extras (rasterio, scikit-image).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from enmi_torch.maps import GeoTransform, MapSource, write_geotiff
from enmi_torch.utils.command import ArgumentParser, run_command

PROG = "python -m data_tools.make_geotiff_map"


def read_photo(text: str) -> np.ndarray:
    """``(H, W)`` or ``(3, H, W)`` uint8 planes of an image file or of ``skimage:NAME``."""
    if text.startswith("skimage:"):
        from skimage import data

        name = text.partition(":")[2]
        loader = getattr(data, name, None)
        if not callable(loader) or name.startswith("_"):
            raise ValueError(f"PHOTO {text!r}: scikit-image has no bundled image {name!r} (try skimage:gravel)")
        try:
            image = np.asarray(loader())
        except Exception as error:  # an image scikit-image would download: refused offline, named here
            raise ValueError(f"PHOTO {text!r} cannot be loaded: {error}") from None
    else:
        from PIL import Image

        try:
            with Image.open(text) as opened:
                image = np.asarray(opened.convert("RGB" if opened.mode not in ("L", "I;16") else opened.mode))
        except OSError as error:
            raise ValueError(f"PHOTO {text!r} is not a readable image: {error}") from None
    if image.ndim == 3:
        image = np.moveaxis(image[..., :3], -1, 0)
    if image.ndim not in (2, 3):
        raise ValueError(f"PHOTO {text!r} must be a grey or colour image, got shape {image.shape}")
    return np.ascontiguousarray(image)


def map_transform(origin: list[float], pixel_size: float, rotation: float) -> GeoTransform:
    """North-up cells of ``pixel_size`` turned ``rotation`` degrees counter-clockwise about the corner ``origin``."""
    cos, sin = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
    return GeoTransform(pixel_size * cos, pixel_size * sin, origin[0], pixel_size * sin, -pixel_size * cos, origin[1])


def _parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("photo", metavar="PHOTO", help="an image file, or skimage:NAME (skimage:gravel, ...)")
    parser.add_argument("output", metavar="OUT.tif", help="the GeoTIFF to write (its folder is made)")
    parser.add_argument("--origin", type=float, nargs=2, required=True, metavar=("E", "N"), help="top-left corner")
    parser.add_argument("--pixel-size", type=float, required=True, help="cell size in map units (metres)")
    parser.add_argument("--crs", default="EPSG:32633", help="coordinate reference system")
    parser.add_argument("--rotation", type=float, default=0.0, help="degrees the cell grid turns counter-clockwise")
    parser.add_argument("--cog", action="store_true", help="write a Cloud-Optimized GeoTIFF (tiles and overviews)")
    parser.add_argument("--crop", help="also write a noisy crop (.npy) as a captured image to localize")
    parser.add_argument("--crop-world", type=float, nargs=2, metavar=("X", "Y"), help="the crop's centre (world)")
    parser.add_argument("--crop-size", type=int, nargs=2, default=[64, 80], metavar=("H", "W"), help="crop size")
    parser.add_argument("--noise", type=float, default=10.0, help="standard deviation of the crop's Gaussian noise")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise")
    return parser


def _check(args: argparse.Namespace) -> None:
    if not (math.isfinite(args.pixel_size) and args.pixel_size > 0):
        raise ValueError(f"--pixel-size must be a finite number > 0, got {args.pixel_size}")
    if not all(math.isfinite(value) for value in [*args.origin, args.rotation]):
        raise ValueError("--origin and --rotation must be finite numbers")
    if (args.crop is None) != (args.crop_world is None):
        raise ValueError("--crop FILE and --crop-world X Y go together")
    if args.crop is not None and Path(args.crop).suffix != ".npy":
        raise ValueError(f"--crop must name a .npy file, got {args.crop!r}")
    if min(args.crop_size) < 2 or not (math.isfinite(args.noise) and args.noise >= 0):
        raise ValueError(f"--crop-size must be at least 2 x 2 and --noise finite and >= 0, got {args.crop_size}")


def make_map(argv: list[str]) -> None:
    """The command: write the map, and the crop where asked for."""
    args = _parser().parse_args(argv)
    _check(args)
    photo = read_photo(args.photo)
    transform = map_transform(args.origin, args.pixel_size, args.rotation)
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_geotiff(output, photo, transform, crs=args.crs, cog=args.cog)
    rows, cols = photo.shape[-2:]
    corner = f"({args.origin[0]}, {args.origin[1]})"
    print(f"wrote {output}: {rows} x {cols} cells of {args.pixel_size:g} m ({args.crs}), top-left corner {corner}")
    if args.crop is None:
        return
    height, width = args.crop_size
    with MapSource.open(output, source="OUT.tif") as source:
        cell = [math.floor(value + 0.5) for value in source.to_cells(args.crop_world).tolist()]
        window = source.window(cell, (width // 2, height // 2), units="cells")
        world = source.to_world(cell).tolist()
    top, left = window.center[1] - height // 2, window.center[0] - width // 2
    if not bool(window.valid_mask[0, 0, top : top + height, left : left + width].all()):
        raise ValueError(f"--crop-world {args.crop_world} puts the {height} x {width} crop partly off the map")
    generator = np.random.default_rng(args.seed)
    crop = window.image[0, 0, top : top + height, left : left + width].numpy()
    crop = crop + args.noise * generator.standard_normal(crop.shape).astype(np.float32)
    Path(args.crop).parent.mkdir(parents=True, exist_ok=True)
    np.save(args.crop, crop)
    print(
        f"wrote {args.crop}: {height} x {width}, noise sigma {args.noise:g}; its centre pixel lies on world "
        f"({world[0]:.2f}, {world[1]:.2f}), map cell (x, y) = ({cell[0]}, {cell[1]})"
    )


def main(argv: list[str] | None = None) -> None:
    """Console form: one-line errors, exit code 2."""
    run_command(PROG, make_map, argv)


if __name__ == "__main__":
    main(sys.argv[1:])
