"""``enmi-example`` (``python -m enmi_torch.cli.example``): the bundled Landsat pair as files to try the commands on.

From :func:`~enmi_torch.data.example_pair` (Nanjing, 3 May 2000 and 12 July 2002, 512 x 512 cells of 30 m in UTM
zone 50N) it writes into a new folder: the 2000 image as a GeoTIFF map in its real CRS and transform; a captured
image cut from the 2002 image around a point given in world coordinates, at a heading, with camera-like sensor noise
(its variance map beside it); training pairs for ``enmi-fit-mask`` (2002 with the same noise against 2000); and
``example.json`` with the truth. It prints where the captured image's centre lies, in world coordinates and in map
cells: the answer ``enmi-localize`` should find.

The sensor: a road camera sees far ground (its top rows) at few pixels per tile, so the variance of a rectified pixel
grows with the cube of its depth (:class:`~enmi_torch.variance.PerspectiveVariance`); here the depth grows linearly
from the bottom row to the top one, whose variance is 100 times the bottom's (its noise 10 times stronger), and the
mean standard deviation is ``--noise``. The noisy values are clipped to ``[0, 255.999]``, as a sensor saturates.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from enmi_torch.utils.command import ArgumentParser, run_command

PROG = "enmi-example"
CENTER_WORLD = (670690.0, 3546940.0)  # near the lake north of the city centre: map cell (336.33, 144.67)
HEADING = 3.0
SIZE = (64, 64)
NOISE = 20.0
PAIRS = 400
FAR_TO_NEAR = 100.0  # the top row's variance over the bottom row's
CEILING = 255.999  # the sensor's largest reading: the bins' value range is [0, 256)
MIN_SIDE, MAX_SIDE = 8, 512
DESCRIPTION = f"""\
Write the bundled example pair (Landsat 5 over Nanjing, 3 May 2000 and 12 July 2002, 512 x 512 cells of 30 m in UTM
zone 50N; USGS, public domain) as files to try the commands on, into a new folder OUT:
  map_2000.tif           the 2000 image, a GeoTIFF in EPSG:32650 (map_2000.npy without the geo extra)
  captured_2002.npy      an image cut from the 2002 image around --center-world at --heading, with camera-like noise
                         (10 times stronger on its top row than on its bottom one), clipped to 0..255.999
  captured_variance.npy  its noise variance per pixel
  pairs/                 --pairs training pairs for enmi-fit-mask: local/ (2002 with the same noise), prior/ (2000),
                         meta.json naming the true variance
  example.json           the truth and where every file came from
and print where the captured image's centre lies: the answer enmi-localize should find.

example:
  {PROG} runs/nanjing                       # also: python -m enmi_torch.cli.example runs/nanjing
  enmi-localize --map runs/nanjing/map_2000.tif --local runs/nanjing/captured_2002.npy \\
      --variance runs/nanjing/captured_variance.npy --prior-world 670730 3546910 --shifts 8 --yaws -6:6:2"""


def camera_like_variance(shape: tuple[int, int], noise_std: float) -> Tensor:
    """``(H, W)`` float64 variance of a rectified road camera's pixels: far (top) rows noisier than near ones.

    The variance of row ``r`` grows as the cube of a depth running linearly from 1 on the bottom row to
    ``FAR_TO_NEAR ** (1 / 3)`` on the top one, scaled so that the mean standard deviation over the pixels is
    ``noise_std``.

    Example:
        >>> variance = camera_like_variance((4, 3), 10.0)
        >>> round(variance.sqrt().mean().item(), 6), round((variance[0, 0] / variance[-1, 0]).item(), 6)
        (10.0, 100.0)
    """
    height, width = shape
    rows = torch.arange(height, dtype=torch.float64)
    depth = 1 + (FAR_TO_NEAR ** (1 / 3) - 1) * (height - 1 - rows) / max(height - 1, 1)
    profile = (depth**3)[:, None].expand(height, width)
    return (noise_std / profile.sqrt().mean()) ** 2 * profile


def capture(image: Tensor, pose: Tensor, variance: Tensor, generator: torch.Generator) -> Tensor:
    """``(H, W)`` float32: ``image`` ``(1, 1, Hm, Wm)`` under the pose ``(1, 3)``, plus noise, clipped like a sensor.

    The map is sampled by its cubic B-spline (:func:`~enmi_torch.registration.warp_reference`); the noise is Gaussian
    with ``variance`` ``(H, W)``; the readings are clipped to ``[0, CEILING]``.
    """
    from enmi_torch.registration import warp_reference

    clean, valid = warp_reference(image.to(torch.float64), pose.to(torch.float64), tuple(variance.shape))
    if not bool(valid.all()):
        raise ValueError(f"the pose {pose.tolist()} puts part of the captured image off the map")
    noise = variance.sqrt() * torch.randn(variance.shape, generator=generator, dtype=torch.float64)
    return (clean[0, 0] + noise).clamp(0, CEILING).to(torch.float32)


def training_pairs(
    earlier: Tensor, later: Tensor, count: int, variance: Tensor, generator: torch.Generator
) -> Iterator[dict]:
    """``count`` co-registered pairs at random places: ``later`` with the noise of ``variance``, ``earlier`` as it is.

    Items are dicts of ``local``, ``prior`` ``(H, W)`` float32 and ``valid`` ``(H, W)`` bool (all ``True``), as
    :func:`~enmi_torch.data.write_pairs` takes them; ``earlier``, ``later`` are ``(Hm, Wm)`` maps.
    """
    height, width = variance.shape
    for _ in range(count):
        top = int(torch.randint(earlier.shape[0] - height + 1, (), generator=generator))
        left = int(torch.randint(earlier.shape[1] - width + 1, (), generator=generator))
        window = np.s_[top : top + height, left : left + width]
        noise = variance.sqrt() * torch.randn(variance.shape, generator=generator, dtype=torch.float64)
        local = (later[window].to(torch.float64) + noise).clamp(0, CEILING)
        yield {
            "local": local.to(torch.float32),
            "prior": earlier[window].to(torch.float32),
            "valid": torch.ones(height, width, dtype=torch.bool),
        }


def _parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description=DESCRIPTION)
    parser.add_argument("out", metavar="OUT", help="a new (or empty) folder to write")
    parser.add_argument(
        "--center-world",
        type=float,
        nargs=2,
        default=list(CENTER_WORLD),
        metavar=("X", "Y"),
        help="easting and northing (EPSG:32650, metres) of the captured image's centre pixel",
    )
    parser.add_argument(
        "--heading", type=float, default=HEADING, help="degrees clockwise from north of the captured image's top"
    )
    parser.add_argument(
        "--size", type=int, nargs=2, default=list(SIZE), metavar=("H", "W"), help="the captured image's rows, columns"
    )
    parser.add_argument("--noise", type=float, default=NOISE, help="mean standard deviation of the noise, grey levels")
    parser.add_argument("--pairs", type=int, default=PAIRS, help="training pairs (0: none)")
    parser.add_argument("--pair-size", type=int, default=SIZE[0], help="side of the square training pairs")
    parser.add_argument("--seed", type=int, default=0, help="the noise and the pairs' places")
    return parser


def _check(args, shape: tuple[int, int]) -> Path:
    """The options' mistakes, before any work; returns OUT as a path."""
    from enmi_torch.utils.files import check_folder_to_write

    out = check_folder_to_write(args.out, "OUT")
    if out.is_dir() and any(out.iterdir()):
        raise ValueError(f"OUT must be a new or empty folder, got {args.out!r}, which holds files: name another one")
    if not all(math.isfinite(value) for value in args.center_world):
        raise ValueError(f"--center-world must be two finite numbers (metres), got {_numbers(args.center_world)}")
    if not math.isfinite(args.heading):
        raise ValueError(f"--heading must be a finite number of degrees, got {args.heading}")
    for name, sides in (("--size", args.size), ("--pair-size", [args.pair_size])):
        if not all(MIN_SIDE <= side <= min(shape) for side in sides):
            raise ValueError(f"{name} must be from {MIN_SIDE} to {min(shape)} cells, got {' '.join(map(str, sides))}")
    if not (math.isfinite(args.noise) and 0 < args.noise <= 1000):
        raise ValueError(f"--noise must be a standard deviation in (0, 1000] grey levels, got {args.noise}")
    if args.pairs < 0:
        raise ValueError(f"--pairs must be 0 or more, got {args.pairs}")
    if args.seed < 0:
        raise ValueError(f"--seed must be 0 or more, got {args.seed}")
    return out


def _check_on_map(pair, pose: Tensor, size: tuple[int, int], center: list[float]) -> None:
    """Refuse a captured image that would reach off the map, before anything is written."""
    from enmi_torch.registration import warp_reference

    _, valid = warp_reference(pair.later, pose, size)
    if not bool(valid.all()):
        rows, cols = pair.later.shape[-2:]
        corners = pair.transform.to_world([[-0.5, -0.5], [cols - 0.5, rows - 0.5]])
        raise ValueError(
            f"--center-world {_numbers(center)} (map cell x {pose[0, 0]:.1f}, y {pose[0, 1]:.1f}) puts part "
            f"of the {size[0]} x {size[1]} captured image off the {rows} x {cols} map, which spans easting "
            f"{corners[0, 0]:.0f} to {corners[1, 0]:.0f} and northing {corners[1, 1]:.0f} to {corners[0, 1]:.0f}"
        )


def make_example(argv: Sequence[str]) -> dict:
    """The command with these arguments; returns what ``example.json`` holds."""
    from enmi_torch.data import example_pair

    args = _parser().parse_args(argv)
    pair = example_pair(torch.float64)
    shape = tuple(pair.earlier.shape[-2:])
    out = _check(args, shape)
    size = tuple(args.size)
    pose = pair.transform.to_cells([*args.center_world, args.heading])[None]
    _check_on_map(pair, pose, size, args.center_world)
    geotiff = _has_rasterio()
    generator = torch.Generator().manual_seed(args.seed)
    variance = camera_like_variance(size, args.noise)
    captured = capture(pair.later, pose, variance, generator)
    pair_variance = camera_like_variance((args.pair_size, args.pair_size), args.noise)
    out.mkdir(parents=True, exist_ok=True)
    files = {"captured": "captured_2002.npy", "variance": "captured_variance.npy"}
    earlier = pair.earlier[0, 0].to(torch.uint8)
    if geotiff:
        from enmi_torch.maps import write_geotiff

        files["map"] = "map_2000.tif"
        write_geotiff(out / files["map"], earlier, pair.transform, crs=pair.crs)
    else:
        files["map"] = "map_2000.npy"
        np.save(out / files["map"], earlier.numpy(), allow_pickle=False)
    np.save(out / files["captured"], captured.numpy(), allow_pickle=False)
    np.save(out / files["variance"], variance.to(torch.float32).numpy(), allow_pickle=False)
    if args.pairs:
        from enmi_torch.data import VarianceTruth, write_pairs

        files["pairs"] = "pairs"
        truth = VarianceTruth(pair_variance, torch.ones_like(pair_variance, dtype=torch.bool), "camera-like")
        source = f"{PROG}: {pair.info['name']}; local: 2002 with camera-like noise {args.noise:g}, prior: 2000"
        pairs = training_pairs(pair.earlier[0, 0], pair.later[0, 0], args.pairs, pair_variance, generator)
        write_pairs(out / files["pairs"], pairs, truth=truth, source=source)
    world = [round(value, 9) for value in pair.transform.to_world(pose[0]).tolist()]  # no 3.0000000000000004
    cells = [round(value, 9) for value in pose[0].tolist()]
    record = _record(args, pair, files, world, cells)
    (out / "example.json").write_text(json.dumps(record, indent=2) + "\n")
    _report(args, pair, out, files, world, cells, geotiff)
    return record


def _numbers(values: Sequence[float]) -> str:
    """``670690 3546940``: numbers as typed, without an exponent."""
    return " ".join(f"{value:.10g}" for value in values)


def _has_rasterio() -> bool:
    try:
        import rasterio  # noqa: F401
    except ImportError:
        return False
    return True


def _record(args, pair, files: dict, world: list[float], cells: list[float]) -> dict:
    return {
        "truth": {
            "world_x": world[0],
            "world_y": world[1],
            "world_yaw_deg": world[2],
            "x": cells[0],
            "y": cells[1],
            "yaw_deg": cells[2],
            "meaning": "where the captured image's centre pixel (h // 2, w // 2) lies on the map, and its heading",
        },
        "files": files,
        "crs": pair.crs,
        "transform": list(pair.transform.affine),
        "captured": {"size": list(args.size), "noise": args.noise, "far_to_near_variance": FAR_TO_NEAR},
        "pairs": {"count": args.pairs, "size": args.pair_size},
        "seed": args.seed,
        "dates": pair.info["dates"],
        "source": pair.info["source"],
        "licence": pair.info["licence"],
        "citation": pair.info["citation"],
    }


def _report(args, pair, out: Path, files: dict, world, cells, geotiff: bool) -> None:
    cell_size = pair.transform.cell_size[0]
    rows, cols = pair.earlier.shape[-2:]
    corner = f"{pair.transform.c:.0f} E, {pair.transform.f:.0f} N"
    print(f"{pair.info['name']} (USGS, public domain); {rows} x {cols} cells of {cell_size:g} m, {pair.crs}")
    if geotiff:
        print(f"wrote {out / files['map']}: the 2000 image, the map (top-left corner {corner})")
    else:
        from enmi_torch.maps.geotiff import GEO_EXTRA

        sys.stderr.write(
            f"{PROG}: note: a GeoTIFF needs rasterio ({GEO_EXTRA}): wrote {out / files['map']} instead, in cells "
            f"only (enmi-localize --around X Y)\n"
        )
        print(f"wrote {out / files['map']}: the 2000 image, the map (cells only; top-left corner {corner})")
    height, width = args.size
    print(
        f"wrote {out / files['captured']}: {height} x {width} of the 2002 image, heading {args.heading:g} degrees, "
        f"noise sigma {args.noise:g} on average (10 times stronger on the top row than on the bottom one); "
        f"its variance: {files['variance']}"
    )
    if args.pairs:
        print(
            f"wrote {out / files['pairs']}: {args.pairs} pairs of {args.pair_size} x {args.pair_size} (2002 with the "
            f"same noise, 2000) for enmi-fit-mask --data.root {out / files['pairs']}"
        )
    print(
        f"the captured image's centre lies on world ({world[0]:.2f}, {world[1]:.2f}), heading {world[2]:.2f} degrees: "
        f"map cell (x, y) = ({cells[0]:.2f}, {cells[1]:.2f}), yaw {cells[2]:.2f}"
    )


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point (``enmi-example``, ``python -m enmi_torch.cli.example``): one-line errors, exit code 2."""
    run_command(PROG, make_example, argv)


if __name__ == "__main__":
    main()
