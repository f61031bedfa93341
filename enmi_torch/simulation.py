"""The paper's simulation (section "Simulated Performance"): probability of a wrong match against noise power.

A captured road section is ``K`` square tiles of amplitudes ``a_k ~ N(mean, std^2)``, seen through the road camera:
tile ``k`` covers the focal-plane area ``A~_k`` (eq. TildeA), so its area-normalised amplitude carries noise of
variance ``N0 / A~_k`` (``V = a + N``). A candidate map section ``u`` is an independent draw of the same law. A
score makes an error when ``score(V, u) >= score(V, a)``; the error rate is estimated over many trials.

Convention:
    Trials are ``(T, K)`` tensors, one row per trial, so the scores run batched over trials with the library's
    own :func:`~enmi_torch.functional.nmi` and :func:`~enmi_torch.functional.enmi`, the truth and the candidate
    scored as two references of one call (``(2, T, K)``: the captured weights are computed once).
    :func:`error_rates` checks its trials once and runs the steps of those functions after their checks, with the
    same scores bit for bit as :func:`count_errors`. Every noise
    power reuses the same amplitudes, candidates and standard normal noise (common random numbers): each point is
    an unbiased estimate from its ``trials`` trials, the curves are smooth in ``N0``, and a point's value does not
    depend on which other points are simulated.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import torch
from torch import Tensor

from enmi_torch.binning import gaussian_log_prior, hard_bin_index
from enmi_torch.geometry.camera import RoadCamera, projected_area
from enmi_torch.histogram import likelihood_counts, mean_surprisal
from enmi_torch.information import entropies, nmi_from_entropies
from enmi_torch.scores.enmi import enmi
from enmi_torch.scores.nmi import nmi
from enmi_torch.utils.checks import (
    check_bins,
    check_option,
    check_positive_int,
    check_positive_number,
    check_value_range,
)

__all__ = [
    "PAPER_ROW_COUNTS",
    "SCORES",
    "ErrorRates",
    "RoadTiles",
    "Trials",
    "count_errors",
    "draw_trials",
    "error_rates",
    "road_tiles",
]

PAPER_ROW_COUNTS = (5, 5, 7, 7, 9, 9, 11, 13)
"""Tiles per row of the paper's Fig. SimRoadImage, nearest row first (66 tiles)."""

SCORES = ("nmi", "enmi_mass", "enmi_density", "enmi_mass_prior")
"""Scores the simulation compares: hard NMI and ENMI with mass, density and mass-with-amplitude-prior weights."""


@dataclass(frozen=True)
class RoadTiles:
    """Square road tiles in rows across the road and their focal-plane areas, ``(K,)`` each, nearest row first.

    Attributes:
        lateral_low: left edge ``x_l`` of each tile.
        lateral_high: right edge ``x_u``.
        distance_near: near edge ``d`` (horizontal distance ahead of the camera).
        distance_far: far edge.
        row: row index of each tile, 0 for the nearest.
        area: focal-plane area ``A~`` of each tile (:func:`~enmi_torch.geometry.camera.projected_area`).
    """

    lateral_low: Tensor
    lateral_high: Tensor
    distance_near: Tensor
    distance_far: Tensor
    row: Tensor
    area: Tensor


def road_tiles(
    camera: RoadCamera,
    row_counts: Sequence[int] = PAPER_ROW_COUNTS,
    tile_size: float = 20.0,
    nearest_distance: float = 40.0,
    *,
    dtype: torch.dtype = torch.float64,
) -> RoadTiles:
    """The tiles of the paper's simulated road image: rows of ``row_counts`` tiles, centred across the road.

    Row ``r`` spans distances ``[nearest + r s, nearest + (r + 1) s]`` (``s = tile_size``) and its ``n`` tiles span
    ``[-n s / 2, n s / 2]`` laterally, so an odd row has a centre tile ``[-s/2, s/2]``. The paper's defaults give
    66 tiles from 40 cm to 200 cm, the range its camera's vertical view covers.

    Args:
        camera: the road camera (:meth:`~enmi_torch.geometry.camera.RoadCamera.paper` for the paper's).
        row_counts: tiles per row, nearest row first, each >= 1.
        tile_size: side of a tile, in the camera's length unit (> 0).
        nearest_distance: road distance of the nearest row's near edge (> 0).
        dtype: floating dtype of the returned tensors.

    Example:
        >>> from enmi_torch.geometry.camera import RoadCamera
        >>> tiles = road_tiles(RoadCamera.paper())
        >>> tiles.area.numel(), f"{tiles.area.max():.2e}", f"{tiles.area.min():.2e}"
        (66, '7.72e-05', '4.74e-06')
    """
    if not isinstance(camera, RoadCamera):
        raise TypeError(f"camera must be an enmi_torch.geometry.camera.RoadCamera, got {type(camera).__name__}")
    counts = list(row_counts)
    if not counts or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in counts):
        raise ValueError(f"row_counts must be a non-empty sequence of ints >= 1, got {row_counts!r}")
    size = check_positive_number("tile_size", tile_size)
    nearest = check_positive_number("nearest_distance", nearest_distance)
    row = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    per_row = torch.tensor(counts, dtype=dtype)[row]
    position = torch.cat([torch.arange(n, dtype=dtype) for n in counts])
    lateral_low = (position - per_row / 2) * size
    distance_near = nearest + row.to(dtype) * size
    area = projected_area(camera, lateral_low, lateral_low + size, distance_near, distance_near + size).to(dtype)
    return RoadTiles(lateral_low, lateral_low + size, distance_near, distance_near + size, row, area)


@dataclass(frozen=True)
class Trials:
    """Simulated trials, ``(T, K)`` each: true amplitudes, an independent candidate, and standard normal noise."""

    amplitudes: Tensor
    candidates: Tensor
    standard_noise: Tensor

    def captured(self, variance: Tensor, part: slice = slice(None)) -> Tensor:
        """The noisy captured amplitudes ``V = a + sqrt(variance) z`` of trials ``part``, per-tile ``variance`` (K,)."""
        return self.amplitudes[part] + variance.sqrt() * self.standard_noise[part]


def draw_trials(
    trials: int,
    tiles: int,
    *,
    generator: torch.Generator,
    amplitude_mean: float = 128.0,
    amplitude_std: float = 32.0,
    dtype: torch.dtype = torch.float32,
) -> Trials:
    """Draw ``trials`` rows of ``tiles`` amplitudes ``N(mean, std^2)``, candidates of the same law, and noise.

    The draws come in that order from ``generator``, each ``(trials, tiles)`` at once, so the same seed gives the
    same trials whatever the later chunking.

    Example:
        >>> trials = draw_trials(3, 66, generator=torch.Generator().manual_seed(0))
        >>> tuple(trials.amplitudes.shape), trials.candidates.dtype
        ((3, 66), torch.float32)
    """
    check_positive_int("trials", trials)
    check_positive_int("tiles", tiles)
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    std = check_positive_number("amplitude_std", amplitude_std)

    def normal() -> Tensor:
        return torch.randn(trials, tiles, generator=generator, dtype=dtype)

    amplitudes = amplitude_mean + std * normal()
    candidates = amplitude_mean + std * normal()
    return Trials(amplitudes, candidates, normal())


def count_errors(
    captured: Tensor,
    amplitudes: Tensor,
    candidates: Tensor,
    variance: Tensor,
    score: str,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    log_prior: Tensor | None = None,
) -> Tensor:
    """Which trials ``score`` gets wrong, ``(T,)`` bool: ``score(V, u) >= score(V, a)`` (ties count as errors).

    Args:
        captured: noisy amplitudes ``V`` ``(T, K)``.
        amplitudes: true amplitudes ``a`` ``(T, K)``.
        candidates: candidate amplitudes ``u`` ``(T, K)``.
        variance: per-tile noise variance ``(K,)`` or ``(1, K)``, used by the ENMI scores.
        score: one of :data:`SCORES`.
        bins: number of bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        log_prior: log prior of the amplitudes per bin for ``"enmi_mass_prior"`` (required there, refused by the
            others).

    Example:
        A constant candidate loses; a permutation of the amplitudes ties with them under hard bins (an error):

        >>> amplitudes = torch.tensor([[10.0, 100.0, 200.0, 250.0]]).expand(2, 4)
        >>> candidates = torch.stack([torch.full((4,), 100.0), amplitudes[0].flip(0)])
        >>> count_errors(amplitudes + 1.0, amplitudes, candidates, torch.ones(4), "nmi").tolist()
        [False, True]
    """
    check_option("score", score, SCORES)
    if (score == "enmi_mass_prior") != (log_prior is not None):
        raise ValueError(
            f"log_prior must be given for score 'enmi_mass_prior' only, got score={score!r} and log_prior "
            f"{'None' if log_prior is None else 'a tensor'}"
        )
    # The trials as flat samples (T, 1, K): one row of K tiles each.
    captured, references = captured[:, None], torch.stack([amplitudes, candidates])[:, :, None]
    if score == "nmi":
        values = nmi(captured, references, bins=bins, value_range=value_range, kernel="hard")
    else:
        kernel = "density" if score == "enmi_density" else "mass"
        variance = variance.reshape(1, 1, -1)
        values = enmi(
            captured, references, variance, bins=bins, value_range=value_range, kernel=kernel, log_prior=log_prior
        )
    return values[1] >= values[0]


class _TrustedScorer:
    """:func:`count_errors` for trials that :func:`error_rates` drew and checked: the same scores, bit for bit.

    It calls the steps :func:`~enmi_torch.functional.nmi` and :func:`~enmi_torch.functional.enmi` take after
    their checks, and computes once what does not depend on the noise power: the references' bins and hard
    entropies. A test checks every decision against :func:`count_errors`.
    """

    def __init__(self, trials: Trials, bins: int, value_range: tuple[float, float], log_prior: Tensor) -> None:
        self.bins, self.value_range = bins, value_range
        self.log_prior = log_prior.reshape(1, 1, bins)
        references = torch.stack([trials.amplitudes, trials.candidates])
        self.reference_bins = hard_bin_index(references, bins, value_range)
        self.ones = references.new_ones(references.shape[1:])
        self.reference_entropy = mean_surprisal(self.reference_bins, bins, self.ones)

    def errors(self, captured: Tensor, part: slice, variance: Tensor, score: str) -> Tensor:
        """Which trials of ``part`` ``score`` gets wrong, ``(T,)`` bool, for their captured values ``(T, K)``."""
        values = self.scores(captured, part, variance, score)
        return values[1] >= values[0]

    def scores(self, captured: Tensor, part: slice, variance: Tensor, score: str) -> Tensor:
        """``score`` of the captured values ``(T, K)`` of trials ``part`` against (truth, candidate), ``(2, T)``."""
        reference_bins = self.reference_bins[:, part]
        if score == "nmi":
            weight = self.ones[part]
            captured_bins = hard_bin_index(captured, self.bins, self.value_range)
            captured_entropy = mean_surprisal(captured_bins, self.bins, weight).expand(reference_bins.shape[:-1])
            joint_entropy = mean_surprisal(captured_bins * self.bins + reference_bins, self.bins**2, weight)
            return nmi_from_entropies(captured_entropy, self.reference_entropy[:, part], joint_entropy)
        batch = captured.shape[0]
        offsets = torch.arange(2 * batch, device=captured.device).view(2, batch, 1) * self.bins
        transposed = likelihood_counts(
            captured,
            variance.reshape(1, -1).expand(captured.shape),
            reference_bins + offsets,
            self.log_prior if score == "enmi_mass_prior" else None,
            self.bins,
            self.value_range,
            "density" if score == "enmi_density" else "mass",
            normalized_later=True,
        )
        counts = transposed[:-1].view(2, batch, self.bins, self.bins).transpose(-1, -2)
        return nmi_from_entropies(*entropies(counts))


@dataclass
class ErrorRates:
    """Result of :func:`error_rates`: one error rate per score and noise power, and where the time went.

    Attributes:
        noise_powers: ``(P,)`` float64, the ``N0`` values.
        rates: score name to ``(P,)`` float64 error rates.
        trials: trials per point.
        seconds: score name to the seconds its scoring took over all points (summed over workers).
    """

    noise_powers: Tensor
    rates: dict[str, Tensor]
    trials: int
    seconds: dict[str, float] = field(default_factory=dict)

    def standard_error(self, score: str) -> Tensor:
        """Binomial standard error ``sqrt(p (1 - p) / trials)`` of each rate of ``score``, ``(P,)``."""
        rate = self.rates[score]
        return (rate * (1 - rate) / self.trials).sqrt()


def error_rates(
    areas: Tensor,
    noise_powers: Sequence[float] | Tensor,
    *,
    trials: int = 10_000,
    scores: Sequence[str] = SCORES,
    seed: int = 0,
    amplitude_mean: float = 128.0,
    amplitude_std: float = 32.0,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    chunk_trials: int = 96,
    dtype: torch.dtype = torch.float32,
    workers: int = 1,
    progress: Callable[[int, dict[str, float], float], None] | None = None,
) -> ErrorRates:
    """Probability of error of each score at each noise power ``N0``: the paper's Fig. simPerformance.

    Args:
        areas: focal-plane area ``A~_k`` of each tile, ``(K,)`` (e.g. ``road_tiles(camera).area``), > 0.
        noise_powers: the ``N0`` values, each > 0; tile ``k`` gets noise variance ``N0 / A~_k``.
        trials: trials per noise power.
        scores: which of :data:`SCORES` to run; all see the same trials.
        seed: seed of the ``torch.Generator`` the trials come from.
        amplitude_mean: mean of the amplitudes.
        amplitude_std: their standard deviation; ``"enmi_mass_prior"`` uses this law, binned, as its prior.
        bins: number of bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        chunk_trials: trials scored per call: small enough for the ``(2, chunk, bins, bins)`` histograms to stay in
            cache, large enough to amortise the per-call overhead.
        dtype: ``torch.float32`` (fast) or ``torch.float64``.
        workers: points scored at once by a pool of Python threads (PyTorch releases the GIL inside its
            kernels). With ``torch.set_num_threads(1)`` this parallelises without the barriers of intra-op
            threads, which stall when the machine's cores are shared. The results do not depend on it.
        progress: called after each point, in order, with its index, its error rates and the seconds it took.

    Returns:
        The :class:`ErrorRates`.

    Example:
        >>> from enmi_torch.geometry.camera import RoadCamera
        >>> areas = road_tiles(RoadCamera.paper()).area
        >>> result = error_rates(areas, [0.0005, 0.05], trials=200, scores=["nmi", "enmi_mass"])
        >>> result.rates["nmi"].tolist(), result.rates["enmi_mass"].tolist()
        ([0.0, 0.44], [0.0, 0.21])
    """
    if not isinstance(areas, Tensor) or areas.ndim != 1 or areas.numel() == 0:
        raise ValueError(f"areas must be a non-empty (K,) tensor, got {getattr(areas, 'shape', type(areas).__name__)}")
    if not bool(torch.isfinite(areas).all() & (areas > 0).all()):
        raise ValueError("areas must be finite and > 0")
    noise = torch.as_tensor(noise_powers, dtype=torch.float64).flatten()
    if noise.numel() == 0 or not bool(torch.isfinite(noise).all() & (noise > 0).all()):
        raise ValueError(f"noise_powers must be a non-empty sequence of finite numbers > 0, got {noise_powers!r}")
    for score in scores:
        check_option("score", score, SCORES)
    check_positive_int("chunk_trials", chunk_trials)
    check_positive_int("workers", workers)
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    bins = check_bins(bins)
    value_range = check_value_range(value_range)

    drawn = draw_trials(
        trials,
        areas.numel(),
        generator=torch.Generator().manual_seed(seed),
        amplitude_mean=amplitude_mean,
        amplitude_std=amplitude_std,
        dtype=dtype,
    )
    log_prior = gaussian_log_prior(amplitude_mean, amplitude_std, bins, value_range, dtype=dtype)
    areas = areas.to(dtype)

    scorer = _TrustedScorer(drawn, bins, value_range, log_prior)

    def run_point(noise_power: float) -> tuple[dict[str, int], dict[str, float], float]:
        started = time.perf_counter()
        variance = noise_power / areas
        errors, seconds = dict.fromkeys(scores, 0), dict.fromkeys(scores, 0.0)
        for start in range(0, trials, chunk_trials):
            part = slice(start, start + chunk_trials)
            captured = drawn.captured(variance, part)
            for score in scores:
                tic = time.perf_counter()
                errors[score] += int(scorer.errors(captured, part, variance, score).sum())
                seconds[score] += time.perf_counter() - tic
        return errors, seconds, time.perf_counter() - started

    counts = {score: torch.zeros(noise.numel(), dtype=torch.int64) for score in scores}
    seconds = dict.fromkeys(scores, 0.0)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for point, (point_errors, point_seconds, elapsed) in enumerate(pool.map(run_point, noise.tolist())):
            for score in scores:
                counts[score][point] = point_errors[score]
                seconds[score] += point_seconds[score]
            if progress is not None:
                progress(point, {score: point_errors[score] / trials for score in scores}, elapsed)
    rates = {score: count.to(torch.float64) / trials for score, count in counts.items()}
    return ErrorRates(noise, rates, trials, seconds)
