"""Time per N0 point of the paper simulation's scores, three ways, against the point's kernel floor.

    python -m data_tools.benchmarks.bench_paper_simulation [--trials 10000] [--repeats 5] [--chunk-trials 96] \
        [--threads 1]

One "point" is ``trials`` trials of the paper's 66 tiles at one N0, each trial scoring the truth and the candidate
against the captured image. Three ways are timed side by side, in interleaved rounds in one process (medians over
``--repeats`` rounds, at N0 = 0.01 and 0.3), after a warm-up round that checks that all three make the same decision
on every trial:

- ``simulation``: what ``enmi_torch.simulation.error_rates`` runs: the library's scoring steps after their checks,
  on trials checked once, with the references' bins and hard entropies computed once for all points.
- ``shared``: ``count_errors``, the public ``nmi`` and ``enmi`` with both references in one call (``reference`` of
  shape ``(2, T, K)``), so ENMI computes the captured likelihood weights once, and hard NMI from ``hard_entropies``
  (pixel-wise surprisal).
- ``separate``: one call per reference, hard NMI from the dense ``(T, 32, 32)`` joint histogram
  (``nmi_from_joint_histogram(joint_histogram(...))``), as without those paths.

The floor is the elementwise work NMI + ENMI (mass) cannot avoid at one point, timed in the same rounds: one ``erf``
over the ``(T, 66, 31)`` standardised interior bin edges and one ``log`` over the ``(T, 2, 32, 32)`` joint
probabilities, each one call on whole tensors; a second floor makes the same calls in chunks of ``--chunk-trials``
trials (cache-resident, no page faults), a bound nothing but arithmetic adds to. Prints Markdown tables: ms per
point for each score and way, the ratios (medians of the per-round ratios), the whole figure's projection (141
points, one core, no workers), and NMI + ENMI (mass) against the floors. The full run's wall time is what
``data_tools/reproduce_paper.py`` prints. A last table times the hard entropies both ways at several image sizes
(262,144 pixels in all, 32 bins): read at the pixels (``hard_entropies``) and from the dense histogram
(``entropies(joint_histogram(...))``), which is why ``nmi`` reads them at the pixels only below ``bins^2 / 4`` pixels.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tqdm import tqdm

from enmi_torch import RoadCamera
from enmi_torch.binning import gaussian_log_prior
from enmi_torch.histogram import hard_entropies, joint_histogram
from enmi_torch.information import entropies, nmi_from_joint_histogram
from enmi_torch.scores.enmi import enmi
from enmi_torch.simulation import SCORES, _TrustedScorer, count_errors, draw_trials, road_tiles

PAPER_POINTS = 141
NOISE_POWERS = (0.01, 0.3)
IMAGE_PIXELS = (66, 256, 1024, 4096, 65536)
WAYS = ("simulation", "shared", "separate")
BINS = 32
VALUE_RANGE = (0.0, 256.0)


def separate_errors(captured, amplitudes, candidates, variance, score, log_prior):
    """The same decision as ``count_errors``, one library call per reference."""

    def score_against(reference):  # the trials as flat samples (T, 1, K)
        if score == "nmi":
            return nmi_from_joint_histogram(joint_histogram(captured[:, None], reference[:, None]))
        weights = "density" if score == "enmi_density" else "mass"
        return enmi(
            captured[:, None], reference[:, None], variance.reshape(1, 1, -1), kernel=weights, log_prior=log_prior
        )

    return score_against(candidates) >= score_against(amplitudes)


def time_point(way: str, score: str, trials, scorer, variance, chunk_trials: int, log_prior) -> tuple[float, int]:
    """Seconds to score one point's trials, and its error count."""
    prior = log_prior if score == "enmi_mass_prior" else None
    errors = 0
    started = time.perf_counter()
    for start in range(0, trials.amplitudes.shape[0], chunk_trials):
        part = slice(start, start + chunk_trials)
        captured = trials.captured(variance, part)
        amplitudes, candidates = trials.amplitudes[part], trials.candidates[part]
        if way == "simulation":
            wrong = scorer.errors(captured, part, variance, score)
        elif way == "shared":
            wrong = count_errors(captured, amplitudes, candidates, variance, score, log_prior=prior)
        else:
            wrong = separate_errors(captured, amplitudes, candidates, variance, score, prior)
        errors += int(wrong.sum())
    return time.perf_counter() - started, errors


def floor_call(trials, variance: torch.Tensor, chunk_trials: int | None = None):
    """The kernel floor of NMI + ENMI (mass) at one point: a callable running its erf and its log.

    ``chunk_trials``: the same two calls on chunks of that many trials (cache-resident), else on whole tensors.
    """
    captured = trials.captured(variance)
    interior = torch.linspace(*VALUE_RANGE, BINS + 1)[1:-1]
    standardized = (interior - captured.unsqueeze(-1)) * (2 * variance).rsqrt().unsqueeze(-1)
    # Joint probabilities: the log's cost does not depend on their values (none is denormal).
    probabilities = torch.rand(captured.shape[0], 2, BINS, BINS, generator=torch.Generator().manual_seed(2)) + 1e-6

    step = chunk_trials or captured.shape[0]

    def run() -> None:
        for start in range(0, captured.shape[0], step):
            torch.erf(standardized[start : start + step])
            torch.log(probabilities[start : start + step])

    return run


def median_ratio(numerators: list[float], denominators: list[float]) -> float:
    return statistics.median(a / b for a, b in zip(numerators, denominators, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--chunk-trials", type=int, default=96)
    parser.add_argument("--chunk_trials", type=int, dest="chunk_trials", help=argparse.SUPPRESS)  # the former name
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    areas = road_tiles(RoadCamera.paper()).area.float()
    trials = draw_trials(args.trials, areas.numel(), generator=torch.Generator().manual_seed(0))
    log_prior = gaussian_log_prior(128, 32, BINS, VALUE_RANGE)
    scorer = _TrustedScorer(trials, BINS, VALUE_RANGE, log_prior)
    seconds = {(way, score): [] for way in WAYS for score in SCORES}
    floor_seconds, chunked_floor_seconds = [], []
    for noise_power in NOISE_POWERS:
        variance = noise_power / areas
        floor = floor_call(trials, variance)
        chunked_floor = floor_call(trials, variance, args.chunk_trials)
        for score in SCORES:  # warm-up; the three ways must agree on every trial
            counts = {
                way: time_point(way, score, trials, scorer, variance, args.chunk_trials, log_prior)[1] for way in WAYS
            }
            if len(set(counts.values())) != 1:
                raise RuntimeError(f"{score} at N0={noise_power}: the ways disagree {counts}")
        floor()
        chunked_floor()
        for _ in tqdm(range(args.repeats), desc=f"N0 = {noise_power:g}", unit="round"):
            started = time.perf_counter()
            floor()
            floor_seconds.append(time.perf_counter() - started)
            started = time.perf_counter()
            chunked_floor()
            chunked_floor_seconds.append(time.perf_counter() - started)
            for score in SCORES:
                for way in WAYS:
                    elapsed, _ = time_point(way, score, trials, scorer, variance, args.chunk_trials, log_prior)
                    seconds[way, score].append(elapsed)

    print(
        f"\n{args.trials} trials per point, chunks of {args.chunk_trials}, {args.threads} thread(s), torch "
        f"{torch.__version__}; medians of {args.repeats} rounds x {len(NOISE_POWERS)} noise powers\n"
    )
    print(
        "| score | simulation: ms per point | shared: ms per point | separate: ms per point | shared / simulation | "
        "separate / simulation | 141 points, simulation (s) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    total = {way: [0.0] * len(floor_seconds) for way in WAYS}
    for score in SCORES:
        for way in WAYS:
            total[way] = [a + b for a, b in zip(total[way], seconds[way, score], strict=True)]
        print(_row(score, {way: seconds[way, score] for way in WAYS}))
    print(_row("all four", total))
    nmi_enmi = [a + b for a, b in zip(seconds["simulation", "nmi"], seconds["simulation", "enmi_mass"], strict=True)]
    print(f"\nNMI + ENMI (mass), whole figure on one core: {statistics.median(nmi_enmi) * PAPER_POINTS:.1f} s\n")
    print("| NMI + ENMI (mass) at one point | ms | / floor | / floor in chunks |")
    print("| --- | --- | --- | --- |")
    floor_ms, chunked_ms = (statistics.median(times) * 1e3 for times in (floor_seconds, chunked_floor_seconds))
    print(f"| floor: erf over (T, 66, 31) + log over (T, 2, 32, 32), whole tensors | {floor_ms:.1f} | 1 | |")
    print(f"| the same floor in chunks of {args.chunk_trials} trials | {chunked_ms:.1f} | | 1 |")
    for way in WAYS:
        both = [a + b for a, b in zip(seconds[way, "nmi"], seconds[way, "enmi_mass"], strict=True)]
        print(
            f"| {way} | {statistics.median(both) * 1e3:.1f} | {median_ratio(both, floor_seconds):.2f} | "
            f"{median_ratio(both, chunked_floor_seconds):.2f} |"
        )

    print("\n| pixels per image | images | hard_entropies ms | entropies(joint_histogram) ms | dense / pixel-wise |")
    print("| --- | --- | --- | --- | --- |")
    generator = torch.Generator().manual_seed(1)
    for pixels in IMAGE_PIXELS:
        images = 262_144 // pixels
        captured = torch.rand(images, 1, pixels, generator=generator) * 256  # flat samples (B, 1, N)
        reference = torch.rand(images, 1, pixels, generator=generator) * 256
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


def _row(name: str, seconds: dict[str, list[float]]) -> str:
    simulation = seconds["simulation"]
    cells = [f"{statistics.median(seconds[way]) * 1e3:.1f}" for way in WAYS]
    ratios = [f"{median_ratio(seconds[way], simulation):.2f}" for way in ("shared", "separate")]
    projection = f"{statistics.median(simulation) * PAPER_POINTS:.1f}"
    return "| " + " | ".join([name, *cells, *ratios, projection]) + " |"


if __name__ == "__main__":
    main()
