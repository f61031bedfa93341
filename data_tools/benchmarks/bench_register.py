r"""Sub-cell registration at known continuous poses: enmi_torch.register against the quadratic peak fit and SimpleITK.

Each trial cuts a 64 x 64 captured image from a real photograph that scikit-image ships (``camera``, ``astronaut``,
``coffee``, ``rocket``, in grey) at a known continuous pose (shift within +-3 cells of an integer cell, yaw within
+-3 degrees, :func:`enmi_torch.registration.warp_reference`), optionally from the photograph changed since
(:mod:`enmi_torch.data.scene_change`, one kind at strength 0.5: the captured image is of the changed scene, the map
is not), and adds Gaussian noise of a camera-like (far rows 100 times the variance of near ones) or lidar-like
(corners 100 times the centre) variance of mean standard deviation ``sigma``. ``localize`` (ECR, the true variance,
+-5 cells, yaws -4 to 4 degrees) gives the start. Then, on the same trials:

* ``quadratic fit``: localize's own pose (a quadratic on the 3 x 3 cells around the peak, a parabola across yaws);
* ``register ECR true`` / ``register ECR uniform``: :func:`enmi_torch.register` with ECR and the true variance, or one
  uniform variance (the true map's mean); ``register NCC``; from localize's pose, ``margin=1`` (as
  ``localize(refine=True)``: the search scored the neighbouring cells);
* ``SimpleITK Mattes translation`` / ``rigid``: SimpleITK's Mattes mutual information (32 bins, every pixel sampled),
  linear interpolation, regular-step gradient descent with physical-shift scales, two levels (shrink 2 and 1,
  smoothing 1 and 0 pixels), started from localize's integer peak (translation) or its pose (rigid); one image at a
  time, as SimpleITK runs.

Reported per cell: how many trials the search put in the right cell ("found": within one cell on both axes, where
a refinement can work), the RMS position error (cells) over those and over all trials, the median error, the share
within 0.25 cell, the yaw RMS over the found trials (degrees, rigid methods), milliseconds per registration (batched
for enmi_torch, one by one for SimpleITK, one thread each; the quadratic fit's is the search's own time), and the
paired difference of squared position errors against ``register ECR true`` over the found trials with its standard
error (negative: the method is closer). kornia's ``ImageRegistrator`` is not run: it computes ``loss_fn(warped, target,
reduction="none")`` and then averages the per-pixel result over the warped image's footprint, which a histogram score
(NMI, ENMI, ECR) cannot give: its value is one number for the whole image, so the pixels warped in from outside would
count (see README).

    python -m data_tools.benchmarks.bench_register                  # every cell, 48 trials each (~5 min on 2 cores)
    python -m data_tools.benchmarks.bench_register --trials 16 --cells camera-like@60
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import torch

from data_tools.experiments.registration.simpleitk_mattes import mattes_registration
from data_tools.experiments.yardstick import yardstick
from enmi_torch import ECR, NCC, localize, register
from enmi_torch.data.scene_change import scene_change
from enmi_torch.registration import warp_reference
from enmi_torch.utils.checks import value_checks

PHOTOGRAPHS = ("camera", "astronaut", "coffee", "rocket")
LOCAL = 64
CELLS = (
    "camera-like@15",
    "camera-like@60",
    "camera-like@120",
    "lidar-like@60",
    "camera-like@60+tone",
    "camera-like@60+shadows",
    "camera-like@60+illumination",
    "camera-like@60+occluders",
)
METHODS = (
    "quadratic fit",
    "register ECR true",
    "register ECR uniform",
    "register NCC",
    "SimpleITK Mattes translation",
    "SimpleITK Mattes rigid",
)


def parse_cell(cell: str) -> tuple[str, float, str | None]:
    """``sensor@sigma[+change]`` -> ``(sensor, sigma, change)``."""
    head, _, change = cell.partition("+")
    sensor, _, sigma = head.partition("@")
    if sensor not in ("camera-like", "lidar-like") or not sigma:
        raise ValueError(f"a cell is sensor@sigma[+change] with sensor camera-like or lidar-like, got {cell!r}")
    return sensor, float(sigma), change or None


def make_trials(cell: str, count: int, seed: int, yardstick):
    """Maps ``(count, 1, H, W)``, captured ``(count, 1, 64, 64)``, variance, integer centres ``(count, 2)``, truth."""
    sensor, sigma, change = parse_cell(cell)
    generator = torch.Generator().manual_seed(seed)
    unit, _ = yardstick.variance_profile(sensor)
    maps, captured, centres, truths = [], [], [], []
    for index in range(count):
        image = yardstick.map_image(PHOTOGRAPHS[index % len(PHOTOGRAPHS)])  # grey, float64 in [0, 255]
        height, width = image.shape
        row = 60 + int(torch.randint(0, height - 120, (1,), generator=generator))
        col = 60 + int(torch.randint(0, width - 120, (1,), generator=generator))
        offset = (torch.rand(3, generator=generator, dtype=torch.float64) - 0.5) * 6
        truth = torch.tensor([[col + offset[0], row + offset[1], offset[2]]], dtype=torch.float64)
        seen = image
        if change is not None:  # the scene around the captured image changed (a 160 x 160 window: all it sees)
            seen = image.clone()
            top, left = max(row - 80, 0), max(col - 80, 0)
            window = (slice(top, top + 160), slice(left, left + 160))
            seen[window] = scene_change(image[window], seed * 1000 + index, 0.5, kinds=[change])
        clean = warp_reference(seen[None, None], truth, (LOCAL, LOCAL))[0]
        noise = torch.randn(1, 1, LOCAL, LOCAL, generator=generator, dtype=torch.float64)
        captured.append(clean + sigma * unit.sqrt() * noise)
        maps.append(image[None, None])
        centres.append((row, col))
        truths.append(truth)
    variance = (sigma**2 * unit)[None, None].expand(count, 1, LOCAL, LOCAL)
    return maps, torch.cat(captured), variance, torch.tensor(centres), torch.cat(truths)


def start_poses(maps, captured, variance, centres) -> torch.Tensor:
    """The pose localize finds (absolute ``x, y, yaw``) of every trial."""
    poses = []
    yaws = [float(yaw) for yaw in range(-4, 5)]
    for index, reference in enumerate(maps):
        found = localize(
            captured[index : index + 1].float(),
            reference.float(),
            variance[index : index + 1].float(),
            shifts=5,
            around=tuple(centres[index].flip(0).tolist()),
            yaws=yaws,
        )
        poses.append(found.pose[0].double())
    return torch.stack(poses)


def run_register(maps, captured, variance, start, score, uniform: bool) -> tuple[torch.Tensor, float]:
    """Registered poses, seconds per registration (one batch per map photograph: the maps differ)."""
    if uniform:
        variance = variance.mean((1, 2, 3), keepdim=True).expand_as(variance)
    poses = torch.empty_like(start)
    began = time.perf_counter()
    for name in range(len(PHOTOGRAPHS)):
        rows = list(range(name, len(maps), len(PHOTOGRAPHS)))
        if not rows:
            continue
        given = None if isinstance(score, NCC) else variance[rows]
        found = register(captured[rows], maps[rows[0]], given, pose=start[rows], score=score, margin=1.0)
        poses[rows] = found.pose.double()
    return poses, (time.perf_counter() - began) / len(maps)


def run_simpleitk(maps, captured, start, rigid: bool) -> tuple[torch.Tensor, float]:
    """SimpleITK's Mattes MI registration of each trial, from the integer peak (translation) or the pose (rigid)."""
    began = time.perf_counter()
    poses = mattes_registration([reference[0, 0] for reference in maps], captured, start, rigid)
    return poses, (time.perf_counter() - began) / len(maps)


def summarise(pose: torch.Tensor, truth: torch.Tensor, found: torch.Tensor, reference: torch.Tensor | None) -> dict:
    """The cell's numbers of one method: RMS errors, median, share within 0.25 cell, yaw RMS, paired difference.

    RMS over all trials and over those whose search found the right cell (``found``); the yaw RMS and the paired
    difference of squared errors against ``reference`` over ``found``.
    """
    squared = (pose[:, :2] - truth[:, :2]).square().sum(1)
    row = {
        "rms": float(squared.mean().sqrt()),
        "rms_found": float(squared[found].mean().sqrt()),
        "median": float(squared.sqrt().median()),
        "within": float((squared.sqrt() <= 0.25).double().mean()),
        "yaw_rms": float((pose[found, 2] - truth[found, 2]).square().mean().sqrt()),
    }
    if reference is not None:
        difference = (squared - reference)[found]
        row["paired"] = (float(difference.mean()), float(difference.std() / math.sqrt(len(difference))))
    return row, squared


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.epilog = "examples:\n" + __doc__.rsplit("\n\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--trials", type=int, default=48, help="paired trials per cell (default 48)")
    parser.add_argument("--cells", nargs="+", default=list(CELLS), help="sensor@sigma[+change] (default: all)")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.trials < 2:
        parser.error(f"--trials must be >= 2, got {args.trials}")
    for cell in args.cells:
        try:
            parse_cell(cell)
        except ValueError as error:
            parser.error(str(error))
    if any(method.startswith("SimpleITK") for method in args.methods):
        try:
            import SimpleITK  # noqa: F401
        except ImportError:
            parser.error("the SimpleITK methods need SimpleITK: pip install -e '.[bench]' (or leave them out)")
    torch.set_num_threads(1)
    print(f"{args.trials} paired trials per cell; torch threads 1; errors in cells (yaw in degrees)", flush=True)
    lines = [
        "| cell | method | found | RMS error, found | RMS error, all | median error | within 0.25 cell "
        "| yaw RMS, found | ms per registration | squared error - ECR true's, found (± SE) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    began = time.perf_counter()
    for number, cell in enumerate(args.cells):
        maps, captured, variance, centres, truth = make_trials(cell, args.trials, args.seed + number, yardstick)
        with value_checks(False):
            start_began = time.perf_counter()
            start = start_poses(maps, captured, variance, centres)
            start_seconds = (time.perf_counter() - start_began) / args.trials
        results = {}
        for method in args.methods:
            if method == "quadratic fit":
                results[method] = (start, start_seconds)
            elif method.startswith("register"):
                score = NCC() if method.endswith("NCC") else ECR()
                results[method] = run_register(maps, captured, variance, start, score, method.endswith("uniform"))
            else:
                results[method] = run_simpleitk(maps, captured, start, method.endswith("rigid"))
        found = (start[:, :2] - truth[:, :2]).abs().amax(1) <= 1  # the search found the right cell: refinable
        reference = None
        if "register ECR true" in results:
            reference = summarise(results["register ECR true"][0], truth, found, None)[1]
        for method, (pose, seconds) in results.items():
            row, _ = summarise(pose, truth, found, None if method == "register ECR true" else reference)
            paired = f"{row['paired'][0]:+.4f} ± {row['paired'][1]:.4f}" if "paired" in row else "-"
            yaw = "-" if method == "SimpleITK Mattes translation" else f"{row['yaw_rms']:.3f}"
            lines.append(
                f"| {cell} | {method} | {int(found.sum())} | {row['rms_found']:.3f} | {row['rms']:.3f} | "
                f"{row['median']:.3f} | {row['within']:.2f} | {yaw} | {1000 * seconds:.1f} | {paired} |"
            )
        print(f"cell {number + 1}/{len(args.cells)} {cell}: {time.perf_counter() - began:.0f} s", flush=True)
    print("\n".join(["", *lines]))


if __name__ == "__main__":
    sys.exit(main())
