"""Time per N0 point of the paper simulation's scores, with and without the library paths built for it.

    python data_tools/bench_paper_simulation.py [--trials 10000] [--repeats 5] [--chunk_trials 128] [--threads 1]

One "point" is ``trials`` trials of the paper's 66 tiles at one N0, each trial scoring the truth and the candidate
against the captured image, as ``enmi_torch.simulation.error_rates`` does. Two ways are timed side by side, in
interleaved rounds in one process (medians over ``--repeats`` rounds, at N0 = 0.01 and 0.3):

- ``shared``: what the simulation uses: both references in one call (``reference`` of shape ``(2, T, K)``), so ENMI
  computes the captured likelihood weights once, and hard NMI from ``hard_entropies`` (pixel-wise surprisal).
- ``separate``: one call per reference, hard NMI from the dense ``(T, 32, 32)`` joint histogram
  (``nmi_from_joint_histogram(joint_histogram(...))``), as without those paths.

Prints a Markdown table: ms per point for each score and way, the ratio, and the whole figure's projection (141
points, one core, no workers). The full run's wall time is what ``data_tools/reproduce_paper.py`` prints. A second
table times the hard entropies both ways at several image sizes (262,144 pixels in all, 32 bins): read at the pixels
(``hard_entropies``) and from the dense histogram (``entropies(joint_histogram(...))``), which is why ``nmi`` reads
them at the pixels only below ``bins^2 / 4`` pixels.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tqdm import tqdm

from enmi_torch import RoadCamera, enmi, entropies, gaussian_log_prior, joint_histogram, nmi_from_joint_histogram
from enmi_torch.histogram import hard_entropies
from enmi_torch.simulation import SCORES, count_errors, draw_trials, road_tiles

PAPER_POINTS = 141
NOISE_POWERS = (0.01, 0.3)
IMAGE_PIXELS = (66, 256, 1024, 4096, 65536)


def separate_errors(captured, amplitudes, candidates, variance, score, log_prior):
    """The same decision as ``count_errors``, one library call per reference."""

    def score_against(reference):
        if score == "nmi":
            return nmi_from_joint_histogram(joint_histogram(captured, reference))
        weights = "density" if score == "enmi_density" else "mass"
        return enmi(captured, reference, variance.reshape(1, -1), weights=weights, log_prior=log_prior)

    return score_against(candidates) >= score_against(amplitudes)


def time_point(way: str, score: str, trials, variance, chunk_trials: int, log_prior) -> tuple[float, int]:
    """Seconds to score one point's trials, and its error count."""
    function = count_errors if way == "shared" else separate_errors
    prior = log_prior if score == "enmi_mass_prior" else None
    errors = 0
    started = time.perf_counter()
    for start in range(0, trials.amplitudes.shape[0], chunk_trials):
        part = slice(start, start + chunk_trials)
        captured = trials.captured(variance, part)
        if way == "shared":
            wrong = function(
                captured, trials.amplitudes[part], trials.candidates[part], variance, score, log_prior=prior
            )
        else:
            wrong = function(captured, trials.amplitudes[part], trials.candidates[part], variance, score, prior)
        errors += int(wrong.sum())
    return time.perf_counter() - started, errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--chunk_trials", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    areas = road_tiles(RoadCamera.paper()).area.float()
    trials = draw_trials(args.trials, areas.numel(), generator=torch.Generator().manual_seed(0))
    log_prior = gaussian_log_prior(128, 32, 32, (0, 256))
    seconds = {(way, score): [] for way in ("shared", "separate") for score in SCORES}
    for noise_power in NOISE_POWERS:
        variance = noise_power / areas
        for score in SCORES:  # warm-up; the two ways must agree on every trial
            counts = {
                way: time_point(way, score, trials, variance, args.chunk_trials, log_prior)[1]
                for way in ("shared", "separate")
            }
            if counts["shared"] != counts["separate"]:
                raise RuntimeError(f"{score} at N0={noise_power}: shared and separate paths disagree {counts}")
        for _ in tqdm(range(args.repeats), desc=f"N0 = {noise_power:g}", unit="round"):
            for score in SCORES:
                for way in ("shared", "separate"):
                    elapsed, _ = time_point(way, score, trials, variance, args.chunk_trials, log_prior)
                    seconds[way, score].append(elapsed)

    print(
        f"\n{args.trials} trials per point, chunks of {args.chunk_trials}, {args.threads} thread(s), torch "
        f"{torch.__version__}; medians of {args.repeats} rounds x {len(NOISE_POWERS)} noise powers\n"
    )
    print("| score | shared: ms per point | separate: ms per point | separate / shared | 141 points, shared (s) |")
    print("| --- | --- | --- | --- | --- |")
    totals = {"shared": 0.0, "separate": 0.0}
    for score in SCORES:
        shared = statistics.median(seconds["shared", score])
        separate = statistics.median(seconds["separate", score])
        totals["shared"] += shared
        totals["separate"] += separate
        print(
            f"| {score} | {shared * 1e3:.1f} | {separate * 1e3:.1f} | {separate / shared:.2f} | "
            f"{shared * PAPER_POINTS:.1f} |"
        )
    nmi_enmi = statistics.median(seconds["shared", "nmi"]) + statistics.median(seconds["shared", "enmi_mass"])
    print(
        f"| all four | {totals['shared'] * 1e3:.1f} | {totals['separate'] * 1e3:.1f} | "
        f"{totals['separate'] / totals['shared']:.2f} | {totals['shared'] * PAPER_POINTS:.1f} |"
    )
    print(f"\nNMI + ENMI (mass), whole figure on one core: {nmi_enmi * PAPER_POINTS:.1f} s\n")
    print("| pixels per image | images | hard_entropies ms | entropies(joint_histogram) ms | dense / pixel-wise |")
    print("| --- | --- | --- | --- | --- |")
    generator = torch.Generator().manual_seed(1)
    for pixels in IMAGE_PIXELS:
        images = 262_144 // pixels
        captured = torch.rand(images, pixels, generator=generator) * 256
        reference = torch.rand(images, pixels, generator=generator) * 256
        timings = {"pixel-wise": [], "dense": []}
        for _ in range(args.repeats + 1):
            for way in ("pixel-wise", "dense"):
                started = time.perf_counter()
                if way == "pixel-wise":
                    hard_entropies(captured, reference)
                else:
                    entropies(joint_histogram(captured, reference))
                timings[way].append(time.perf_counter() - started)
        pixel_wise, dense = (statistics.median(timings[way][1:]) for way in ("pixel-wise", "dense"))
        print(f"| {pixels} | {images} | {pixel_wise * 1e3:.2f} | {dense * 1e3:.2f} | {dense / pixel_wise:.2f} |")


if __name__ == "__main__":
    main()
