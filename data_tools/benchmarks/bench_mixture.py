"""Speed of the two-stage mixture surface against the FFT ECR and ENMI surfaces, on one CPU thread.

A 64 x 64 local image cut from scikit-image's gravel texture (CC0), seen through a non-monotonic response with
noise of per-pixel variance, placed in an 88 x 88 window (25 x 25 placements), 32 bins, float32. The surfaces are
timed in interleaved rounds (each round runs every surface once, in turn) and the medians printed; shared-machine
load bursts then hit every surface alike. Also printed: how many placements the two-stage surface rescored, and
whether its argmax equals the direct loop's (every placement rescored, run once).

    python -m data_tools.benchmarks.bench_mixture            # about a minute on a busy 2-core machine
    python -m data_tools.benchmarks.bench_mixture --rounds 21
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from skimage import data

from enmi_torch.scores import ECR, ENMI, Mixture, direct_surface

LOCAL, WINDOW, BINS = 64, 88, 32


def _case():
    generator = torch.Generator().manual_seed(0)
    gravel = torch.from_numpy(data.gravel().astype(np.float32)).reshape(1, 1, 512, 512)
    window = gravel[..., 200 : 200 + WINDOW, 180 : 180 + WINDOW]
    top, left = 9, 14
    section = window[..., top : top + LOCAL, left : left + LOCAL]
    rows, cols = torch.meshgrid(torch.arange(float(LOCAL)), torch.arange(float(LOCAL)), indexing="ij")
    variance = (100.0 + 0.3 * ((rows - 32) ** 2 + (cols - 32) ** 2)).reshape(1, 1, LOCAL, LOCAL)
    local = 300 * (section / 256 - 0.4).abs() + variance.sqrt() * torch.randn(section.shape, generator=generator)
    return local, window, variance, (top, left)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=11)
    arguments = parser.parse_args()
    torch.set_num_threads(1)
    local, window, variance, truth = _case()
    scores = {
        "mixture_surface": Mixture(bins=BINS),
        "mixture_surface em_steps=2": Mixture(bins=BINS, em_steps=2),
        "ecr_surface": ECR(bins=BINS),
        "enmi_surface": ENMI(bins=BINS),
    }

    def surface(score):
        return lambda: score.surface(local, window, variance)

    runs = {name: surface(score) for name, score in scores.items()}
    for run in runs.values():  # warm-up
        run()
    times = {name: [] for name in runs}
    for _ in range(arguments.rounds):
        for name, run in runs.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    print(f"{LOCAL} x {LOCAL} local in a {WINDOW} x {WINDOW} window, {BINS} bins, float32, 1 thread,")
    print(f"medians of {arguments.rounds} interleaved rounds [min, max]:")
    for name, values in times.items():
        median, low, high = (1e3 * statistic(values) for statistic in (statistics.median, min, max))
        print(f"  {name:28s} {median:8.1f} ms  [{low:.1f}, {high:.1f}]")

    two_stage = Mixture(bins=BINS).surface(local, window, variance).score[0]
    start = time.perf_counter()
    direct = direct_surface(Mixture(bins=BINS), local, window, variance).score[0]
    direct_time = time.perf_counter() - start
    columns = two_stage.shape[1]
    rescored = int(torch.isfinite(two_stage).sum())
    best = divmod(int(two_stage.argmax()), columns)
    print(f"two-stage rescored {rescored} of {two_stage.numel()} placements; argmax {best}")
    print(f"direct loop ({direct_time:.1f} s once): argmax {divmod(int(direct.argmax()), columns)}; truth {truth}")
    agree = torch.isfinite(two_stage)
    print(f"largest |two-stage - direct| where rescored: {(two_stage[agree] - direct[agree]).abs().max().item():.1e}")


if __name__ == "__main__":
    main()
