"""Speed of the FFT score surfaces against per-candidate loops, with and without glibc's malloc thresholds raised.

The case of the localization issue: a 128 x 128 local image cut from scikit-image's gravel texture (CC0) with
noise, a 101 x 101 window of shifts (10,201 candidates), 32 bins, float32, all CPU threads torch uses. Measured, in
one process each (medians of repeated runs, best run in brackets):

* the FFT surfaces (ENMI, NMI, NCC) and ENMI over 36 yaws (``localize``, rotation included);
* the best direct loop: the captured likelihood weights computed once, then one ``index_add_`` of them into the
  joint histogram per candidate (timed on a few rows of candidates and scaled to all; equal scores checked);
* the library's reference :func:`~enmi_torch.score_surface.direct_surface` (one ``joint_histogram`` per candidate);
* the other fast path considered: ``conv2d`` with the 32 captured weight planes as kernels over the 32 reference
  indicator planes (timed on a few output rows and scaled).

The parent process runs the measurement twice in child processes, once as is and once with
``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` set high, and prints both side by side.

    python data_tools/bench_localize.py            # about 1-2 minutes on 2 CPU cores
    python data_tools/bench_localize.py --quick    # fewer repeats
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

from enmi_torch.binning import hard_bin_index, likelihood_weights
from enmi_torch.information import nmi_from_joint_histogram
from enmi_torch.localize import localize
from enmi_torch.score_surface import direct_surface, enmi_surface, ncc_surface, nmi_surface

LOCAL, RADIUS, BINS, VALUE_RANGE = 128, 50, 32, (0.0, 256.0)
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(1 << 30), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}


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


def _timed(function, repeats):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times), result


def _best_direct_loop(local, window, variance, rows):
    """Likelihood weights once, then one scatter into the joint histogram per candidate of the first ``rows`` rows."""
    weights = likelihood_weights(local.flatten(), variance.flatten(), BINS, VALUE_RANGE, "mass")
    window_bins = hard_bin_index(window[0, 0], BINS, VALUE_RANGE)
    cols = window.shape[-1] - LOCAL + 1
    transposed = weights.new_zeros(rows * cols, BINS, BINS)
    for row in range(rows):
        for col in range(cols):
            reference_bins = window_bins[row : row + LOCAL, col : col + LOCAL].reshape(-1)
            transposed[row * cols + col].index_add_(0, reference_bins, weights)
    return nmi_from_joint_histogram(transposed.transpose(1, 2)).reshape(rows, cols)


def _conv2d_surface_rows(local, window, variance, rows):
    """The K x K correlations of the first ``rows`` rows of placements by conv2d (reference planes as a batch)."""
    weights = likelihood_weights(local[0, 0], variance[0, 0], BINS, VALUE_RANGE, "mass").permute(2, 0, 1)
    section = window[..., : LOCAL + rows - 1, :]
    indicators = torch.nn.functional.one_hot(hard_bin_index(section[0, 0], BINS, VALUE_RANGE), BINS)
    indicators = indicators.permute(2, 0, 1).unsqueeze(1).to(local.dtype)
    return torch.nn.functional.conv2d(indicators, weights.unsqueeze(1))


def measure(repeats: int, loop_rows: int) -> dict:
    """All timings of one process, as a dict."""
    prior_map, local, variance, window, center = _case()
    candidates = (2 * RADIUS + 1) ** 2
    results = {"threads": torch.get_num_threads(), "candidates": candidates}
    enmi_median, enmi_best, fast = _timed(lambda: enmi_surface(local, window, variance, bins=BINS), repeats)
    results["enmi_surface_s"] = (enmi_median, enmi_best)
    results["nmi_surface_s"] = _timed(lambda: nmi_surface(local, window, bins=BINS), repeats)[:2]
    results["ncc_surface_s"] = _timed(lambda: ncc_surface(local, window), repeats)[:2]
    peak = divmod(int(fast.score[0].flatten().argmax()), 2 * RADIUS + 1)
    results["enmi_peak_shift"] = (peak[0] - RADIUS, peak[1] - RADIUS)

    single = _timed(lambda: enmi_surface(local.double(), window.double(), variance.double(), bins=BINS), 1)
    results["enmi_surface_float64_s"] = single[0]
    results["float32_vs_float64_max_abs"] = float((fast.score.double() - single[2].score).abs().max())

    loop_median, loop_best, looped = _timed(lambda: _best_direct_loop(local, window, variance, loop_rows), repeats)
    scale = candidates / (loop_rows * (2 * RADIUS + 1))
    results["best_direct_loop_s"] = (loop_median * scale, loop_best * scale)
    results["best_direct_loop_vs_fft_max_abs"] = float((looped - fast.score[0, :loop_rows]).abs().max())

    few = window[..., : LOCAL + 1, : LOCAL + 2]
    reference_loop = _timed(lambda: direct_surface(local, few, variance, bins=BINS), 1)
    results["direct_surface_s"] = reference_loop[0] * candidates / 6
    results["direct_surface_vs_fft_max_abs"] = float((reference_loop[2].score[0] - fast.score[0, :2, :3]).abs().max())

    conv_rows = 2
    conv = _timed(lambda: _conv2d_surface_rows(local, window, variance, conv_rows), 1)
    results["conv2d_correlations_s"] = conv[0] * (2 * RADIUS + 1) / conv_rows

    yaws = [float(angle) for angle in range(-35, 36, 2)]
    yaw_repeats = max(1, repeats // 3)
    yaw_median, yaw_best, located = _timed(
        lambda: localize(local, prior_map, variance, shifts=RADIUS, center=center, yaws=yaws, bins=BINS), yaw_repeats
    )
    results["yaws"] = len(yaws)
    results["localize_36_yaws_s"] = (yaw_median, yaw_best)
    results["localize_pose"] = [round(value, 2) for value in located.pose[0].tolist()]
    return results


def _child(environment: dict, repeats: int, loop_rows: int) -> dict:
    command = [sys.executable, __file__, "--child", "--repeats", str(repeats), "--loop-rows", str(loop_rows)]
    inherited = {key: value for key, value in os.environ.items() if key not in MALLOC_ENV}
    completed = subprocess.run(command, env={**inherited, **environment}, capture_output=True, text=True, check=True)
    return json.loads(completed.stdout.strip().splitlines()[-1])


def _report(runs: dict[str, dict]) -> None:
    names = list(runs)
    first = runs[names[0]]
    print(
        f"128 x 128 local, {first['candidates']} candidates (101 x 101 shifts), {BINS} bins, float32, "
        f"{first['threads']} torch threads; median [best] of repeated runs\n"
    )
    header = "| | " + " | ".join(names) + " |"
    print(header)
    print("|" + " --- |" * (len(names) + 1))

    def row(label, key, per_candidate=True):
        cells = []
        for name in names:
            median, best = runs[name][key] if isinstance(runs[name][key], (list, tuple)) else (runs[name][key],) * 2
            rate = f", {first['candidates'] / median:,.0f} cand/s" if per_candidate else ""
            cells.append(f"{median:.3f} s [{best:.3f}]{rate}")
        print(f"| {label} | " + " | ".join(cells) + " |")

    row("ENMI surface, FFT", "enmi_surface_s")
    row("NMI surface, FFT", "nmi_surface_s")
    row("NCC surface, FFT", "ncc_surface_s")
    row("ENMI surface, FFT, float64", "enmi_surface_float64_s")
    row("best direct loop (weights once, one index_add per candidate; scaled from a few rows)", "best_direct_loop_s")
    row("direct_surface (one joint_histogram per candidate; scaled from 6)", "direct_surface_s")
    row(
        "conv2d of weight planes over indicator planes (correlations only; scaled from 2 rows)", "conv2d_correlations_s"
    )
    row(f"localize, ENMI, {first['yaws']} yaws (rotation, surfaces, peak)", "localize_36_yaws_s", per_candidate=False)
    print()
    for name in names:
        run = runs[name]
        fft = run["enmi_surface_s"][0]
        print(
            f"{name}: best direct loop / FFT = {run['best_direct_loop_s'][0] / fft:.1f}x, "
            f"direct_surface / FFT = {run['direct_surface_s'] / fft:.0f}x, conv2d / FFT = "
            f"{run['conv2d_correlations_s'] / fft:.1f}x; per yaw {run['localize_36_yaws_s'][0] / run['yaws']:.3f} s; "
            f"max |FFT - loop| = {run['best_direct_loop_vs_fft_max_abs']:.1e}, "
            f"max |FFT - direct_surface| = {run['direct_surface_vs_fft_max_abs']:.1e}, "
            f"max |float32 - float64| = {run['float32_vs_float64_max_abs']:.1e}; "
            f"peak {run['enmi_peak_shift']} (true (7, -12)), pose {run['localize_pose']}"
        )
    base, raised = (runs[name]["enmi_surface_s"][0] for name in names[:2])
    print(f"\nraising the malloc thresholds: ENMI surface {base / raised:.2f}x faster")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--loop-rows", type=int, default=3, help="rows of candidates the direct loop is timed on")
    parser.add_argument("--quick", action="store_true", help="3 repeats")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    repeats = 3 if args.quick else args.repeats
    if args.child:
        print(json.dumps(measure(repeats, args.loop_rows)))
        return
    runs = {
        "glibc defaults": _child({}, repeats, args.loop_rows),
        "MALLOC_MMAP_THRESHOLD_ = MALLOC_TRIM_THRESHOLD_ = 2^30": _child(MALLOC_ENV, repeats, args.loop_rows),
    }
    _report(runs)


if __name__ == "__main__":
    main()
