"""Speed of the FFT score surfaces against per-candidate loops, with and without glibc's malloc thresholds raised.

The case measured: a 128 x 128 local image cut from scikit-image's gravel texture (CC0) with
noise, a 101 x 101 window of shifts (10,201 candidates), 32 bins, float32, all CPU threads torch uses. Measured, in
one process each (medians of repeated runs, best run in brackets):

* the FFT surfaces (ENMI, NMI, NCC) and ENMI over 36 yaws (``localize``, rotation included);
* the best direct loop: the captured likelihood weights computed once, then one ``index_add_`` of them into the
  joint histogram per candidate (timed on a few rows of candidates and scaled to all; equal scores checked);
* the FFT core alone: the products and inverse transforms of the ENMI surface's bin pairs, nothing else; no FFT
  method that correlates bin planes can beat it, so ``loop / core`` bounds the ratio any such surface can reach;
* the library's reference :func:`~enmi_torch.direct_surface` (one score of an aligned pair per candidate);
* the other fast path considered: ``conv2d`` with the 32 captured weight planes as kernels over the 32 reference
  indicator planes (timed on a few output rows and scaled).

The parent process runs the measurements in child processes, in turn as is, with ``MALLOC_MMAP_THRESHOLD_`` and
``MALLOC_TRIM_THRESHOLD_`` set high, and with ``OMP_WAIT_POLICY=PASSIVE`` (OpenMP threads sleep between parallel
regions instead of spinning), and prints them side by side; the ratio to the direct loop is the median of ratios
taken within each round, which shared-machine load bursts affect least.

    python -m data_tools.benchmarks.bench_localize                          # about 3 minutes on 2 CPU cores
    python -m data_tools.benchmarks.bench_localize --rounds 8 --children 3  # steadier medians
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from skimage import data
from tqdm import tqdm

from enmi_torch.binning import hard_bin_index, likelihood_weights
from enmi_torch.information import nmi_from_joint_histogram
from enmi_torch.localization.search import localize
from enmi_torch.placement import fft_size
from enmi_torch.scores import ENMI, NCC, NMI, direct_surface

LOCAL, RADIUS, BINS, VALUE_RANGE = 128, 50, 32, (0.0, 256.0)
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(1 << 30), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}
PASSIVE_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}


def _case(dtype=torch.float32):
    generator = torch.Generator().manual_seed(0)
    gravel = torch.from_numpy(data.gravel().astype(np.float64)).reshape(1, 1, 512, 512)
    center = (256, 256)
    true_shift = (7, -12)
    top, left = center[0] - LOCAL // 2 + true_shift[0], center[1] - LOCAL // 2 + true_shift[1]
    local = gravel[..., top : top + LOCAL, left : left + LOCAL]
    local = local + 8.0 * torch.randn(local.shape, generator=generator, dtype=local.dtype)
    rows, cols = torch.meshgrid(torch.arange(float(LOCAL)), torch.arange(float(LOCAL)), indexing="ij")
    variance = (16.0 + 0.02 * ((rows - 64) ** 2 + (cols - 64) ** 2)).reshape(1, 1, LOCAL, LOCAL)
    top, left = center[0] - LOCAL // 2 - RADIUS, center[1] - LOCAL // 2 - RADIUS
    window = gravel[..., top : top + LOCAL + 2 * RADIUS, left : left + LOCAL + 2 * RADIUS]
    return gravel.to(dtype), local.to(dtype), variance.to(dtype), window.to(dtype), center


def _timed(function):
    start = time.perf_counter()
    result = function()
    return time.perf_counter() - start, result


def _best_direct_loop(local, window, variance, rows):
    """Likelihood weights once, then one scatter into the joint histogram per candidate of the first ``rows`` rows.

    Each candidate's reference bins are copied into one preallocated index (5-8 % faster than a fresh one each).
    """
    weights = likelihood_weights(local.flatten(), variance.flatten(), BINS, VALUE_RANGE, "mass")
    window_bins = hard_bin_index(window[0, 0], BINS, VALUE_RANGE)
    cols = window.shape[-1] - LOCAL + 1
    transposed = weights.new_zeros(rows * cols, BINS, BINS)
    reference_bins = window_bins.new_empty(LOCAL, LOCAL)
    for row in range(rows):
        for col in range(cols):
            reference_bins.copy_(window_bins[row : row + LOCAL, col : col + LOCAL])
            transposed[row * cols + col].index_add_(0, reference_bins.view(-1), weights)
    return nmi_from_joint_histogram(transposed.transpose(1, 2)).reshape(rows, cols)


def _fft_core(local, window, variance):
    """The products and inverse transforms of the ENMI surface's bin pairs, in the library's blocks; spectra given."""
    weights = likelihood_weights(local[0, 0], variance[0, 0], BINS, VALUE_RANGE, "mass").permute(2, 0, 1)
    window_bins = hard_bin_index(window[0, 0], BINS, VALUE_RANGE)
    present = torch.bincount(window_bins.flatten(), minlength=BINS).nonzero()[:, 0]
    size = (fft_size(window.shape[-2]), fft_size(window.shape[-1]))
    rows, cols = (window.shape[-2] - LOCAL + 1, window.shape[-1] - LOCAL + 1)
    captured = torch.fft.rfft2(weights, s=size).transpose(-1, -2).conj().contiguous()
    reference = torch.fft.rfft2((window_bins == present[:, None, None]).to(local.dtype), s=size)
    reference = reference.transpose(-1, -2).contiguous()
    blocks = -(-reference.shape[0] // 16)
    per_block = -(-reference.shape[0] // blocks)
    product = reference.new_empty(per_block, *reference.shape[1:])

    def core():
        for index in range(captured.shape[0]):
            for start in range(0, reference.shape[0], per_block):
                count = min(per_block, reference.shape[0] - start)
                torch.mul(captured[index], reference[start : start + count], out=product[:count])
                inverse = torch.fft.ifft(product[:count], dim=-1, norm="forward")[..., :rows]
                torch.fft.irfft(inverse, n=size[1], dim=-2, norm="forward")[:, :cols]

    return core, captured.shape[0] * reference.shape[0]


def _conv2d_surface_rows(local, window, variance, rows):
    """The K x K correlations of the first ``rows`` rows of placements by conv2d (reference planes as a batch)."""
    weights = likelihood_weights(local[0, 0], variance[0, 0], BINS, VALUE_RANGE, "mass").permute(2, 0, 1)
    section = window[..., : LOCAL + rows - 1, :]
    indicators = torch.nn.functional.one_hot(hard_bin_index(section[0, 0], BINS, VALUE_RANGE), BINS)
    indicators = indicators.permute(2, 0, 1).unsqueeze(1).to(local.dtype)
    return torch.nn.functional.conv2d(indicators, weights.unsqueeze(1))


def measure(rounds: int, loop_rows: int, yaw_rounds: int) -> dict:
    """Timings of one process: lists of per-round seconds, measured in interleaved rounds."""
    prior_map, local, variance, window, center = _case()
    candidates = (2 * RADIUS + 1) ** 2
    scale = candidates / (loop_rows * (2 * RADIUS + 1))
    times = {key: [] for key in ("enmi", "nmi", "ncc", "enmi_float64", "fft_core", "best_direct_loop")}
    double = (local.double(), window.double(), variance.double())
    core, pairs = _fft_core(local, window, variance)
    enmi = ENMI(bins=BINS, value_range=VALUE_RANGE)
    for _ in range(rounds):
        # Interleaved rounds: a burst of load from other processes hits every method of the round alike.
        seconds, fast = _timed(lambda: enmi.surface(local, window, variance))
        times["enmi"].append(seconds)
        times["nmi"].append(_timed(lambda: NMI(bins=BINS).surface(local, window))[0])
        times["ncc"].append(_timed(lambda: NCC().surface(local, window))[0])
        seconds, exact = _timed(lambda: enmi.surface(*double))
        times["enmi_float64"].append(seconds)
        times["fft_core"].append(_timed(core)[0])
        seconds, looped = _timed(lambda: _best_direct_loop(local, window, variance, loop_rows))
        times["best_direct_loop"].append(seconds * scale)
    peak = divmod(int(fast.score[0].flatten().argmax()), 2 * RADIUS + 1)
    checks = {
        "enmi_peak_shift": (peak[0] - RADIUS, peak[1] - RADIUS),
        "float32_vs_float64_max_abs": float((fast.score.double() - exact.score).abs().max()),
        "best_direct_loop_vs_fft_max_abs": float((looped - fast.score[0, :loop_rows]).abs().max()),
    }
    few = window[..., : LOCAL + 1, : LOCAL + 2]
    seconds, reference = _timed(lambda: direct_surface(enmi, local, few, variance))
    times["direct_surface"] = [seconds * candidates / 6]
    checks["direct_surface_vs_fft_max_abs"] = float((reference.score[0] - fast.score[0, :2, :3]).abs().max())
    conv_rows = 2
    times["conv2d_correlations"] = [
        _timed(lambda: _conv2d_surface_rows(local, window, variance, conv_rows))[0] * (2 * RADIUS + 1) / conv_rows
    ]
    yaws = [float(angle) for angle in range(-35, 36, 2)]
    times["localize_36_yaws"] = []
    for _ in range(yaw_rounds):
        seconds, located = _timed(
            lambda: localize(local, prior_map, variance, score=enmi, shifts=RADIUS, around=center[::-1], yaws=yaws)
        )
        times["localize_36_yaws"].append(seconds)
    checks["localize_pose"] = [round(value, 2) for value in [*located.shift[0].tolist(), float(located.yaw[0])]]
    checks["bin_pairs"] = pairs
    return {"threads": torch.get_num_threads(), "candidates": candidates, "yaws": len(yaws), **checks, "times": times}


def _child(environment: dict, rounds: int, loop_rows: int, yaw_rounds: int) -> dict:
    command = [sys.executable, "-m", __spec__.name, "--child", "--rounds", str(rounds), "--loop-rows", str(loop_rows)]
    command += ["--yaw-rounds", str(yaw_rounds)]
    inherited = {key: value for key, value in os.environ.items() if key not in {*MALLOC_ENV, *PASSIVE_ENV}}
    completed = subprocess.run(command, env={**inherited, **environment}, capture_output=True, text=True, check=True)
    return json.loads(completed.stdout.strip().splitlines()[-1])


def _merge(runs: list[dict]) -> dict:
    merged = {**runs[0], "times": {key: [] for key in runs[0]["times"]}}
    for run in runs:
        for key, values in run["times"].items():
            merged["times"][key] += values
    return merged


LABELS = {
    "enmi": "ENMI surface, FFT",
    "nmi": "NMI surface, FFT",
    "ncc": "NCC surface, FFT",
    "enmi_float64": "ENMI surface, FFT, float64",
    "fft_core": "FFT core alone: products and inverse transforms of the {pairs} bin pairs",
    "best_direct_loop": "best direct loop: weights once, one `index_add_` per candidate (timed on {rows} rows, scaled)",
    "direct_surface": "`direct_surface`: one `joint_histogram` per candidate (timed on 6, scaled)",
    "conv2d_correlations": "`conv2d`, weight planes over indicator planes (correlations only; 2 rows, scaled)",
    "localize_36_yaws": "`localize`, ENMI, 36 yaws (rotations, 36 surfaces, peak)",
}


def _report(runs: dict[str, dict], loop_rows: int) -> None:
    names = list(runs)
    first = runs[names[0]]
    print(
        f"128 x 128 local, {first['candidates']:,} candidates (101 x 101 shifts), {BINS} bins, float32, "
        f"{first['threads']} torch threads; median [best] seconds over interleaved rounds\n"
    )
    print("| | " + " | ".join(names) + " |")
    print("|" + " --- |" * (len(names) + 1))
    for key, label in LABELS.items():
        cells = []
        for name in names:
            values = runs[name]["times"][key]
            median = statistics.median(values)
            rate = "" if key == "localize_36_yaws" else f", {first['candidates'] / median:,.0f} candidates/s"
            cells.append(f"{median:.3f} [{min(values):.3f}]{rate}")
        print(f"| {label.format(rows=loop_rows, pairs=first['bin_pairs'])} | " + " | ".join(cells) + " |")
    print()
    for name in names:
        run, times = runs[name], runs[name]["times"]
        paired = [loop / fft for loop, fft in zip(times["best_direct_loop"], times["enmi"], strict=True)]
        fft = statistics.median(times["enmi"])
        ceiling = [loop / core for loop, core in zip(times["best_direct_loop"], times["fft_core"], strict=True)]
        print(
            f"{name}: best direct loop / FFT = {statistics.median(paired):.1f}x (median of per-round ratios; "
            f"loop / FFT core alone = {statistics.median(ceiling):.1f}x), "
            f"direct_surface / FFT = {times['direct_surface'][0] / fft:.0f}x, conv2d / FFT = "
            f"{times['conv2d_correlations'][0] / fft:.1f}x; 36 yaws: "
            f"{statistics.median(times['localize_36_yaws']) / run['yaws']:.3f} s per yaw"
        )
    print(
        f"\nchecks: max |FFT - loop| = {first['best_direct_loop_vs_fft_max_abs']:.1e}, "
        f"max |FFT - direct_surface| = {first['direct_surface_vs_fft_max_abs']:.1e}, "
        f"max |float32 - float64| = {first['float32_vs_float64_max_abs']:.1e}; "
        f"surface peak (dy, dx) = {tuple(first['enmi_peak_shift'])} (true (7, -12)); "
        f"36-yaw pose (dx, dy, yaw) = {first['localize_pose']}"
    )
    base, raised = (statistics.median(runs[name]["times"]["enmi"]) for name in names[:2])
    print(f"raising the malloc thresholds: ENMI surface median {base:.3f} s -> {raised:.3f} s ({base / raised:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4, help="interleaved rounds per child process")
    parser.add_argument("--children", type=int, default=2, help="child processes per malloc setting, alternated")
    parser.add_argument("--yaw-rounds", type=int, default=1, help="36-yaw searches per child process")
    parser.add_argument("--loop-rows", type=int, default=5, help="rows of candidates the direct loop is timed on")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.rounds, args.loop_rows, args.yaw_rounds)))
        return
    settings = {
        "defaults": {},
        "MALLOC_MMAP_THRESHOLD_=MALLOC_TRIM_THRESHOLD_=2^30": MALLOC_ENV,
        "OMP_WAIT_POLICY=PASSIVE": PASSIVE_ENV,
    }
    collected = {name: [] for name in settings}
    with tqdm(total=args.children * len(settings), desc="child processes", unit="child") as bar:
        for _ in range(args.children):
            for name, environment in settings.items():
                collected[name].append(_child(environment, args.rounds, args.loop_rows, args.yaw_rounds))
                bar.update()
    _report({name: _merge(runs) for name, runs in collected.items()}, args.loop_rows)


if __name__ == "__main__":
    main()
