r"""Below one cell on real photographs: register against the quadratic peak fit and SimpleITK, the truth exact.

Each trial takes a photograph under ``--photos`` (folders of PNG, JPEG or TIFF files, or glob patterns; read with PIL,
luma ``0.299 R + 0.587 G + 0.114 B``) and makes, at a random place in it:

* the map: the 3 x 3 block means of an 80 x 80-cell window (240 x 240 source pixels), as an area-averaging sensor
  would see it;
* the captured image: the 3 x 3 block means of a 64 x 64-cell window of the same photograph moved by whole source
  pixels ``(sx, sy)``, each uniform in -17..17, so the truth is the exact shift ``(sx / 3, sy / 3)`` cells from the
  map's centre (no interpolation in the truth; a third of the trials per axis on a whole cell), yaw 0;
* noise of a camera-like (far rows 100 times the variance of near rows) or lidar-like (corners 100 times the centre)
  profile, the yardstick's (:func:`data_tools.experiments.yardstick.yardstick.variance_profile`), its mean standard
  deviation each of ``--levels`` grey levels, the noisy values clipped to 0..255.999.

The photographs, places, shifts and normal draws are the same at every level and for every method (common random
numbers). ``localize`` (ECR, the true variance, +-8 cells around the map's centre, yaw 0) gives the start; then:

* ``parabola``: localize's own pose, the quadratic fitted to the 3 x 3 surface around its peak;
* ``register ECR true`` / ``uniform``: ``register(pose=<the parabola's pose>)`` with ``ECR()`` and the true variance,
  or one uniform variance (the true one's mean per image); ``register ECR linear`` likewise with
  ``ECR(response="linear")``; ``register NCC``;
* ``localize(refine=True)``: the search's own refinement (``register`` with ``margin=1``);
* ``SimpleITK Mattes``: SimpleITK's Mattes mutual information (32 bins, every pixel), linear interpolation,
  regular-step gradient descent with physical-shift scales, two levels (shrink 2 and 1, smoothing 1 and 0), a rigid
  transform from the parabola's pose; one image at a time, one thread;
* ``--diagnose`` adds what decides the error (the cause): ``register`` with the previous release's model
  (``interpolation="bilinear"``, ``blur=(1.0, 0.0)``), bilinear with the half-cell blur, the B-spline without it,
  a stricter stopping rule (``tolerance=1e-6``) and a start on the search's integer peak.

Reported per cell (sensor, level): how many trials the search put within one cell of the truth on both axes
("found", where a refinement can work), and over those the RMS position error in cells and, for each method, the
paired difference of its squared errors less the parabola's with the standard error (negative: closer); then the
claims' paired differences (register ECR true against the parabola, the uniform variance and SimpleITK). ``--time``
times ``register`` of one batch of ``--trials`` captured images against SimpleITK per image, interleaved rounds,
medians, one thread each. ``--figure PATH`` draws the RMS error against the noise level per method.

    # the results page's tables (~6 min each on 2 busy cores): held-out photographs, then those the blur was chosen on
    python -m data_tools.experiments.registration.subcell --photos '/work/data/src/dataset/Optical-Optical/*_1.jpg' \
        --time --figure docs/images/registration_subcell.png
    python -m data_tools.experiments.registration.subcell --photos /work/data/src/samples_LEVIR/A \
        /work/data/src/samples_DSIFN/A --diagnose
    python -m data_tools.experiments.registration.subcell --photos PHOTOS --trials 8 --levels 30 --sensors camera-like
"""

from __future__ import annotations

import argparse
import glob
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from data_tools.experiments.registration.simpleitk_mattes import mattes_registration
from enmi_torch import ECR, NCC, localize, register
from enmi_torch.utils.checks import value_checks

BLOCK = 3  # source pixels per cell
LOCAL = 64  # captured cells
MAP = 80  # map cells
MOVE = 17  # the largest move in source pixels (5.67 cells: inside the search's +-8 with the peak's 3 x 3 around it)
SHIFTS = 8
LEVELS = (10.0, 30.0, 90.0)
SENSORS = ("camera-like", "lidar-like")
SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
CLIP = (0.0, 255.999)
METHODS = (
    "parabola",
    "register ECR true",
    "register ECR uniform",
    "register ECR linear true",
    "register ECR linear uniform",
    "register NCC",
    "localize(refine=True)",
    "SimpleITK Mattes",
)
DIAGNOSES = {  # register ECR true with one thing changed
    "register bilinear, blur (1, 0) (previous model)": {"interpolation": "bilinear", "blur": (1.0, 0.0)},
    "register bilinear, blur 0.5": {"interpolation": "bilinear"},
    "register B-spline, no blur": {"blur": (0.0,)},
    "register tolerance 1e-6": {"tolerance": 1e-6},
    "register from the integer peak": {"start": "integer"},
}


def photo_paths(sources: list[str]) -> list[Path]:
    """The photographs: every image file in each folder, or the files a glob pattern names, sorted."""
    paths = []
    for source in sources:
        folder = Path(source)
        if folder.is_dir():
            paths += sorted(path for path in folder.iterdir() if path.suffix.lower() in SUFFIXES)
        else:
            paths += sorted(Path(path) for path in glob.glob(source) if Path(path).suffix.lower() in SUFFIXES)
    return paths


def luma(path: Path) -> torch.Tensor:
    """``(H, W)`` float64 luma of an image file, ``0.299 R + 0.587 G + 0.114 B`` of its RGB (grey: itself)."""
    from PIL import Image

    with Image.open(path) as image:
        rgb = np.asarray(image.convert("RGB"), dtype=np.float64)
    return torch.from_numpy(rgb @ np.array([0.299, 0.587, 0.114]))


def block_means(image: torch.Tensor) -> torch.Tensor:
    """The ``BLOCK x BLOCK`` means of ``(H, W)`` (H and W multiples of ``BLOCK``)."""
    return F.avg_pool2d(image[None, None], BLOCK)[0, 0]


def make_trials(paths: list[Path], count: int, seed: int):
    """Maps ``(count, 1, MAP, MAP)``, clean captured ``(count, 1, LOCAL, LOCAL)``, truth ``(count, 3)``, draws."""
    generator = torch.Generator().manual_seed(seed)
    photographs: dict[Path, torch.Tensor] = {}
    span, margin = BLOCK * MAP, BLOCK * (MAP - LOCAL) // 2
    maps, clean, truth = [], [], []
    for index in range(count):
        path = paths[index % len(paths)]
        if path not in photographs:
            photographs[path] = luma(path)
        photo = photographs[path]
        top = int(torch.randint(0, photo.shape[0] - span + 1, (1,), generator=generator))
        left = int(torch.randint(0, photo.shape[1] - span + 1, (1,), generator=generator))
        move_y, move_x = torch.randint(-MOVE, MOVE + 1, (2,), generator=generator).tolist()
        maps.append(block_means(photo[top : top + span, left : left + span]))
        row, col = top + margin + move_y, left + margin + move_x
        clean.append(block_means(photo[row : row + BLOCK * LOCAL, col : col + BLOCK * LOCAL]))
        # Captured cell (i, j) covers the source pixels of map cell (i, j) moved by (move_y, move_x): its centre pixel
        # (LOCAL // 2, LOCAL // 2) lies on map position (MAP // 2 + move_x / 3, MAP // 2 + move_y / 3).
        truth.append([MAP // 2 + move_x / BLOCK, MAP // 2 + move_y / BLOCK, 0.0])
    draws = torch.randn(count, 1, LOCAL, LOCAL, generator=generator, dtype=torch.float64)
    return torch.stack(maps)[:, None], torch.stack(clean)[:, None], torch.tensor(truth, dtype=torch.float64), draws


def noisy(clean: torch.Tensor, draws: torch.Tensor, sensor: str, level: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Captured images with ``sensor``'s noise of mean standard deviation ``level``, clipped; and their variance."""
    from data_tools.experiments.yardstick.yardstick import variance_profile

    unit, _ = variance_profile(sensor)
    variance = (level**2 * unit)[None, None].expand_as(clean).clone()
    return (clean + draws * variance.sqrt()).clamp(*CLIP), variance


def run_simpleitk(maps: torch.Tensor, captured: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """SimpleITK's Mattes MI rigid registration of each captured image in its map from ``start``, one at a time."""
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    return mattes_registration(maps[:, 0], captured, start)


def register_with(maps, captured, variance, start, method: str, options: dict | None = None) -> torch.Tensor:
    """``register`` (or ``localize(refine=True)``) as ``method`` names it, float32 as a user would call it."""
    options = dict(options or {})
    if options.pop("start", None) == "integer":
        start = torch.cat([start[:, :2].round(), start[:, 2:]], 1)
    if method == "localize(refine=True)":
        return localize(captured, maps, variance, shifts=SHIFTS, around=(MAP // 2, MAP // 2), refine=True).pose
    score = NCC() if method == "register NCC" else ECR(response="linear" if "linear" in method else "shrunk")
    if isinstance(score, NCC):
        variance = None
    elif method.endswith("uniform"):
        variance = variance.mean((1, 2, 3), keepdim=True).expand_as(variance)
    return register(captured, maps, variance, pose=start, score=score, **options).pose


def paired(first: torch.Tensor, second: torch.Tensor) -> tuple[float, float]:
    """Mean and standard error of ``first - second`` over paired trials."""
    difference = (first - second).double()
    return float(difference.mean()), float(difference.std() / math.sqrt(max(len(difference), 1)))


def run_cell(maps, clean, truth, draws, sensor: str, level: float, methods: list[str]) -> dict:
    """Squared position errors ``(T,)`` per method and the trials the search found, for one sensor and level."""
    captured, variance = noisy(clean, draws, sensor, level)
    captured, variance, maps32 = captured.float(), variance.float(), maps.float()
    with value_checks(False):
        found = localize(captured, maps32, variance, shifts=SHIFTS, around=(MAP // 2, MAP // 2))
        start = found.pose
        poses = {"parabola": start}
        for method in methods:
            if method in ("parabola", "SimpleITK Mattes"):
                continue
            options = DIAGNOSES.get(method)
            name = "register ECR true" if options is not None else method
            poses[method] = register_with(maps32, captured, variance, start, name, options)
        if "SimpleITK Mattes" in methods:
            poses["SimpleITK Mattes"] = run_simpleitk(maps, captured, start.double())
    errors = {method: (pose.double()[:, :2] - truth[:, :2]).square().sum(1) for method, pose in poses.items()}
    inside = (start.double()[:, :2] - truth[:, :2]).abs().amax(1) <= 1
    return {"errors": errors, "found": inside}


def time_register(maps, clean, draws, start_of, rounds: int) -> dict:
    """Seconds per round (lists) of register of the whole batch and of SimpleITK per image, interleaved."""
    captured, variance = noisy(clean, draws, "camera-like", LEVELS[1])
    captured, variance, maps32 = captured.float(), variance.float(), maps.float()
    start = start_of(maps32, captured, variance)
    fixed = ECR(model_variance=100.0, response_variance=100.0)
    subset = min(len(maps), 16)
    calls = {
        "register, the batch": lambda: register(captured, maps32, variance, pose=start),
        "register, the batch, tau^2 and delta^2 given": lambda: register(
            captured, maps32, variance, pose=start, score=fixed
        ),
        "SimpleITK Mattes, per image": lambda: run_simpleitk(maps[:subset], captured[:subset], start[:subset].double()),
    }
    times = {name: [] for name in calls}
    with value_checks(False):
        for call in calls.values():  # warm-up
            call()
        for number in range(rounds):
            for name, call in calls.items():
                began = time.perf_counter()
                call()
                seconds = time.perf_counter() - began
                times[name].append(seconds / subset if name.startswith("SimpleITK") else seconds)
            print(f"  timing round {number + 1}/{rounds}", end="\r", file=sys.stderr, flush=True)
    print(" " * 40, end="\r", file=sys.stderr)
    return times


def report(cells: dict, methods: list[str]) -> list[str]:
    """The markdown tables: RMS and paired differences against the parabola, then the claims."""
    lines = [
        "| sensor | level | found | " + " | ".join(methods) + " |",
        "| --- | --- | --- | " + " | ".join("---" for _ in methods) + " |",
    ]
    claims = ["", "| sensor | level | ECR true - parabola | ECR true - ECR uniform | ECR true - SimpleITK |"]
    claims.append("| --- | --- | --- | --- | --- |")
    for (sensor, level), cell in cells.items():
        inside, errors = cell["found"], cell["errors"]
        row = [sensor, f"{level:g}", str(int(inside.sum()))]
        for method in methods:
            squared = errors[method][inside]
            rms = math.sqrt(float(squared.mean()))
            if method == "parabola":
                row.append(f"{rms:.3f}")
            else:
                mean, error = paired(squared, errors["parabola"][inside])
                row.append(f"{rms:.3f} ({mean:+.4f} ± {error:.4f})")
        lines.append("| " + " | ".join(row) + " |")
        if "register ECR true" in errors:
            best = errors["register ECR true"][inside]
            against = []
            for other in ("parabola", "register ECR uniform", "SimpleITK Mattes"):
                if other in errors:
                    mean, error = paired(best, errors[other][inside])
                    against.append(f"{mean:+.4f} ± {error:.4f}")
                else:
                    against.append("-")
            claims.append(f"| {sensor} | {level:g} | " + " | ".join(against) + " |")
    return lines + claims


def draw(cells: dict, methods: list[str], path: str) -> None:
    """RMS position error (found trials) against the noise level, one panel per sensor, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sensors = sorted({sensor for sensor, _ in cells}, key=SENSORS.index)
    figure, axes = plt.subplots(1, len(sensors), figsize=(5.2 * len(sensors), 4.0), squeeze=False, sharey=True)
    styles = {"parabola": {"color": "black", "linestyle": "--"}, "SimpleITK Mattes": {"color": "grey"}}
    styles["register ECR true"] = {"color": "tab:red", "linewidth": 2.5}
    for axis, sensor in zip(axes[0], sensors, strict=True):
        levels = sorted(level for name, level in cells if name == sensor)
        for number, method in enumerate(methods):
            rms = []
            for level in levels:
                cell = cells[(sensor, level)]
                rms.append(math.sqrt(float(cell["errors"][method][cell["found"]].mean())))
            style = styles.get(method, {"linewidth": 1.0, "marker": "osv^<>pDh"[number % 9], "markersize": 4})
            axis.plot(levels, rms, **{"marker": "o", **style}, label=method)
        axis.set(xscale="log", yscale="log", xlabel="noise, mean standard deviation (grey levels)", title=sensor)
        axis.set_xticks(levels, [f"{level:g}" for level in levels])
    axes[0, 0].set_ylabel("RMS position error (cells)")
    axes[0, -1].legend(fontsize=7, loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="examples:\n" + __doc__.rsplit("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--photos", nargs="+", required=True, help="folders of photographs, or glob patterns")
    parser.add_argument("--trials", type=int, default=64, help="trials per cell, one batch (default 64)")
    parser.add_argument("--levels", type=float, nargs="+", default=list(LEVELS), help="noise levels, grey levels")
    parser.add_argument("--sensors", nargs="+", choices=SENSORS, default=list(SENSORS))
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--diagnose", action="store_true", help="add register with one thing changed at a time")
    parser.add_argument("--time", action="store_true", help="time register of the batch against SimpleITK")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds (default 5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--figure", help="PNG of the RMS error against the noise level per method")
    args = parser.parse_args(argv)
    paths = photo_paths(args.photos)
    if not paths:
        parser.error(f"--photos names no PNG, JPEG or TIFF file: {args.photos}")
    if args.trials < 2 or args.rounds < 1 or any(not math.isfinite(level) or level < 0 for level in args.levels):
        parser.error("--trials must be >= 2, --rounds >= 1 and --levels finite numbers >= 0")
    if "SimpleITK Mattes" in args.methods or args.time:
        try:
            import SimpleITK  # noqa: F401
        except ImportError:
            parser.error("SimpleITK is needed (pip install -e '.[bench]'), or leave out its method and --time")
    small = [path.name for path in paths if min(luma(path).shape) < BLOCK * MAP]
    if small:
        parser.error(f"photographs smaller than {BLOCK * MAP} x {BLOCK * MAP} pixels: {small}")
    torch.set_num_threads(1)
    methods = list(args.methods) + (list(DIAGNOSES) if args.diagnose else [])
    maps, clean, truth, draws = make_trials(paths, args.trials, args.seed)
    print(
        f"{len(paths)} photograph(s), {args.trials} trials per cell, truth a whole number of thirds of a cell; torch "
        "threads 1; errors in cells",
        flush=True,
    )
    cells, began = {}, time.perf_counter()
    for sensor in args.sensors:
        for level in args.levels:
            cells[(sensor, level)] = run_cell(maps, clean, truth, draws, sensor, level, methods)
            print(f"  {sensor} {level:g}: {time.perf_counter() - began:.0f} s", file=sys.stderr, flush=True)
    print("\n".join(["", *report(cells, methods)]))
    if args.time:

        def start_of(maps32, captured, variance):
            with value_checks(False):
                return localize(captured, maps32, variance, shifts=SHIFTS, around=(MAP // 2, MAP // 2)).pose

        times = time_register(maps, clean, draws, start_of, args.rounds)
        print(
            f"\ncamera-like {LEVELS[1]:g}, {args.trials} images of {LOCAL} x {LOCAL}, one thread, median of "
            f"{args.rounds} interleaved rounds:"
        )
        for name, seconds in times.items():
            print(f"  {name}: {1000 * statistics.median(seconds):.1f} ms")
        batch = statistics.median(times["register, the batch"])
        per_image = statistics.median(times["SimpleITK Mattes, per image"])
        print(
            f"  register per image in the batch: {1000 * batch / args.trials:.2f} ms, "
            f"{per_image * args.trials / batch:.1f}x SimpleITK's throughput; the batch is {batch / per_image:.1f}x "
            "SimpleITK's time per image"
        )
    if args.figure:
        draw(cells, [method for method in methods if method in cells[next(iter(cells))]["errors"]], args.figure)
        print(f"wrote {args.figure}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
