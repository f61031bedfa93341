"""``enmi-localize`` (``python -m enmi_torch.cli.localize``): localize a local image file in a map file."""

from __future__ import annotations

import argparse
import ast
import json
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from enmi_torch.localization.peak import Localization
from enmi_torch.localization.search import RESAMPLING, localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.scores import Score, as_score, score_names
from enmi_torch.utils.command import ArgumentParser, run_command, with_flag_names
from enmi_torch.utils.options import OptionConflict

if TYPE_CHECKING:
    from enmi_torch.maps import MapWindow


def _read_array(path: str, name: str):
    """The image of ``--name``: a ``.npy`` array or a grey PNG (16 bits kept), read like the pair folders."""
    from enmi_torch.utils.files import read_image

    if not Path(path).is_file() and Path(path).suffix.lower() in (".npy", ".png"):
        raise FileNotFoundError(f"--{name}: no such file {path!r}")
    return read_image(path, f"--{name}")


def _parse_yaws(text: str) -> list[float]:
    """``"start:stop:step"`` (both ends included) or a comma-separated list of degrees."""
    try:
        values = [float(value) for value in text.replace(":", ",").split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"yaws must be start:stop:step or a,b,c in degrees, got {text!r}") from None
    if ":" in text:
        if len(values) != 3:
            raise argparse.ArgumentTypeError(f"yaws start:stop:step needs three numbers, got {text!r}")
        start, stop, step = values
        if not all(math.isfinite(value) for value in values):
            raise argparse.ArgumentTypeError(f"yaws start:stop:step needs three finite numbers, got {text!r}")
        if step <= 0 or stop < start:
            raise argparse.ArgumentTypeError(f"yaws start:stop:step needs step > 0 and stop >= start, got {text!r}")
        count = math.floor((stop - start) / step + 1e-9) + 1
        if count > _MAX_YAWS:
            raise argparse.ArgumentTypeError(
                f"yaws start:stop:step gives {count:.3g} yaws, more than the {_MAX_YAWS} searched at most, got {text!r}"
            )
        return [start + k * step for k in range(count)]
    return values


_MAX_YAWS = 36_000  # a full turn in steps of 0.01 degree


_PROG = "enmi-localize"
_EPILOG = f"""example (files from, in a clone, python -m data_tools.experiments.yardstick.localization_benchmark \\
         --example runs/example):
  {_PROG} --map runs/example/map.npy --local runs/example/local.npy --variance runs/example/variance.npy \\
      --local-mask runs/example/local_mask.npy --around 220 300 --shifts 16 --yaws -6:6:1

output: one JSON line, for example
  {{"x": 211.01, "y": 304.98, "yaw_deg": 2.8, "dx": -8.99, "dy": 4.98, "row": 304.98, "col": 211.01,
   "score": 1.1127, "margin": 0.5266}}
  x, y      the pose: the map column and row (down) under the local image's centre pixel, in cells (sub-cell),
            with yaw_deg the (x, y, yaw) that register and Tracker.start take
  yaw_deg   rotation of the local image against the map, degrees counter-clockwise as displayed
  dx, dy    shift of the local image's centre from --around, in map cells along columns and rows
  row, col  the same cell as y, x (kept for scripts that read them)
  score     the best score: ECR and mixture in nats per pixel (0: no evidence), ENMI and NMI in [1, 2], NCC in [-1, 1]
  margin    best score minus the best score farther than --exclusion-radius cells from it: near 0, another
            place of the map fits about as well (a repetitive map); null when the window has no such place
--output also draws the score surface at the best yaw and the best score per yaw.

a GeoTIFF map (pip install "enmi_torch[geo]"; a map and a crop to try: python -m data_tools.make_geotiff_map):
  {_PROG} --map city.tif --local local.npy --variance 100 --prior-world 500090 5399890 --shifts 16
reads only the window the search needs around the prior (world coordinates in the map's CRS; or --center ROW COL)
and adds to the output, for a georeferenced map:
  world_x, world_y  where the local image's centre pixel lies, in the map's CRS
  world_yaw_deg     heading of the local image's top, degrees clockwise from north (+Y): yaw_deg on a north-up map
  crs               the map's coordinate reference system (EPSG:32633, else its WKT)
row and col stay cells of the whole map; the local image must be on the map's cell grid (same cell size)."""


def _parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog=_PROG,
        description="Find the pose (shift and yaw) of a local image in a prior map with ECR, ENMI, mixture, NMI or\n"
        "NCC score surfaces, and print it as JSON (also runs as python -m enmi_torch.cli.localize).",
        epilog=_EPILOG,
    )
    parser.add_argument(
        "--map",
        required=True,
        help="prior map: .npy (2-D), .png (read as grey levels), or a GeoTIFF/COG (read by windows, the geo extra)",
    )
    parser.add_argument("--local", required=True, help="local image on the map's cell grid, .npy or .png")
    parser.add_argument(
        "--variance", help="local noise variance: a number or a .npy map (needed by --score ecr, enmi, mixture)"
    )
    parser.add_argument("--local-mask", help="valid local pixels, .npy or .png (nonzero = valid)")
    parser.add_argument("--map-mask", help="valid map cells, .npy or .png (nonzero = valid)")
    parser.add_argument(
        "--score", default="ecr", choices=score_names(), help="score of a candidate pose (ecr: the noise-aware default)"
    )
    # The flag's former name, kept working.
    parser.add_argument("--metric", dest="score", choices=score_names(), help=argparse.SUPPRESS)
    parser.add_argument("--shifts", type=int, nargs="+", default=[16], help="search radius r, or ry rx, in cells")
    parser.add_argument(
        "--around",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        help="prior map column and row of the local centre, rounded to a cell (default: the map's centre)",
    )
    # The former spelling, (row, col), kept working for one release (a note on stderr).
    parser.add_argument("--center", type=int, nargs=2, metavar=("ROW", "COL"), help=argparse.SUPPRESS)
    parser.add_argument(
        "--prior-world",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        help="prior position of the local centre in world coordinates of a GeoTIFF map's CRS (instead of --around)",
    )
    parser.add_argument(
        "--band",
        type=int,
        help="band of a multi-band GeoTIFF map, from 1 (default: the one band or the luma of red, green, blue)",
    )
    parser.add_argument(
        "--yaws", type=_parse_yaws, default="0", help="degrees: start:stop:step (ends included) or a,b,c"
    )
    parser.add_argument("--bins", type=int, default=32, help="histogram bins (ECR: of the map; ENMI, mixture, NMI)")
    parser.add_argument(
        "--value-range", type=float, nargs=2, default=[0.0, 256.0], metavar=("LOW", "HIGH"), help="range of the bins"
    )
    parser.add_argument(
        "--score-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other option of the score, repeatable (e.g. model_variance=4.0, kernel=density, em_steps=2; the "
        "value read as a Python literal, else as text)",
    )
    parser.add_argument(
        "--min-overlap", type=float, default=0.5, help="share of valid local pixels a candidate must cover"
    )
    parser.add_argument("--exclusion-radius", type=int, default=3, help="cells around the peak left out of the margin")
    parser.add_argument(
        "--coarse-factor", type=int, default=1, help="> 1: search coarse-to-fine on f x f averaged cells"
    )
    parser.add_argument("--resample", choices=RESAMPLING, default="nearest", help="how the local image is rotated")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="precision of the scores")
    parser.add_argument("--output", help="PNG of the score surface at the best yaw, peak marked")
    return parser


# Library argument names as this command's options, for error messages.
_OPTION_NAMES = {
    "valid_mask": "--local-mask",
    "captured_mask": "--local-mask",
    "reference_mask": "--map-mask",
    "reference": "--map",
    "captured": "--local",
    "min_overlap": "--min-overlap",
    "exclusion_radius": "--exclusion-radius",
    "coarse_factor": "--coarse-factor",
    "value_range": "--value-range",
}


def _score(args: argparse.Namespace) -> Score:
    """The score of ``--score`` with ``--bins``, ``--value-range`` (where it has them) and every ``--score-option``.

    Built by the score's constructor, which decides which options it takes and which combinations mean something;
    its refusal comes back with the options spelt as this command takes them (:func:`_spell_score_option`).
    """
    family = type(as_score(args.score))
    names = family.option_names()
    flags = {"bins": args.bins, "value_range": tuple(args.value_range)}
    options = {name: value for name, value in flags.items() if name in names}
    for text in args.score_option:
        key, equals, value = text.partition("=")
        if not equals or key not in names:
            raise ValueError(
                f"--score-option takes KEY=VALUE with KEY one of {family.__name__}'s options {list(names)}, "
                f"got {text!r}"
            )
        try:
            options[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            options[key] = value
    try:
        return family(**options)
    except OptionConflict as conflict:
        raise ValueError(conflict.spelled(_spell_score_option)) from None
    except (ValueError, TypeError) as error:
        flags = {name: _SCORE_FLAGS.get(name, f"--score-option {name}") for name in names}
        message = with_flag_names(str(error), flags)
        if message == str(error):
            raise
        raise type(error)(message) from None


_SCORE_FLAGS = {"bins": "--bins", "value_range": "--value-range"}  # the score options with flags of their own


def _spell_score_option(name: str, value: object) -> str:
    """A score option as this command takes it: ``--bins 8``, ``--value-range 0.0 1.0``, ``--score-option k=v``."""
    if name == "value_range":
        return f"--value-range {value[0]} {value[1]}"
    return f"--bins {value}" if name == "bins" else f"--score-option {name}={value}"


def _check_finite_file(name: str, values: Tensor, valid: Tensor | None) -> None:
    bad = ~torch.isfinite(values) if valid is None else ~torch.isfinite(values) & valid
    if bool(bad.any()):
        raise ValueError(
            f"--{name} holds {int(bad.sum())} NaN/inf value(s) at valid pixels; leave them out with --{name}-mask "
            "FILE (nonzero = valid)"
        )


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point (``enmi-localize``, ``python -m enmi_torch.cli.localize``): one-line errors, exit code 2."""
    run_command(_PROG, _command, argv)


def _command(argv: Sequence[str]) -> dict:
    """The command with these arguments; returns the printed result as a dict."""
    args = _parser().parse_args(argv)
    score = _score(args)  # its options refused before any file is read
    if args.output is not None:
        _check_output(args.output)
    dtype = getattr(torch, args.dtype)
    local = torch.as_tensor(_read_array(args.local, "local"), dtype=dtype)
    if local.ndim != 2:
        raise ValueError(f"--local must hold a 2-D image, got shape {tuple(local.shape)}")
    if len(args.shifts) not in (1, 2):
        raise ValueError(f"--shifts takes r or ry rx, got {args.shifts}")
    around = None if args.around is None else tuple(args.around)
    if args.center is not None:
        if around is not None:
            raise ValueError("--center ROW COL is the former spelling of --around X Y: pass --around alone")
        row, col = args.center
        around = (col, row)
        print(f"{_PROG}: --center ROW COL is deprecated: pass --around {col} {row} (X Y)", file=sys.stderr)
    searched = _searched_map(args, tuple(local.shape), dtype, around)
    prior_map = searched.image
    variance = None
    if args.variance is not None:
        try:
            variance = float(args.variance)
        except ValueError:
            variance = torch.as_tensor(_read_array(args.variance, "variance"), dtype=dtype)
    masks = {} if searched.valid_mask is None else {"reference_mask": searched.valid_mask}
    for name, path, option in (
        ("captured_mask", args.local_mask, "local-mask"),
        ("reference_mask", args.map_mask, "map-mask"),
    ):
        if path is not None:
            masks[name] = torch.as_tensor(_read_array(path, option) != 0)
    for name, image, mask_name in (("local", local, "captured_mask"), ("map", prior_map, "reference_mask")):
        mask = masks.get(mask_name)
        _check_finite_file(name, image, mask if mask is not None and mask.shape == image.shape else None)
    try:
        result = localize(
            local[None, None],
            prior_map[None, None],
            variance,
            shifts=args.shifts[0] if len(args.shifts) == 1 else tuple(args.shifts),
            around=searched.around,
            yaws=args.yaws,
            score=score,
            min_overlap=args.min_overlap,
            exclusion_radius=args.exclusion_radius,
            search=SearchStrategy(coarse_factor=args.coarse_factor),
            resample=args.resample,
            **masks,
        )
    except (ValueError, TypeError) as error:
        message = str(error)
        if message.startswith("--score-option"):  # it lists the option names as --score-option takes them
            raise
        # value_range=(0.0, 1.0) as the flag takes it: --value-range 0.0 1.0
        message = re.sub(r"\bvalue_range=\(([^,()]+), ([^()]+)\)", r"--value-range \1 \2", message)
        for name, option in _OPTION_NAMES.items():
            message = re.sub(rf"\b{name}\b", option, message)
        raise ValueError(message) from error
    x, y, yaw = result.pose[0].double().tolist()  # in the searched map's cells
    dx, dy = result.shift[0].double().tolist()
    x, y = x + searched.offset[0], y + searched.offset[1]  # in the whole map's
    # The scores are not log-likelihoods, so the fitted covariance is not printed as an uncertainty.
    report = {
        "x": round(x, 2),
        "y": round(y, 2),
        "yaw_deg": round(yaw, 2),
        "dx": round(dx, 2),
        "dy": round(dy, 2),
        "row": round(y, 2),
        "col": round(x, 2),
        "score": round(float(result.score[0]), 4),
        "margin": round(float(result.margin[0]), 4) if bool(torch.isfinite(result.margin[0])) else None,
    }
    if searched.window is not None:
        report.update(_world_report(searched.window, tuple(result.pose[0].double().tolist())))
    print(json.dumps(report))
    if args.output is not None:
        _draw_surface(result, args.output, args.score)
        print(f"wrote {args.output}", file=sys.stderr)
    return report


class _SearchedMap(NamedTuple):
    """The map the search runs on, in its own cells: a whole ``.npy``/PNG map, or a GeoTIFF's window."""

    image: Tensor  # (H, W)
    valid_mask: Tensor | None  # (H, W) bool: a GeoTIFF's nodata, mask or alpha, and cells off the map
    around: tuple[float, float] | None  # (x, y) of the prior cell in ``image`` (None: the map's centre)
    offset: tuple[int, int]  # (x0, y0): the whole map's cell under image cell (0, 0)
    window: MapWindow | None  # a GeoTIFF's window, with its transform and CRS


def _searched_map(
    args: argparse.Namespace, local_shape: tuple[int, int], dtype: torch.dtype, around: tuple[float, float] | None
) -> _SearchedMap:
    """The whole ``--map`` (``.npy``, PNG), or the window of a GeoTIFF that the search needs, read alone.

    The window is centred on the prior cell (``--prior-world`` converted to cells, ``around``, or the map's centre)
    and holds every shift of ``--shifts`` with the local image and one cell more, its corner on a multiple of
    ``--coarse-factor`` (so the coarse search pools the cells it would pool in the whole map).
    """
    suffix = Path(args.map).suffix.lower()
    if suffix in (".npy", ".png"):
        for flag, value in (("--prior-world", args.prior_world), ("--band", args.band)):
            if value is not None:
                raise ValueError(f"{flag} is for GeoTIFF maps; --map {args.map!r} is a {suffix} image in cells")
        image = torch.as_tensor(_read_array(args.map, "map"), dtype=dtype)
        return _SearchedMap(image, None, around, (0, 0), None)
    if args.map_mask is not None:
        raise ValueError("--map-mask is for .npy and .png maps; a GeoTIFF marks its own invalid cells (nodata, masks)")
    if around is not None and args.prior_world is not None:
        raise ValueError("give the prior as --around X Y (map cells) or as --prior-world X Y (world), not both")
    from enmi_torch.maps import MapSource

    try:
        source = MapSource.open(args.map, band=args.band, source="--map")
    except ImportError as error:  # rasterio missing: the message names the extra
        raise ValueError(str(error)) from None
    with source:
        if args.prior_world is None:
            rows, cols = source.shape
            prior = (cols // 2, rows // 2) if around is None else tuple(math.floor(value + 0.5) for value in around)
        elif not all(math.isfinite(value) for value in args.prior_world):
            raise ValueError(f"--prior-world must be two finite numbers X Y, got {args.prior_world}")
        elif source.transform is None:
            raise ValueError(f"--prior-world needs a georeferenced map; --map {args.map!r} has no geotransform")
        else:
            prior = tuple(math.floor(value + 0.5) for value in source.to_cells(args.prior_world).tolist())
        shift_y, shift_x = (args.shifts[0], args.shifts[0]) if len(args.shifts) == 1 else args.shifts
        factor = max(args.coarse_factor, 1)
        radius = []
        for axis, shift, size in ((0, shift_x, local_shape[1]), (1, shift_y, local_shape[0])):  # x, then y
            reach = max(shift, 0) + size // 2 + 1
            radius.append(reach + (prior[axis] - reach) % factor)
        window = source.window(prior, tuple(radius), units="cells", dtype=dtype)
    return _SearchedMap(window.image[0, 0], window.valid_mask[0, 0], tuple(window.center), window.offset, window)


def _world_report(window: MapWindow, pose: tuple[float, float, float]) -> dict:
    """``world_x``, ``world_y``, ``world_yaw_deg`` and ``crs`` of a pose ``(x, y, yaw)`` in the window's cells.

    World coordinates are given to a hundredth of a cell; nothing for a map without georeferencing.
    """
    if window.transform is None:
        return {}
    world_x, world_y, world_yaw = window.to_world(pose).tolist()
    digits = max(0, math.ceil(-math.log10(min(window.transform.cell_size) / 100)))
    return {
        "world_x": round(world_x, digits),
        "world_y": round(world_y, digits),
        "world_yaw_deg": round(world_yaw, 2),
        "crs": window.crs,
    }


def _check_output(path: str) -> None:
    """Refuse an ``--output`` that could not be written as named, before the search runs."""
    output = Path(path)
    if output.is_dir():
        raise ValueError(f"--output must name a PNG file to write, got the existing folder {path!r}")
    if not output.parent.is_dir():
        raise ValueError(f"--output {path!r} lies in a folder that does not exist ({str(output.parent)!r})")


def _draw_surface(result: Localization, path: str, score_name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    surface = result.surface[0]
    yaw_index = int(surface.flatten(1).amax(1).argmax())
    plane = surface[yaw_index].double()
    radius_y, radius_x = (plane.shape[0] - 1) // 2, (plane.shape[1] - 1) // 2
    shown = plane.masked_fill(~torch.isfinite(plane), float("nan")).numpy()
    several = surface.shape[0] > 1
    figure, axes = plt.subplots(1, 2 if several else 1, figsize=(9.5 if several else 5.2, 4.2), squeeze=False)
    image = axes[0, 0].imshow(
        shown, extent=(-radius_x - 0.5, radius_x + 0.5, radius_y + 0.5, -radius_y - 0.5), cmap="viridis"
    )
    dx, dy = result.shift[0].tolist()
    yaw = float(result.yaw[0])
    axes[0, 0].plot(dx, dy, marker="+", color="red", markersize=14, markeredgewidth=2)
    axes[0, 0].set(
        xlabel="dx (cells)",
        ylabel="dy (cells)",
        title=f"{score_name.upper()} at yaw {float(result.yaws[yaw_index]):g}°",
    )
    figure.colorbar(image, ax=axes[0, 0], shrink=0.85)
    if several:
        profile = surface.flatten(1).amax(1).double()
        axes[0, 1].plot(
            result.yaws.double().numpy(), profile.masked_fill(~torch.isfinite(profile), float("nan")).numpy(), "o-"
        )
        axes[0, 1].axvline(yaw, color="red")
        axes[0, 1].set(xlabel="yaw (degrees)", ylabel="best score over shifts", title=f"peak at yaw {yaw:.2f}°")
    figure.tight_layout()
    figure.savefig(path, dpi=90, format="png")  # at the path as named (no ".png" appended)
    plt.close(figure)


if __name__ == "__main__":
    main()
