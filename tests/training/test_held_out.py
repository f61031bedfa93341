"""The held-out comparison of enmi-fit-mask: searches by localize, levels read from the data, tallies, the printout."""

import math

import numpy as np
import pytest
import torch

from enmi_torch import ECR, ENMI, NCC, NMI
from enmi_torch.training.fit_outputs import print_summary
from enmi_torch.training.held_out import (
    LADDER_HIGHEST,
    LADDER_LOWEST,
    METHOD_MEANINGS,
    HeldOutTally,
    Trial,
    amplified,
    calibrate_levels,
    held_out_order,
    localization_trials,
    trial_methods,
)


def table(shares: dict[float, dict[str, float]]):
    """``rates_at`` reading a table, and the factors it was asked for, in order."""
    asked = []

    def rates_at(factor: float) -> dict[str, float]:
        asked.append(factor)
        return shares[factor]

    return rates_at, asked


def test_the_hard_level_is_where_the_best_method_crosses_half_interpolated_in_log_factor():
    shares = {
        1.0: {"ncc": 1.0, "ecr_uniform": 1.0},
        2.0: {"ncc": 0.6, "ecr_uniform": 0.9},
        4.0: {"ncc": 0.7, "ecr_uniform": 0.8},  # the best method changes between levels: the best share counts
        8.0: {"ncc": 0.2, "ecr_uniform": 0.3},
        16.0: {"ncc": 0.9, "ecr_uniform": 0.9},  # beyond the first crossing: never asked
    }
    rates_at, asked = table(shares)
    calibration = calibrate_levels(rates_at, 10)
    assert asked == [1.0, 2.0, 4.0, 8.0]
    assert calibration.factors == [1.0, 2.0, 4.0, 8.0] and calibration.best == [1.0, 0.9, 0.8, 0.3]
    expected = 4 * 2 ** ((0.8 - 0.5) / (0.8 - 0.3))  # 6.06...
    assert calibration.hard == float(f"{expected:.2g}") == 6.1
    assert calibration.easy == 1.5 and calibration.bracketed == "yes" and calibration.pairs == 10
    assert calibration.rates == {"ncc": [1.0, 0.6, 0.7, 0.2], "ecr_uniform": [1.0, 0.9, 0.8, 0.3]}
    assert calibration.leaders() == ["ecr_uniform", "ecr_uniform", "ecr_uniform", "ecr_uniform"]
    assert calibration.levels() == {"level_easy": 1.5, "level_hard": 6.1}


def test_pairs_beyond_half_as_they_are_halve_the_factor_below_one():
    shares = {1.0: {"ncc": 0.25}, 0.5: {"ncc": 0.4}, 0.25: {"ncc": 0.9}, 0.125: {"ncc": 1.0}}
    rates_at, asked = table(shares)
    calibration = calibrate_levels(rates_at, 4)
    assert asked == [1.0, 0.5, 0.25]
    assert calibration.factors == [0.25, 0.5, 1.0] and calibration.best == [0.9, 0.4, 0.25]
    expected = 0.25 * 2 ** ((0.9 - 0.5) / (0.9 - 0.4))
    assert calibration.hard == float(f"{expected:.2g}") == 0.44 and calibration.easy == 0.11


def test_exactly_half_counts_as_finding_half():
    rates_at, asked = table({1.0: {"ncc": 1.0}, 2.0: {"ncc": 0.5}, 4.0: {"ncc": 0.25}})
    assert calibrate_levels(rates_at, 4).hard == 2.0 and asked == [1.0, 2.0, 4.0]  # on up from a level at one half
    rates_at, asked = table({1.0: {"ncc": 0.25}, 0.5: {"ncc": 0.5}, 0.25: {"ncc": 1.0}})
    assert calibrate_levels(rates_at, 4).hard == 0.5 and asked == [1.0, 0.5]  # down to the first level at one half


@pytest.mark.parametrize(
    ("share", "factors", "hard", "bracketed"), [(1.0, 9, LADDER_HIGHEST, "above"), (0.0, 4, LADDER_LOWEST, "below")]
)
def test_the_ladder_stops_at_its_ends(share, factors, hard, bracketed):
    rates_at, asked = table({2.0**power: {"nmi": share} for power in range(-3, 9)})
    calibration = calibrate_levels(rates_at, 8)
    assert len(asked) == factors and calibration.hard == hard and calibration.bracketed == bracketed
    assert calibration.easy == float(f"{hard / 4:.2g}")  # 64 and 0.031
    assert asked == sorted(asked, reverse=share == 0) and calibration.factors == sorted(asked)
    assert asked[-1] == hard and asked[0] == 1.0


def _direct_ncc_located(local: np.ndarray, prior: np.ndarray, shift: int) -> bool:
    """Pearson's correlation at every shift by a loop; located when the best is within one pixel of zero."""
    height, width = prior.shape
    crop = local[shift : height - shift, shift : width - shift]
    best, where = -math.inf, None
    for dy in range(-shift, shift + 1):
        for dx in range(-shift, shift + 1):
            section = prior[shift + dy : height - shift + dy, shift + dx : width - shift + dx]
            value = np.corrcoef(crop.ravel(), section.ravel())[0, 1]
            if value > best:
                best, where = value, (dy, dx)
    return abs(where[0]) <= 1 and abs(where[1]) <= 1


def test_a_ladder_on_tiny_pairs_picks_the_level_of_a_direct_computation():
    """Amplified and clipped pairs, localized by localize, against Pearson's correlation at every shift by loops."""
    rng = np.random.default_rng(3)
    pairs, height, width, shift = 12, 18, 22, 3  # not square: a swapped axis would crop the wrong pixels
    prior = rng.uniform(0, 255, (pairs, 1, height, width))
    local = prior + rng.normal(0, 100, prior.shape)
    valid = torch.ones(prior.shape, dtype=torch.bool)
    local_t, prior_t = torch.from_numpy(local).float(), torch.from_numpy(prior).float()

    def rates_at(factor: float) -> dict[str, float]:
        searched = localization_trials(
            amplified(local_t, prior_t, factor, (0.0, 256.0)), prior_t, valid, {}, max_shift=shift, scores=(NCC(),)
        )
        return {"ncc": float(searched["ncc"].located.double().mean())}

    def direct(factor: float) -> dict[str, float]:
        noisy = local if factor == 1 else np.clip(prior + factor * (local - prior), 0, 256)
        hits = [_direct_ncc_located(noisy[index, 0], prior[index, 0], shift) for index in range(pairs)]
        return {"ncc": float(np.mean(hits))}

    calibration = calibrate_levels(rates_at, pairs)
    reference = calibrate_levels(direct, pairs)
    assert calibration.bracketed == "yes" and 1 < calibration.hard < LADDER_HIGHEST  # a crossing inside the ladder
    assert calibration == reference
    low = max(factor for factor, best in zip(reference.factors, reference.best, strict=True) if best >= 0.5)
    assert low <= calibration.hard <= 2 * low


def test_localization_trials_find_aligned_pairs_and_miss_shifted_ones():
    generator = torch.Generator().manual_seed(0)
    prior = torch.rand(3, 1, 20, 24, generator=generator) * 255
    valid = torch.ones(3, 1, 20, 24, dtype=torch.bool)
    variance = torch.linspace(1, 100, 20 * 24).reshape(20, 24)
    noisy = prior + torch.randn(prior.shape, generator=generator) * variance.sqrt()
    scores = (ECR(bins=16), ENMI(bins=16), NMI(bins=16), NCC())
    options = {"max_shift": 3, "scores": scores, "uniform_grid": (0.25, 4.0)}
    results = localization_trials(noisy, prior, valid, {"learned": variance, "uniform": 50.0}, **options)
    expected = ["ecr_learned", "enmi_learned", "ecr_uniform", "ecr_uniform_x0.25", "ecr_uniform_x4", "enmi_uniform"]
    expected += ["enmi_uniform_x0.25", "enmi_uniform_x4", "nmi", "ncc"]
    assert list(results) == expected == trial_methods(scores, ["learned", "uniform"], (0.25, 4.0))
    assert all(bool(trial.located.all()) and bool((trial.margin > 3).all()) for trial in results.values())
    # The local image sits two pixels off along the columns only: the zero shift loses, for every method.
    results = localization_trials(
        noisy.roll(2, dims=-1), prior, valid, {"learned": variance, "uniform": 50.0}, **options
    )
    assert not any(bool(trial.located.any()) for trial in results.values())
    # A one-pixel offset still counts as located (the yardstick's rule), along either axis.
    for dims in (-2, -1):
        results = localization_trials(noisy.roll(1, dims=dims), prior, valid, {"uniform": 50.0}, **options)
        assert bool(results["ecr_uniform"].located.all()) and bool(results["ncc"].located.all())


def test_the_default_score_is_searched_with_its_finalist_stage(monkeypatch):
    """ECR's pairs go through localize's finalist stage: the surface's best local maxima rescored exactly."""
    from enmi_torch.localization import candidates

    calls = []
    finalists = candidates.CandidateSurfaces.finalists

    def counted(self, *args, **kwargs):
        calls.append(1)
        return finalists(self, *args, **kwargs)

    monkeypatch.setattr(candidates.CandidateSurfaces, "finalists", counted)
    generator = torch.Generator().manual_seed(2)
    prior = torch.rand(2, 1, 16, 16, generator=generator) * 255
    local = prior + 10 * torch.randn(prior.shape, generator=generator)
    valid = torch.ones(prior.shape, dtype=torch.bool)
    localization_trials(local, prior, valid, {"uniform": 100.0}, max_shift=2, scores=(ENMI(bins=16), NCC()))
    assert calls == []  # exact surfaces: nothing to rescore
    localization_trials(local, prior, valid, {"uniform": 100.0}, max_shift=2, scores=(ECR(bins=16),))
    assert calls == [1]


def test_a_pair_is_located_by_the_finalist_localize_chose_not_by_the_surfaces_maximum(monkeypatch):
    """Where the finalist stage overrules the surface, the finalist's placement counts."""
    from enmi_torch.localization.peak import Finalists, Localization
    from enmi_torch.training import held_out

    surface = torch.zeros(3, 1, 5, 5)
    surface[:, 0, 0, 0] = 5.0  # the surface's maximum: two cells off on both axes
    # (yaw, row, col) of two finalists per pair; the chosen one: the zero shift, one row off, two columns off.
    placements = torch.tensor([[[0, 0, 0], [0, 2, 2]], [[0, 3, 1], [0, 0, 0]], [[0, 0, 0], [0, 2, 4]]])
    chosen = torch.tensor([1, 0, 1])

    def fake_localize(captured, reference, variance, **options):
        assert options["shifts"] == 2 and captured.shape[0] == 3
        finalists = Finalists(placements, torch.zeros(3, 2), chosen)
        zeros = torch.zeros(3)
        return Localization(
            torch.zeros(3, 3), zeros, surface, torch.zeros(3, 2, 2), zeros, torch.zeros(1), finalists=finalists
        )

    monkeypatch.setattr(held_out, "localize", fake_localize)
    window = torch.rand(3, 1, 10, 12)
    crop, valid = window[..., 2:8, 2:10], torch.ones(3, 1, 6, 8, dtype=torch.bool)
    assert held_out._search(NCC(), crop, window, None, valid, 2).located.tolist() == [True, True, False]


def test_a_crop_holding_one_value_is_missed_and_the_others_searched():
    generator = torch.Generator().manual_seed(4)
    prior = torch.rand(3, 1, 14, 18, generator=generator) * 255
    local = prior + torch.randn(prior.shape, generator=generator)
    local[1] = 0.0  # clipped flat: every placement scores alike
    valid = torch.ones(prior.shape, dtype=torch.bool)
    results = localization_trials(local, prior, valid, {}, max_shift=2, scores=(NCC(),))
    assert results["ncc"].located.tolist() == [True, False, True]
    assert math.isnan(results["ncc"].margin[1]) and bool(torch.isfinite(results["ncc"].margin[[0, 2]]).all())


def test_localization_of_fixed_methods_apart_equals_one_call():
    """The module scores the true map, NMI and NCC once per fit and the mask's methods at every validation."""
    generator = torch.Generator().manual_seed(1)
    prior = torch.rand(2, 1, 18, 22, generator=generator) * 255
    valid = torch.rand(2, 1, 18, 22, generator=generator) > 0.1
    truth = torch.linspace(1, 400, 18 * 22).reshape(18, 22)
    noisy = prior + torch.randn(prior.shape, generator=generator) * truth.sqrt()
    variance_scores = (ECR(bins=16), ENMI(bins=16))
    scores = (*variance_scores, NMI(bins=16), NCC())
    mine = {"learned": truth * 1.5, "uniform": 120.0}
    options = {"max_shift": 2, "uniform_grid": (0.5,)}
    together = localization_trials(noisy, prior, valid, {**mine, "true": truth}, scores=scores, **options)
    apart = localization_trials(noisy, prior, valid, mine, scores=variance_scores, **options)
    assert "nmi" not in apart and "ecr_true" not in apart
    apart.update(localization_trials(noisy, prior, valid, {"true": truth}, max_shift=2, scores=scores))
    assert apart.keys() == together.keys()
    for method, trial in together.items():
        assert torch.equal(apart[method].located, trial.located)
        torch.testing.assert_close(apart[method].margin, trial.margin, equal_nan=True)


def _trial(located: list[int], margin: list[float]) -> Trial:
    return Trial(torch.tensor(located, dtype=torch.bool), torch.tensor(margin, dtype=torch.float64))


def test_a_tally_over_two_processes_equals_one_and_pairs_the_methods_pair_by_pair():
    names = ["hard/ecr_learned", "hard/ecr_uniform", "hard/ecr_uniform_x4", "hard/enmi_uniform", "hard/nmi"]
    outcomes = {
        "ecr_learned": _trial([1, 1, 0, 1, 0, 1], [3.0, 2.0, 0.5, 4.0, math.nan, 1.0]),
        "ecr_uniform": _trial([1, 0, 0, 1, 0, 0], [2.0, 1.0, 0.0, 3.0, 1.0, 0.0]),
        "ecr_uniform_x4": _trial([1, 0, 1, 1, 0, 0], [2.5, 1.0, 2.0, 3.0, 1.0, 0.0]),
        "enmi_uniform": _trial([0, 0, 0, 1, 0, 0], [0.0] * 6),
        "nmi": _trial([0, 1, 0, 0, 0, 0], [0.0] * 6),
    }
    one = HeldOutTally(8, names)
    one.add("hard", outcomes, torch.arange(6))
    ranks = [HeldOutTally(8, names), HeldOutTally(8, names)]
    for rank, tally in enumerate(ranks):  # a shard sampler's split: every other pair
        part = torch.arange(rank, 6, 2)
        tally.add(
            "hard", {method: Trial(trial.located[part], trial.margin[part]) for method, trial in outcomes.items()}, part
        )
    summed = ranks[0].reduce(lambda tensor: tensor + _stack(ranks[1]))  # the sum over the two processes
    alone = one.reduce(lambda tensor: tensor).summary()
    assert summed.summary() == alone
    assert alone.pairs == 6
    assert alone.rates["hard/ecr_learned"] == 4 / 6 and alone.rates["hard/ecr_uniform"] == 2 / 6
    assert alone.margins["hard/ecr_learned"] == pytest.approx((3 + 2 + 0.5 + 4 + 1) / 5)  # the NaN left out
    # The best uniform: x4 finds 3 of 6, the mean 2: picked after the fact, on these pairs (an oracle).
    assert alone.rates["hard/ecr_best_uniform"] == 3 / 6 and alone.rates["hard/enmi_best_uniform"] == 1 / 6
    assert "hard/ecr_uniform_x4" not in alone.rates  # the grid's members are not rows of the table
    learned = np.array([1, 1, 0, 1, 0, 1.0])
    for control, bits in (("ecr_uniform", [1, 0, 0, 1, 0, 0]), ("ecr_best_uniform", [1, 0, 1, 1, 0, 0])):
        difference = learned - np.array(bits)
        mean, error = alone.paired["hard"][f"ecr_learned - {control}"]
        assert mean == pytest.approx(difference.mean()) and error == pytest.approx(
            difference.std(ddof=1) / math.sqrt(6)
        )
    assert alone.paired["hard"]["ecr_learned - enmi_best_uniform"][0] == pytest.approx(3 / 6)


def _stack(tally: HeldOutTally) -> torch.Tensor:
    """What ``reduce`` sums over the processes: the tally's rows, stacked."""
    names = sorted(tally.located)
    rows = [tally.searched] + [tally.located[name] for name in names]
    rows += [tally.margin_sums[name] for name in names] + [tally.margin_counts[name] for name in names]
    return torch.stack(rows)


def test_held_out_sets_are_ordered_easiest_first():
    assert held_out_order(["level_hard", "noise_x32", "level_easy", "noise_x4", "other"]) == [
        "other",
        "level_easy",
        "level_hard",
        "noise_x4",
        "noise_x32",
    ]


def _summary(calibration: dict | None, levels: dict[str, float]) -> dict:
    sets = list(levels)
    methods = list(METHOD_MEANINGS)
    rates = {
        name: {method: 1 - index / 20 - position / 10 for index, method in enumerate(methods)}
        for position, name in enumerate(sets)
    }
    return {
        "errors": {"rel_rms_vs_empirical": 0.01},
        "shape": [64, 48],
        "train_pairs": 760,
        "source": "pairs",
        "epochs": 10,
        "seconds": 12.0,
        "learned_pixels": 3072,
        "files": {"pt": "runs/fit_mask/pairs_0/mask/variance_mask.pt"},
        "last_checkpoint": "runs/fit_mask/pairs_0/checkpoints/last.ckpt",
        "log_dir": "runs/fit_mask/pairs_0",
        "localization_pairs": 40,
        "localization_levels": levels,
        "localization_calibration": calibration,
        "localization_grid": [1.0, 0.25, 4.0],
        "value_range": [0.0, 256.0],
        "localization": rates,
        "localization_paired": {name: {"ecr_learned - ecr_uniform": {"mean": 0.025, "se": 0.0125}} for name in sets},
    }


def test_the_printout_says_which_levels_were_chosen_and_why_and_ends_with_how_to_use_the_mask(capsys):
    calibration = {"factors": [0.5, 1.0], "best": [0.9, 0.3], "bracketed": "yes", "pairs": 32}
    print_summary(_summary(calibration, {"level_easy": 0.18, "level_hard": 0.7}))
    lines = capsys.readouterr().out.splitlines()
    start = lines.index(
        "  held-out levels read from 32 held-out pairs: their residual local - prior amplified by a factor, clipped to "
        "[0, 256]"
    )
    assert lines[start + 1 : start + 4] == [
        "    factor        x0.5     x1",
        "    best share    0.90   0.30",
        "    level_hard x0.7: where the best method finds 0.5 of the pairs (L50)",
    ]
    assert lines[start + 4] == "    level_easy x0.18: a quarter of level_hard's factor"
    table = lines[start + 5 :]
    assert (
        table[0] == "  held-out pairs located within one pixel by localize, share of 40 (standard error at most 0.08):"
    )
    assert table[1].split() == ["level_easy", "level_hard"]
    rows = [line.split()[0] for line in table[2:12]]
    assert rows == list(METHOD_MEANINGS) and rows[0] == "ecr_learned"  # the library's default score first
    assert table[2].split() == ["ecr_learned", "1.000", "0.900"] and table[11].split() == ["ncc", "0.550", "0.450"]
    assert "*_best_uniform: the best of the mask's mean times 0.25, 1 or 4 (an oracle)" in table[15]
    assert table[16] == "  paired differences over the same 40 pairs (mean ± standard error):"
    assert table[18].split() == ["ecr_learned", "-", "ecr_uniform", "+0.025", "±", "0.013", "+0.025", "±", "0.013"]
    assert lines[-5:] == [
        "Use the mask, with the library's default score first:",
        '  mask = LearnedVariance.load("runs/fit_mask/pairs_0/mask/variance_mask.pt")',
        "  localize(captured, prior_map, mask)   # ECR(), localize's default score",
        "  ECRLoss(variance_model=mask)          # its loss (registration, training)",
        "  ENMILoss(variance_model=mask)         # ENMI, the paper's score",
    ]


def test_the_printout_names_factors_given_by_hand_and_the_ends_of_the_ladder(capsys):
    print_summary(_summary(None, {"noise_x1": 1.0, "noise_x16": 16.0}))
    printed = capsys.readouterr().out
    assert "  held-out levels given by hand (--model.localization_noise): x1, x16\n" in printed
    lines = printed.splitlines()
    header = lines[lines.index("  held-out levels given by hand (--model.localization_noise): x1, x16") + 2]
    assert header.split() == ["noise_x1", "noise_x16"]
    calibration = {"factors": [0.125, 0.25, 0.5, 1.0], "best": [0.2, 0.2, 0.1, 0.0], "bracketed": "below", "pairs": 8}
    print_summary(_summary(calibration, {"level_easy": 0.031, "level_hard": 0.125}))
    assert (
        "    level_hard x0.125: the lowest factor tried, where the best method still finds less than 0.5 of the pairs\n"
        "    level_easy x0.031: a quarter of level_hard's factor\n"
    ) in capsys.readouterr().out
