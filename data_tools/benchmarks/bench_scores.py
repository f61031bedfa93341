"""Speed of each score's FFT surface against the paper's ENMI surface, side by side in one process.

Two cases, float32, a camera-like per-pixel variance: the localization benchmark's (a 128 x 128 local image of
scikit-image's gravel, 101 x 101 shifts, 10,201 candidates) and the yardstick's (64 x 64, 25 x 25 shifts). Each
round times every surface once, in turn; the ratio to ENMI is the median of the per-round ratios (robust to the
load bursts of a shared machine). Run it with one thread (the default here) or say the setting you used.

    python -m data_tools.benchmarks.bench_scores                 # ~1 minute on a quiet 2-core CPU
    python -m data_tools.benchmarks.bench_scores --rounds 20 --threads 2
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from skimage import data

from enmi_torch.scores import ECR, ENMI, NCC, NMI

CASES = {"128x128 local, 101x101 shifts": (128, 50), "64x64 local, 25x25 shifts": (64, 12)}


def _case(size: int, radius: int):
    generator = torch.Generator().manual_seed(0)
    gravel = torch.from_numpy(data.gravel().astype(np.float64))
    window = gravel[100 : 100 + size + 2 * radius, 120 : 120 + size + 2 * radius].reshape(1, 1, size + 2 * radius, -1)
    rows = torch.arange(size, dtype=torch.float64)
    variance = (25.0 * (1 + 99 * ((size - 1 - rows) / (size - 1)) ** 3)).reshape(size, 1).expand(size, size)
    local = window[..., radius + 3 : radius + 3 + size, radius - 5 : radius - 5 + size]
    local = local + torch.randn(local.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    return local.float(), window.float(), variance.float().reshape(1, 1, size, size)


def _surfaces(local, window, variance) -> dict:
    scores = {"ENMI (mass)": ENMI(), "ECR": ECR(), "ECR linear": ECR(response="linear"), "NMI": NMI(), "NCC": NCC()}

    def surface(score):
        return lambda: score.surface(local, window, variance if score.uses_variance else None)

    return {name: surface(score) for name, score in scores.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rounds", type=int, default=10, help="interleaved rounds (default 10)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        parser.error(f"--rounds and --threads must be >= 1, got {args.rounds} and {args.threads}")
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), {args.rounds} interleaved rounds, float32, 32 bins\n")
    print("| case | surface | median time | ratio to the ENMI surface (median of per-round ratios) |")
    print("|---|---|---|---|")
    for label, (size, radius) in CASES.items():
        local, window, variance = _case(size, radius)
        surfaces = _surfaces(local, window, variance)
        for function in surfaces.values():
            function()  # warm-up
        times = {name: [] for name in surfaces}
        for round_index in range(args.rounds):
            for name, function in surfaces.items():
                start = time.perf_counter()
                function()
                times[name].append(time.perf_counter() - start)
            print(f"  {label}: round {round_index + 1}/{args.rounds}", end="\r", file=sys.stderr, flush=True)
        print(" " * 60, end="\r", file=sys.stderr)
        for name, seconds in times.items():
            ratios = [mine / reference for mine, reference in zip(seconds, times["ENMI (mass)"], strict=True)]
            median = statistics.median(seconds)
            print(f"| {label} | {name} | {median * 1e3:.1f} ms | {statistics.median(ratios):.2f}x |")


if __name__ == "__main__":
    main()
