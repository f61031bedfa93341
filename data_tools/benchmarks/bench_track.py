"""One step of the tracking filter against one ``localize`` call of the same window, in one run.

A 64 x 64 frame (the drive's camera model, ``data_tools.experiments.drive.drive``), a window of +-8 cells and 5 yaws one
degree apart, ECR with a per-pixel variance and the tracker's default spatially correlated misfit (``--misfit
independent`` for ECR's own default): ``track_step`` (predict, the search, update, pose read-out and health) against the
bare ``localize`` call, interleaved in rounds on one thread; the table gives the medians of the per-round times and of
the per-round ratios.

    python -m data_tools.benchmarks.bench_track              # ~1 min on 2 cores
    python -m data_tools.benchmarks.bench_track --bins 16 --rounds 40
    python -m data_tools.benchmarks.bench_track --misfit independent
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from data_tools.experiments.drive import drive as drive_tools
from enmi_torch.scores.ecr import MISFITS
from enmi_torch.tracking import TrackerSettings, default_score, initial_belief, track_step


def _seconds(call, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3, help="calls per round and method (the fastest counts)")
    parser.add_argument("--bins", type=int, default=32)
    parser.add_argument(
        "--misfit", choices=MISFITS, default=default_score().misfit, help="ECR's misfit (default: the tracker's)"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    drive = drive_tools.Drive(12, seed=0)
    index = 10
    frame = drive.frames[index : index + 1].float()
    variance = drive.variance("analytic", drive.pixel_noise)[index : index + 1]
    reference = drive.map.float()
    truth = drive.truth[index - 1 : index]
    odometry = drive.odometry[index : index + 1]
    belief = initial_belief(truth, shifts=8, yaw_bins=5, yaw_step=1.0, std=(0.5, 0.5, 0.5))
    center = torch.stack([truth[:, 1], truth[:, 0]], 1).round().long()
    yaws = (truth[0, 2].round() + torch.arange(-2.0, 3.0)).tolist()
    score = default_score().replace(bins=args.bins, misfit=args.misfit)

    def search():
        drive_tools.search(frame, reference, variance, drive.valid, center, yaws, score)

    def step():
        track_step(
            belief,
            frame,
            reference,
            odometry,
            variance,
            drive.valid,
            score=score,
            settings=TrackerSettings(motion_noise=drive.motion_noise),
        )

    search(), step()
    searches, steps, ratios = [], [], []
    for _ in range(args.rounds):
        first, second = _seconds(search, args.repeats), _seconds(step, args.repeats)
        searches.append(first)
        steps.append(second)
        ratios.append(second / first)
    print(
        f"64 x 64 frame, +-8 cells, 5 yaws, ECR {args.bins} bins, misfit {args.misfit}, 1 thread, {args.rounds} "
        "interleaved rounds\n"
    )
    print("| call | median time (ms) |")
    print("| --- | --- |")
    print(f"| localize | {1000 * statistics.median(searches):.1f} |")
    print(f"| track_step | {1000 * statistics.median(steps):.1f} |")
    quartiles = statistics.quantiles(ratios, n=4)
    print(
        f"\nmedian per-round ratio track_step / localize: {statistics.median(ratios):.3f} "
        f"(quartiles {quartiles[0]:.3f} to {quartiles[2]:.3f})"
    )


if __name__ == "__main__":
    main()
