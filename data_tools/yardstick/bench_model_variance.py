"""Speed of the ECR surfaces with an estimated model variance against today's ECR surface, in one process.

The cases of ``data_tools/bench_scores.py`` (float32, camera-like variance): a 128 x 128 local image of scikit-image's
gravel over 101 x 101 shifts, and the yardstick's 64 x 64 over 25 x 25. Each round times every surface once, in
turn; the ratio to today's ECR surface (``ecr_surface``, ``tau^2 = bin_width^2 / 12``) is the median of the
per-round ratios (robust to the load bursts of a shared machine). One torch thread unless told.

    python data_tools/yardstick/bench_model_variance.py              # a minute or two on a quiet 2-core CPU
    python data_tools/yardstick/bench_model_variance.py --rounds 41 --surfaces "est cheap" "local fisher"
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from skimage import data

from enmi_torch import _model_variance as model_variance
from enmi_torch.localization.surface import ecr_surface

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
    return {
        "ECR today": lambda: ecr_surface(local, window, variance),
        "est cheap": lambda: model_variance.ecr_estimated_surface(local, window, variance, first="cheap"),
        "est cheap r2": lambda: model_variance.ecr_estimated_surface(local, window, variance, first="cheap", rounds=2),
        "est uniform": lambda: model_variance.ecr_estimated_surface(local, window, variance, first="uniform"),
        "est default": lambda: model_variance.ecr_estimated_surface(local, window, variance, first="default"),
        "profile 3": lambda: model_variance.ecr_profile_surface(
            local, window, variance, factors=(1.0, 1 / 16, 1 / 256)
        ),
        "profile 6": lambda: model_variance.ecr_profile_surface(local, window, variance),
        "per-bin": lambda: model_variance.ecr_bin_variance_surface(local, window, variance),
        "local fisher": lambda: model_variance.ecr_local_surface(local, window, variance),
        "local fisher default": lambda: model_variance.ecr_local_surface(local, window, variance, first="default"),
        "local fisher c8": lambda: model_variance.ecr_local_surface(local, window, variance, candidates=8),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rounds", type=int, default=11, help="interleaved rounds (default 11)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--surfaces", nargs="+", default=None, help="a subset of the surfaces (ECR today always)")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        parser.error(f"--rounds and --threads must be >= 1, got {args.rounds} and {args.threads}")
    torch.set_num_threads(args.threads)
    print(f"| case | surface | median time (ms) | ratio to today's ECR (median of {args.rounds} rounds) |")
    print("|---|---|---|---|")
    for case, (size, radius) in CASES.items():
        surfaces = _surfaces(*_case(size, radius))
        if args.surfaces is not None:
            unknown = set(args.surfaces) - set(surfaces)
            if unknown:
                parser.error(f"--surfaces: unknown {sorted(unknown)}; choose from {list(surfaces)}")
            surfaces = {name: surface for name, surface in surfaces.items() if name in {"ECR today", *args.surfaces}}
        for surface in surfaces.values():
            surface()  # warm-up: first-call allocations, FFT plans
        times = {name: [] for name in surfaces}
        for round_index in range(args.rounds):
            for name, surface in surfaces.items():
                start = time.perf_counter()
                surface()
                times[name].append(time.perf_counter() - start)
            print(f"[{case}] round {round_index + 1}/{args.rounds}", file=sys.stderr, flush=True)
        for name in surfaces:
            ratios = [mine / today for mine, today in zip(times[name], times["ECR today"], strict=True)]
            print(f"| {case} | {name} | {statistics.median(times[name]) * 1e3:.1f} | {statistics.median(ratios):.2f} |")


if __name__ == "__main__":
    main()
