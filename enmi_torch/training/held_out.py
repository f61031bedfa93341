"""The fit-mask command's held-out comparison: its methods, its noise levels read from the data, its searches.

Each held-out pair is searched by :func:`~enmi_torch.localize`, as a user searches (the library's default score
``ECR()`` with its finalist stage, and the controls), at noise levels read from the held-out pairs themselves
(:func:`calibrate_levels`): the residual ``local - prior`` amplified by a factor ``k`` (the variance by ``k^2``),
clipped to ``value_range`` as a sensor saturates. The method names below are those of the console table,
``summary.json`` and the dashboards' tags (``localization/<set>/<method>``), in this order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.localization import localize
from enmi_torch.scores import Score

# The methods of the comparison, the library's default score first, and what each name means: ``<score>_<variance>``.
METHOD_MEANINGS = {
    "ecr_learned": "ECR(), the library's default score (localize's, finalist stage included), with the learned mask",
    "ecr_true": "ECR() with the true variance (where the pairs name it: synthetic ones, meta.json truth)",
    "ecr_uniform": "ECR() with one uniform variance, the learned mask's mean",
    "ecr_best_uniform": "ECR() with the best uniform variance of a grid (an oracle: picked on these pairs)",
    "enmi_learned": "ENMI, the paper's score, with the learned mask",
    "enmi_true": "ENMI with the true variance",
    "enmi_uniform": "ENMI with one uniform variance, the learned mask's mean",
    "enmi_best_uniform": "ENMI with the best uniform variance of the grid (an oracle)",
    "nmi": "NMI (hard bins, no variance): a control",
    "ncc": "NCC (no variance): a control",
}
# The lines that answer "with the default score, does the learned mask beat a uniform variance (and ENMI)?".
ANSWER_METHODS = ("ecr_learned", "ecr_true", "ecr_uniform", "ecr_best_uniform", "enmi_best_uniform")
# The best-uniform controls, each the best of its score's uniform grid (``<score>_uniform_x<factor>``).
BEST_UNIFORM = {"ecr_best_uniform": "ecr_uniform", "enmi_best_uniform": "enmi_uniform"}
# Paired differences reported per held-out set: the default score's learned mask against its controls and ENMI's best.
PAIRED = (
    ("ecr_learned", "ecr_uniform"),
    ("ecr_learned", "ecr_best_uniform"),
    ("ecr_learned", "ecr_true"),
    ("ecr_learned", "enmi_best_uniform"),
    ("enmi_learned", "enmi_uniform"),
)

# The held-out sets read from the data: the hardest level where the best method still finds half the pairs, and one
# easier level, a quarter of it (the yardstick's L50 and L50 / 4).
LEVEL_EASY, LEVEL_HARD = "level_easy", "level_hard"
EASY_FRACTION = 0.25
TARGET = 0.5
# The calibration ladder: from x1 (the pairs as they are) doubling up while the best method finds half the pairs,
# halving down while it does not, within these factors.
LADDER_LOWEST, LADDER_HIGHEST = 1 / 8, 256.0
# Held-out pairs the calibration searches at each level of its ladder (the first ones).
CALIBRATION_PAIRS = 32


def held_out_order(names) -> list[str]:
    """Held-out set names, easiest first: ``level_easy``, ``level_hard``; ``noise_x<k>`` by ``k``; others by name."""

    def key(name: str) -> tuple[int, float, str]:
        if name in (LEVEL_EASY, LEVEL_HARD):
            return 1, float(name == LEVEL_HARD), name
        factor = name.rsplit("_x", 1)[-1] if "_x" in name else ""
        try:
            return 1, float(factor), name
        except ValueError:
            return 0, 0.0, name

    return sorted(names, key=key)


def amplified(local: Tensor, prior: Tensor, factor: float, value_range: Sequence[float]) -> Tensor:
    """``prior + factor (local - prior)`` clipped to ``value_range`` (a sensor saturates); ``local`` as it is at 1."""
    if factor == 1:
        return local
    return (prior + factor * (local - prior)).clamp(float(value_range[0]), float(value_range[1]))


class Trial(NamedTuple):
    """One method's outcome on each held-out pair.

    Attributes:
        located: ``(B,)`` bool, the placement :func:`~enmi_torch.localize` chose (its finalist stage's, where it
            has one) within one pixel of the truth (the zero shift) on both axes.
        margin: ``(B,)`` float64, the z-score of the zero shift's surface value among the shifts more than one pixel
            away (NaN where none is, or where a pair holds one value and cannot be searched).
    """

    located: Tensor
    margin: Tensor


def _search(score: Score, crop: Tensor, window: Tensor, variance, crop_valid: Tensor, max_shift: int) -> Trial:
    """Localize each crop in its window (the zero shift is the truth); pairs holding one value count as missed."""
    batch = crop.shape[0]
    located = torch.zeros(batch, dtype=torch.bool, device=crop.device)
    margin = torch.full((batch,), math.nan, dtype=torch.float64, device=crop.device)
    values = crop.flatten(1)
    keep = crop_valid.flatten(1)
    large = torch.finfo(values.dtype).max
    flat = torch.where(keep, values, -large).amax(1) <= torch.where(keep, values, large).amin(1)
    searched = (~flat).nonzero()[:, 0]  # a flat crop scores alike everywhere: nothing to find
    if len(searched) == 0:
        return Trial(located, margin)
    if isinstance(variance, Tensor) and variance.ndim == 4 and variance.shape[0] == batch:
        variance = variance[searched]
    found = localize(
        crop[searched], window[searched], variance, score=score, shifts=max_shift, captured_mask=crop_valid[searched]
    )
    surface = found.surface[:, 0].double()
    span = 2 * max_shift + 1
    if found.finalists is not None:  # the candidate localize chose: its finalist stage's, else the surface's best
        chosen = found.finalists.best()[:, 1:]
    else:
        peak = surface.flatten(1).argmax(1)
        chosen = torch.stack([peak // span, peak % span], 1)
    located[searched] = ((chosen - max_shift).abs() <= 1).all(1)
    offsets = torch.arange(span, device=crop.device) - max_shift
    far = (offsets.abs().view(-1, 1) > 1) | (offsets.abs().view(1, -1) > 1)
    others = surface[:, far]
    if others.shape[1] >= 2:  # max_shift 1 leaves no shift farther than a pixel: no margin to measure
        finite = torch.isfinite(others)
        count = finite.sum(1)
        mean = torch.where(finite, others, 0.0).sum(1) / count.clamp_min(1)
        spread = (torch.where(finite, others - mean[:, None], 0.0).square().sum(1) / (count - 1).clamp_min(1)).sqrt()
        margin[searched] = torch.where(
            count >= 2, (surface[:, max_shift, max_shift] - mean) / spread.clamp_min(1e-12), math.nan
        )
    return Trial(located, margin)


def localization_trials(
    local: Tensor,
    prior: Tensor,
    valid: Tensor,
    variances: Mapping[str, Tensor | float],
    *,
    max_shift: int,
    scores: Sequence[Score],
    uniform_grid: Sequence[float] = (),
) -> dict[str, Trial]:
    """Whole-image localization of aligned pairs with :func:`~enmi_torch.localize`, the yardstick's protocol.

    Each pair's local image, less a border of ``max_shift`` pixels, is searched in its prior image at every shift in
    ``[-max_shift, max_shift]^2`` by :func:`~enmi_torch.localize` with each score (ECR's finalist stage included:
    what a user gets); the pair is located when the placement it chose (before the sub-pixel fit) is within one pixel
    of the zero shift on both axes, as ``data_tools/experiments/yardstick/scene_change.py`` counts.

    Args:
        local: ``(B, 1, H, W)``.
        prior: ``(B, 1, H, W)``, aligned with ``local``.
        valid: bool ``(B, 1, H, W)``, pixels usable by every method.
        variances: name -> ``(H, W)`` variance map or a number (one uniform variance); each score that uses a
            variance is searched with each (methods ``"<score name>_<variance name>"``, e.g. ``"ecr_learned"``).
        max_shift: largest shift in pixels.
        scores: the scores searched (e.g. ``ECR(bins=32)``, ``ENMI(bins=32)``, ``NMI(bins=32)``, ``NCC()``); those
            without a variance once each (method ``"<score name>"``).
        uniform_grid: factors of the variance named ``"uniform"`` that each score using a variance is also searched
            with (``"<score name>_uniform_x<factor>"``): the grid of the best-uniform controls.

    Returns:
        Method -> :class:`Trial` (per pair: located or not, and the margin).
    """
    height, width = local.shape[-2:]
    inner = (..., slice(max_shift, height - max_shift), slice(max_shift, width - max_shift))
    crop, crop_valid = local[inner].float(), valid[inner]
    window = prior.float()
    results = {}
    for name, variance in variances.items():
        if isinstance(variance, Tensor):
            variance = variance[inner].float()
        factors = [1.0, *uniform_grid] if name == "uniform" else [1.0]
        for score in scores:
            if not score.uses_variance:
                continue
            for factor in factors:
                method = f"{score.name}_{name}" if factor == 1 else f"{score.name}_uniform_x{factor:g}"
                results[method] = _search(score, crop, window, variance * factor, crop_valid, max_shift)
    for score in scores:
        if not score.uses_variance:
            results[score.name] = _search(score, crop, window, None, crop_valid, max_shift)
    return results


def trial_methods(
    scores: Sequence[Score], variance_names: Sequence[str], uniform_grid: Sequence[float] = ()
) -> list[str]:
    """The methods :func:`localization_trials` returns, in its order (``variance_names``: its ``variances``' keys)."""
    methods = []
    for name in variance_names:
        factors = [1.0, *uniform_grid] if name == "uniform" else [1.0]
        for score in scores:
            if score.uses_variance:
                methods += [
                    f"{score.name}_{name}" if factor == 1 else f"{score.name}_uniform_x{factor:g}" for factor in factors
                ]
    return methods + [score.name for score in scores if not score.uses_variance]


class LevelCalibration(NamedTuple):
    """The levels read from the held-out pairs (:func:`calibrate_levels`).

    Attributes:
        factors: the amplification factors tried, ascending.
        rates: method -> share of the pairs located at each factor of ``factors``.
        best: the best method's share at each factor.
        hard: ``L50``: the factor where the best method's share falls to one half, interpolated in ``log factor``
            between the ladder's last level at or above one half and the next (2 significant digits).
        easy: ``hard`` times :data:`EASY_FRACTION`.
        bracketed: ``"yes"``; ``"below"`` when even :data:`LADDER_LOWEST` is below one half (``hard`` is that factor),
            ``"above"`` when even :data:`LADDER_HIGHEST` is at or above it (``hard`` is that one).
        pairs: the held-out pairs searched at each level.
    """

    factors: list[float]
    rates: dict[str, list[float]]
    best: list[float]
    hard: float
    easy: float
    bracketed: str
    pairs: int

    def levels(self) -> dict[str, float]:
        """``{"level_easy": easy, "level_hard": hard}``: the held-out sets' factors."""
        return {LEVEL_EASY: self.easy, LEVEL_HARD: self.hard}

    def leaders(self) -> list[str]:
        """The best method at each factor (the first of :data:`METHOD_MEANINGS`'s order among ties)."""
        order = [method for method in METHOD_MEANINGS if method in self.rates]
        order += sorted(set(self.rates) - set(order))
        return [max(order, key=lambda method: self.rates[method][index]) for index in range(len(self.factors))]


def _significant(value: float) -> float:
    return float(f"{value:.2g}")


def calibrate_levels(
    rates_at: Callable[[float], Mapping[str, float]],
    pairs: int,
    *,
    target: float = TARGET,
    lowest: float = LADDER_LOWEST,
    highest: float = LADDER_HIGHEST,
) -> LevelCalibration:
    """Read the held-out levels from the data: a ladder of amplification factors around x1.

    From x1 (the pairs as they are) the factor doubles while the best method locates at least ``target`` of the pairs
    (up to ``highest``), or halves while it does not (down to ``lowest``); the hard level is where the best share
    crosses ``target``, interpolated linearly in ``log factor`` between the two levels that bracket it (as
    ``data_tools/experiments/yardstick/scene_change.py``'s ``calibrate`` reads ``L50``); the easy level a quarter of it.

    Args:
        rates_at: factor -> method -> share of the ``pairs`` held-out pairs located at that factor.
        pairs: the pairs ``rates_at`` searches (for the record).
        target: the share the hard level is read at.
        lowest: the smallest factor tried.
        highest: the largest factor tried.

    Example:
        >>> shares = {1.0: 1.0, 2.0: 0.75, 4.0: 0.25}  # the best method's share at each factor
        >>> calibration = calibrate_levels(lambda factor: {"ncc": shares[factor]}, 4)
        >>> calibration.factors, calibration.hard, calibration.easy  # 2 * 2 ** ((0.75 - 0.5) / (0.75 - 0.25))
        ([1.0, 2.0, 4.0], 2.8, 0.7)
    """
    tried: dict[float, Mapping[str, float]] = {}

    def best(factor: float) -> float:
        if factor not in tried:
            tried[factor] = dict(rates_at(factor))
        return max(tried[factor].values())

    factor, bracketed = 1.0, "yes"
    if best(factor) >= target:
        while factor < highest and best(factor * 2) >= target:
            factor *= 2
        if factor >= highest:
            bracketed = "above"
        low, high = factor, factor * 2
    else:
        while factor > lowest and best(factor / 2) < target:
            factor /= 2
        if factor <= lowest:
            bracketed = "below"
        low, high = factor / 2, factor
    hard = factor  # the end of the ladder, where the crossing is not bracketed
    if bracketed == "yes":
        above, below = best(low), best(high)
        fraction = (above - target) / (above - below)
        hard = _significant(math.exp(math.log(low) + fraction * (math.log(high) - math.log(low))))
    factors = sorted(tried)
    methods = list(tried[factors[0]])
    rates = {method: [float(tried[level][method]) for level in factors] for method in methods}
    best_rates = [max(tried[level].values()) for level in factors]
    return LevelCalibration(factors, rates, best_rates, hard, _significant(hard * EASY_FRACTION), bracketed, pairs)


def paired_difference(first: Tensor, second: Tensor) -> tuple[float, float]:
    """Mean and standard error of ``first - second`` over paired outcomes (``(N,)`` 0/1); SE 0 for one pair."""
    difference = first.double() - second.double()
    count = difference.numel()
    error = float(difference.std() / math.sqrt(count)) if count > 1 else 0.0
    return float(difference.mean()), error


class HeldOutTally:
    """Every method's outcome on every held-out pair of one validation, by the pair's index in the held-out set.

    Each process adds the pairs it searched (:meth:`add`); :meth:`reduce` sums the processes' tallies (each pair is
    searched by one process), so that the shares and the paired differences are those of all the pairs searched.

    Args:
        pairs: the held-out set's size (indices run below it).
        names: every ``"<set>/<method>"`` the processes will add (the same on each, so that their tallies sum).
    """

    def __init__(self, pairs: int, names: Sequence[str] = ()) -> None:
        self.pairs = pairs
        self.located = {name: torch.zeros(pairs, dtype=torch.float64) for name in names}
        self.margin_sums = {name: torch.zeros(pairs, dtype=torch.float64) for name in names}
        self.margin_counts = {name: torch.zeros(pairs, dtype=torch.float64) for name in names}
        self.searched = torch.zeros(pairs, dtype=torch.float64)

    def add(self, held_out: str, results: Mapping[str, Trial], index: Tensor) -> None:
        """Record ``results`` (method -> :class:`Trial`) of held-out set ``held_out`` at the pairs ``index``."""
        index = index.cpu()
        self.searched[index] = 1.0
        for method, trial in results.items():
            name = f"{held_out}/{method}"
            for store in (self.located, self.margin_sums, self.margin_counts):
                store.setdefault(name, torch.zeros(self.pairs, dtype=torch.float64))
            margin = trial.margin.cpu()
            finite = torch.isfinite(margin)
            self.located[name][index] = trial.located.cpu().double()
            self.margin_sums[name][index] = torch.where(finite, margin, 0.0)
            self.margin_counts[name][index] = finite.double()

    def reduce(self, reduce_sum: Callable[[Tensor], Tensor]) -> HeldOutTally:
        """The tally of every process: ``reduce_sum`` sums a tensor over them (the identity for one process)."""
        names = sorted(self.located)
        stacked = torch.stack(
            [self.searched]
            + [self.located[name] for name in names]
            + [self.margin_sums[name] for name in names]
            + [self.margin_counts[name] for name in names]
        )
        stacked = reduce_sum(stacked).cpu()
        total = HeldOutTally(self.pairs, names)
        total.searched = stacked[0]
        count = len(names)
        for position, name in enumerate(names, 1):
            total.located[name] = stacked[position]
            total.margin_sums[name] = stacked[position + count]
            total.margin_counts[name] = stacked[position + 2 * count]
        return total

    def summary(self) -> HeldOutSummary:
        """Shares, mean margins and paired differences, with the best-uniform controls picked per held-out set."""
        searched = self.searched > 0
        pairs = int(searched.sum())
        if pairs == 0:
            return HeldOutSummary(0, {}, {}, {})
        outcomes = {name: located[searched] for name, located in self.located.items()}
        rates = {name: float(located.mean()) for name, located in outcomes.items()}
        margins = {
            name: float(self.margin_sums[name].sum() / count) if (count := self.margin_counts[name].sum()) else math.nan
            for name in outcomes
        }
        for held_out in sorted({name.split("/")[0] for name in outcomes}):
            for best, prefix in BEST_UNIFORM.items():
                group = [name for name in sorted(outcomes) if name.startswith(f"{held_out}/{prefix}")]
                if group:
                    chosen = max(group, key=lambda name: (rates[name], margins[name]))
                    key = f"{held_out}/{best}"
                    rates[key], margins[key], outcomes[key] = rates[chosen], margins[chosen], outcomes[chosen]
        paired: dict[str, dict[str, tuple[float, float]]] = {}
        for name in outcomes:
            held_out, method = name.split("/")
            for first, second in PAIRED:
                if method == first and f"{held_out}/{second}" in outcomes:
                    difference = paired_difference(outcomes[name], outcomes[f"{held_out}/{second}"])
                    paired.setdefault(held_out, {})[f"{first} - {second}"] = difference
        shown = {name for name in rates if name.split("/")[1] in METHOD_MEANINGS}
        return HeldOutSummary(
            pairs,
            {name: rates[name] for name in sorted(shown)},
            {name: margins[name] for name in sorted(shown)},
            paired,
        )


class HeldOutSummary(NamedTuple):
    """One validation's held-out comparison (:meth:`HeldOutTally.summary`).

    Attributes:
        pairs: held-out pairs searched per set.
        rates: ``"<set>/<method>"`` -> share located, for the methods of :data:`METHOD_MEANINGS`.
        margins: the same keys -> mean margin (z-score; NaN where none could be measured).
        paired: set -> ``"<method> - <control>"`` of :data:`PAIRED` -> (mean, standard error) over the paired pairs.
    """

    pairs: int
    rates: dict[str, float]
    margins: dict[str, float]
    paired: dict[str, dict[str, tuple[float, float]]]
