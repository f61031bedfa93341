"""Speed of ``localize`` (the default ECR score) against globalign's whole-surface search, side by side in one process.

The anchor is globalign's per-angle core (Öfverstedt et al., "Fast computation of mutual information in the frequency
domain with applications to global multimodal image alignment", Pattern Recognition Letters 2022;
https://github.com/MIDA-group/globalign, MIT licence), reimplemented here from its ``align_rigid`` (not imported: it
is not a dependency): both images quantised into hard levels, one-hot level planes in float32, the reference's
spectra computed once for all angles; per angle the captured image's level and mask planes are transformed
(``rfft2``, conjugated), every level pair and both marginals are correlated by a full ``irfft2`` of the reference's
size, rounded, and turned into ``p log2 p`` sums, giving NMI (``H_marginals / H_joint - 1``) at every placement, then
the overlap filter and the argmax. Its rotation of the captured image is left out (``localize``'s is timed).

The case: a 128 x 128 captured image cut from scikit-image's gravel (CC0) with noise of a camera-like per-pixel
variance, 101 x 101 shifts, 32 bins, float32, one torch thread by default. Each round times every method once, in
turn; ratios are medians of per-round ratios (robust to the load bursts of a shared machine). The 36-yaw search is
timed exhaustive and two-stage (``search="two_stage"``). A floor row times ``localize`` with ECR's ``tau^2`` and
``delta^2`` given (what the default's estimates cost is the difference), another the default without its finalist
stage (``SearchStrategy(finalists=0)``): the stage's share of the call is printed.

Then the two-stage search's miss rate: how often its best candidate (yaw, shift) differs from the exhaustive search's,
over random cases: 64 x 64 captured images cut at random shifts (+-12 cells) and yaws (-6..6 degrees) from
scikit-image's gravel, brick (repetitive) and camera (CC0), seen through the identity or a non-monotonic response
(``255 |2 v / 255 - 1|^0.8``), with noise of a camera-like variance profile (16-fold range) at four levels up to an
extreme one (noise std 8 to 128 grey levels at the profile's mean), searched over +-16 cells and 7 yaws.

    python -m data_tools.benchmarks.bench_search                 # about 2 minutes on a busy 2-core CPU
    python -m data_tools.benchmarks.bench_search --rounds 9 --trials 8
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from skimage import data
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.localization.candidates import rotate_captured
from enmi_torch.localization.search import localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.scores import ECR

LOCAL, RADIUS, BINS, VALUE_RANGE = 128, 50, 32, (0.0, 256.0)
YAWS = [float(angle) for angle in range(-35, 36, 2)]
# The floor of the default's cost: ECR with its model variance tau^2 and response variance delta^2 given instead of
# estimated (no cheap first pass, no fits at its peak). The values are this case's estimates, rounded.
FIXED = {"model_variance": 6.4, "response_variance": 0.019}


def _case():
    """Map, captured image (true shift dx = -12, dy = 7, yaw 0), its variance and the prior centre."""
    generator = torch.Generator().manual_seed(0)
    gravel = torch.from_numpy(data.gravel().astype(np.float64)).reshape(1, 1, 512, 512)
    center = (256, 256)
    top, left = center[0] - LOCAL // 2 + 7, center[1] - LOCAL // 2 - 12
    rows = torch.arange(LOCAL, dtype=torch.float64)
    variance = (25.0 * (1 + 15 * ((LOCAL - 1 - rows) / (LOCAL - 1)) ** 3)).reshape(LOCAL, 1).expand(LOCAL, LOCAL)
    local = gravel[..., top : top + LOCAL, left : left + LOCAL]
    local = local + torch.randn(local.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    return gravel.float(), local.float(), variance.reshape(1, 1, LOCAL, LOCAL).float(), center


class GlobalignAngle:
    """globalign's per-angle search (NMI of hard level planes by full-size FFT correlations), reimplemented."""

    def __init__(self, window: Tensor, levels: int, overlap: float = 0.5) -> None:
        self.levels, self.overlap = levels, overlap
        self.shape = tuple(window.shape)
        reference_levels = hard_bin_index(window, levels, VALUE_RANGE)
        planes = torch.nn.functional.one_hot(reference_levels, levels).permute(2, 0, 1).float()
        self.reference_spectra = torch.fft.rfft2(planes)
        self.mask_spectrum = torch.fft.rfft2(torch.ones(self.shape))

    def _correlate(self, first: Tensor, second: Tensor, valid_shape) -> Tensor:
        return torch.fft.irfft2(first * second, s=self.shape)[..., : valid_shape[0], : valid_shape[1]].round()

    def __call__(self, captured: Tensor) -> tuple[float, tuple[int, int]]:
        """Best NMI and placement (row, col) of ``captured`` ``(h, w)`` at one angle."""
        eps = 1e-7
        height, width = captured.shape
        valid_shape = (self.shape[0] - height + 1, self.shape[1] - width + 1)
        padding = (0, self.shape[1] - width, 0, self.shape[0] - height)
        captured_levels = hard_bin_index(captured, self.levels, VALUE_RANGE)
        captured_planes = torch.nn.functional.one_hot(captured_levels, self.levels).permute(2, 0, 1).float()
        captured_spectra = torch.fft.rfft2(torch.nn.functional.pad(captured_planes, padding)).conj()
        captured_mask = torch.fft.rfft2(torch.nn.functional.pad(torch.ones(height, width), padding)).conj()
        count = self._correlate(self.mask_spectrum, captured_mask, valid_shape).clamp_min(eps)

        def entropy_terms(counts: Tensor) -> Tensor:
            probability = counts / count
            return probability * torch.log2(probability.clamp_min(eps))

        marginals = -entropy_terms(self._correlate(self.mask_spectrum, captured_spectra, valid_shape)).sum(0)
        joint = torch.zeros(valid_shape)
        for level in range(self.levels):
            reference = self.reference_spectra[level]
            marginals -= entropy_terms(self._correlate(reference, captured_mask, valid_shape))
            joint -= entropy_terms(self._correlate(reference, captured_spectra, valid_shape)).sum(0)
        score = (marginals / (joint + eps) - 1).clamp(0.0, 1.0)
        score[count < self.overlap * count.max()] = 0.0
        best = int(score.flatten().argmax())
        return float(score.flatten()[best]), divmod(best, valid_shape[1])


MISS_TEXTURES = {"gravel": data.gravel, "brick": data.brick, "camera": data.camera}
MISS_RESPONSES = {
    "identity": lambda values: values,
    "non-monotonic": lambda values: 255 * (2 * values / 255 - 1).abs() ** 0.8,
}
MISS_NOISE = (8.0, 24.0, 64.0, 128.0)
MISS_YAWS = [-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0]


def _miss_case(texture: str, response: str, noise: float, generator: torch.Generator):
    """A random captured image of ``texture`` with its variance, the map and the prior centre."""
    size, radius = 64, 16
    image = torch.from_numpy(MISS_TEXTURES[texture]().astype(np.float64))[:512, :512].reshape(1, 1, 512, 512)
    center = (256, 256)
    dy, dx = (int(value) for value in torch.randint(-12, 13, (2,), generator=generator))
    yaw = MISS_YAWS[int(torch.randint(len(MISS_YAWS), (1,), generator=generator))]
    top, left = center[0] + dy - size, center[1] + dx - size
    section = image[..., top : top + 2 * size, left : left + 2 * size]
    turned = rotate_captured(section, None, torch.ones_like(section, dtype=torch.bool), [yaw], "bilinear")[0]
    local = MISS_RESPONSES[response](turned[..., size // 2 : size // 2 + size, size // 2 : size // 2 + size])
    rows = torch.arange(size, dtype=torch.float64)
    profile = 1 + 15 * ((size - 1 - rows) / (size - 1)) ** 3
    variance = (noise**2 * profile / profile.mean()).reshape(1, 1, size, 1).expand(1, 1, size, size)
    local = local + torch.randn(local.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    return image.float(), local.float(), variance.float(), center, radius, (dx, dy, -yaw)


def miss_rate(trials: int, cheap_bins: int) -> None:
    """Print how often the two-stage search's best candidate differs from the exhaustive one's, per case."""
    generator = torch.Generator().manual_seed(0)
    cases = [(t, r, n) for t in MISS_TEXTURES for r in MISS_RESPONSES for n in MISS_NOISE]
    print("\n| texture | response | noise std | misses / trials | exhaustive found the truth | rescored (mean) |")
    print("|---|---|---|---|---|---|")
    total_misses = 0
    for index, (texture, response, noise) in enumerate(cases):
        misses = found = rescored = 0
        for _ in range(trials):
            reference, captured, variance, center, radius, truth = _miss_case(texture, response, noise, generator)
            options = {"shifts": radius, "around": center[::-1], "yaws": MISS_YAWS, "score": ECR(bins=BINS)}
            exhaustive = localize(captured, reference, variance, **options)
            two_stage = localize(
                captured, reference, variance, search=SearchStrategy("two_stage", cheap_bins=cheap_bins), **options
            )
            misses += int(exhaustive.surface.flatten().argmax()) != int(two_stage.surface.flatten().argmax())
            rescored += int(torch.isfinite(two_stage.surface).sum())
            error = (torch.cat([exhaustive.shift[0], exhaustive.yaw]) - torch.tensor(truth)).abs()
            found += bool((error[:2] <= 1).all() and error[2] <= 1)
        total_misses += misses
        print(f"| {texture} | {response} | {noise:g} | {misses} / {trials} | {found} | {rescored / trials:.0f} |")
        print(f"  case {index + 1}/{len(cases)}", end="\r", file=sys.stderr, flush=True)
    print(f"\nmisses (cheap_bins={cheap_bins}): {total_misses} of {trials * len(cases)} cases")


def _timed(function):
    start = time.perf_counter()
    result = function()
    return time.perf_counter() - start, result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--trials", type=int, default=4, help="random cases per miss-rate row (0: skip it)")
    parser.add_argument("--cheap-bins", type=int, default=4, help="bins of the two-stage search's first stage")
    parser.add_argument("--miss-only", action="store_true", help="skip the timings, measure the miss rate only")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        parser.error(f"--rounds and --threads must be >= 1, got {args.rounds} and {args.threads}")
    torch.set_num_threads(args.threads)
    if args.miss_only:
        miss_rate(args.trials, args.cheap_bins)
        return
    reference, captured, variance, center = _case()
    top, left = center[0] - LOCAL // 2 - RADIUS, center[1] - LOCAL // 2 - RADIUS
    window = reference[0, 0, top : top + LOCAL + 2 * RADIUS, left : left + LOCAL + 2 * RADIUS]
    anchor = GlobalignAngle(window, BINS)
    options = {"shifts": RADIUS, "around": center[::-1], "score": ECR(bins=BINS)}
    methods = {
        "globalign, one angle": lambda: anchor(captured[0, 0]),
        "localize, ECR, 1 yaw": lambda: localize(captured, reference, variance, **options),
        "localize, ECR, 1 yaw, no finalist stage": lambda: localize(
            captured, reference, variance, search=SearchStrategy(finalists=0), **options
        ),
        "localize, ECR with tau^2 and delta^2 given, 1 yaw": lambda: localize(
            captured, reference, variance, **{**options, "score": ECR(bins=BINS, **FIXED)}
        ),
        "localize, ECR, 36 yaws": lambda: localize(captured, reference, variance, yaws=YAWS, **options),
        "localize, ECR, 36 yaws, two-stage": lambda: localize(
            captured,
            reference,
            variance,
            yaws=YAWS,
            search=SearchStrategy("two_stage", cheap_bins=args.cheap_bins),
            **options,
        ),
    }
    results = {name: function() for name, function in methods.items()}  # warm-up
    times = {name: [] for name in methods}
    for round_index in range(args.rounds):
        for name, function in methods.items():
            seconds, results[name] = _timed(function)
            times[name].append(seconds)
        print(f"  round {round_index + 1}/{args.rounds}", end="\r", file=sys.stderr, flush=True)
    print(" " * 40, end="\r", file=sys.stderr)
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), {args.rounds} interleaved rounds, float32, {BINS} bins, "
        f"{LOCAL} x {LOCAL} captured, {2 * RADIUS + 1} x {2 * RADIUS + 1} shifts\n"
    )
    anchor_times = times["globalign, one angle"]
    print("| method | median time | globalign per angle / method (median of per-round ratios) |")
    print("|---|---|---|")
    for name, seconds in times.items():
        per_angle = len(YAWS) if "36 yaws" in name else 1
        ratios = [per_angle * anchor_time / mine for mine, anchor_time in zip(seconds, anchor_times, strict=True)]
        print(f"| {name} | {statistics.median(seconds) * 1e3:.1f} ms | {statistics.median(ratios):.2f}x |")
    score, (row, col) = results["globalign, one angle"]
    print(f"\nglobalign peak (dy, dx) = ({row - RADIUS}, {col - RADIUS}), NMI {score:.3f}; true (7, -12)")
    for name in methods:
        if name.startswith("localize"):
            found = results[name]
            shown = [round(value, 2) for value in [*found.shift[0].tolist(), float(found.yaw[0])]]
            print(f"{name}: pose (dx, dy, yaw) = {shown}")
    with_stage, without = times["localize, ECR, 1 yaw"], times["localize, ECR, 1 yaw, no finalist stage"]
    shares = [(whole - rest) / whole for whole, rest in zip(with_stage, without, strict=True)]
    share = statistics.median(shares)
    print(f"1 yaw: the finalist stage's share of the call = {share:.2f} (median of per-round shares)")
    exhaustive, two_stage = times["localize, ECR, 36 yaws"], times["localize, ECR, 36 yaws, two-stage"]
    ratios = [slow / fast for slow, fast in zip(exhaustive, two_stage, strict=True)]
    print(f"36 yaws: exhaustive / two-stage = {statistics.median(ratios):.2f}x (median of per-round ratios)")
    if args.trials > 0:
        miss_rate(args.trials, args.cheap_bins)


if __name__ == "__main__":
    main()
