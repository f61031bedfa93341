"""Cost of ECR's default (the shrunk response, estimated model variance) against the binned response, in one process.

The cases of ``bench_scores.py`` (float32, camera-like variance, 32 bins): a 128 x 128 local image of scikit-image's
gravel over 101 x 101 shifts, and the yardstick's 64 x 64 over 25 x 25; for each, the surface and ``localize`` over
5 yaws, exhaustive and two-stage, with three scores: ``ECR()`` (the default: the shrunk response's profile over
``delta^2`` is its extra work), ``ECR(response="binned")`` (the default before it) and ``ECR(response="binned",
model_variance=None)`` (the fixed ``tau^2`` before that: the estimate's cheap first pass and its REML fit are the
binned default's extra work). Each round times every entry once, in turn; the ratio to the
fixed ``tau^2`` is the median of the per-round ratios (robust to the load bursts of a shared machine). One torch
thread unless told.

    python -m data_tools.benchmarks.bench_model_variance               # a minute or two on a quiet 2-core CPU
    python -m data_tools.benchmarks.bench_model_variance --rounds 41
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from skimage import data

from enmi_torch import ECR, localize

CASES = {"128x128 local, 101x101 shifts": (128, 50), "64x64 local, 25x25 shifts": (64, 12)}
YAWS = [-4.0, -2.0, 0.0, 2.0, 4.0]
SCORES = {
    "default": {},
    "binned": {"response": "binned"},
    "binned, fixed tau^2": {"response": "binned", "model_variance": None},
}


def _case(size: int, radius: int):
    generator = torch.Generator().manual_seed(0)
    gravel = torch.from_numpy(data.gravel().astype(np.float64))
    window = gravel[100 : 100 + size + 2 * radius, 120 : 120 + size + 2 * radius].reshape(1, 1, size + 2 * radius, -1)
    rows = torch.arange(size, dtype=torch.float64)
    variance = (25.0 * (1 + 99 * ((size - 1 - rows) / (size - 1)) ** 3)).reshape(size, 1).expand(size, size)
    local = window[..., radius + 3 : radius + 3 + size, radius - 5 : radius - 5 + size]
    local = local + torch.randn(local.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    return local.float(), window.float(), variance.float().reshape(1, 1, size, size), radius


def _entries(local, window, variance, radius) -> dict:
    """``{what: {score name: call}}``."""
    scores = {name: ECR(**options) for name, options in SCORES.items()}
    centre = (window.shape[3] // 2, window.shape[2] // 2)  # (x, y)

    def surface(score):
        return lambda: score.surface(local, window, variance)

    def search(score, kind):
        return lambda: localize(
            local, window, variance, score=score, shifts=radius, around=centre, yaws=YAWS, search=kind
        )

    return {
        "surface": {name: surface(score) for name, score in scores.items()},
        "localize, 5 yaws": {name: search(score, "exhaustive") for name, score in scores.items()},
        "localize, 5 yaws, two-stage": {name: search(score, "two_stage") for name, score in scores.items()},
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rounds", type=int, default=11, help="interleaved rounds (default 11)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        parser.error(f"--rounds and --threads must be >= 1, got {args.rounds} and {args.threads}")
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), {args.rounds} interleaved rounds, float32, 32 bins\n")
    print(
        "| case | what | binned, fixed tau^2 | binned (the former default) | default (shrunk) | default / binned | "
        "default / fixed |"
    )
    print("|---|---|---|---|---|---|---|")
    for label, (size, radius) in CASES.items():
        entries = _entries(*_case(size, radius))
        calls = [(what, name, call) for what, pair in entries.items() for name, call in pair.items()]
        for _, _, call in calls:
            call()  # warm-up: first-call allocations, FFT plans
        times = {(what, name): [] for what, name, _ in calls}
        for round_index in range(args.rounds):
            for what, name, call in calls:
                start = time.perf_counter()
                call()
                times[what, name].append(time.perf_counter() - start)
            print(f"  {label}: round {round_index + 1}/{args.rounds}", end="\r", file=sys.stderr, flush=True)
        print(" " * 60, end="\r", file=sys.stderr)
        for what in entries:
            fixed, binned, default = (times[what, name] for name in ("binned, fixed tau^2", "binned", "default"))
            ratios = [
                statistics.median(mine / reference for mine, reference in zip(default, baseline, strict=True))
                for baseline in (binned, fixed)
            ]
            columns = (fixed, binned, default)
            milliseconds = " | ".join(f"{statistics.median(column) * 1e3:.1f} ms" for column in columns)
            print(f"| {label} | {what} | {milliseconds} | {ratios[0]:.2f}x | {ratios[1]:.2f}x |")


if __name__ == "__main__":
    main()
