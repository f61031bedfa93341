"""Frame health: the peak z-score, the running mean of the matches, clearness."""

from __future__ import annotations

import math

import torch


def test_the_peak_z_score_of_a_nearly_flat_log_likelihood_stays_small():
    from enmi_torch.tracking.health import peak_z_score

    # A featureless frame: a few nats of bump on a log-likelihood whose MAD is a hundredth of a nat. Its z-score was
    # ~3e8, which passed every peak rule and, averaged into the recent matches' z, made every later match look weak.
    generator = torch.Generator().manual_seed(0)
    flat = 0.01 * torch.randn(5, 17, 17, generator=generator, dtype=torch.float64)
    flat[2, 8, 8] = 2.5
    median = flat.median()
    assert float(peak_z_score(flat)) > 100
    torch.testing.assert_close(peak_z_score(flat, min_spread=1.0), 2.5 - median)
    # A clear peak on a spread surface is not changed by the floor.
    spread = 30.0 * torch.randn(5, 17, 17, generator=generator, dtype=torch.float64)
    spread[2, 8, 8] = 400.0
    torch.testing.assert_close(peak_z_score(spread, min_spread=1.0), peak_z_score(spread))
    assert 8 < float(peak_z_score(spread)) < 20


def test_one_freak_peak_counts_at_most_twice_the_running_mean_of_the_matches():
    from enmi_torch.tracking.health import check_health, next_health

    health = check_health(None, 2, torch.device("cpu"))
    yes, no = torch.tensor([True, True]), torch.tensor([False, False])
    no_candidate = torch.full((2, 3), math.nan, dtype=torch.float64)
    health = next_health(
        health, yes, no, torch.zeros(2), torch.tensor([5.0, 5.0]), torch.tensor([8.0, 8.0]), no_candidate
    )
    health = next_health(
        health, yes, no, torch.zeros(2), torch.tensor([91.0, 6.0]), torch.tensor([8.0, 8.0]), no_candidate
    )
    torch.testing.assert_close(health.typical_z, torch.tensor([0.7 * 5 + 0.3 * 10, 0.7 * 5 + 0.3 * 6]).double())
    relocalized = next_health(health, yes, yes, torch.zeros(2), torch.tensor([91.0, 2.0]), torch.ones(2), no_candidate)
    assert relocalized.typical_z.tolist() == [91.0, 2.0]  # a relocalization starts afresh


def test_clearness_is_one_for_a_usable_peak_the_squared_ratio_below_and_zero_where_ruled_out():
    from enmi_torch.tracking.health import Health, check_health, clearness

    fresh = check_health(None, 5, torch.device("cpu"))
    peak_z = torch.tensor([4.0, 1.5, 1.5, math.nan, 6.0], dtype=torch.float64)
    surprise = torch.tensor([0.0, 0.0, 40.0, 0.0, 0.0], dtype=torch.float64)
    weight = clearness(peak_z, surprise, fresh, min_peak_z=3.0, z_drop=0.3, max_surprise=30.0)
    # usable; (1.5 / 3)^2; ruled out by the prediction; no candidate; usable
    torch.testing.assert_close(weight, torch.tensor([1.0, 0.25, 0.0, 0.0, 1.0], dtype=torch.float64))
    # After matches of z 40, z_drop * 40 = 12 is the bar: a peak of 6 weighs (6 / 12)^2.
    seasoned = Health(
        fresh.weak_frames, torch.full((5,), 40.0, dtype=torch.float64), fresh.typical_temperature, fresh.candidate
    )
    weight = clearness(peak_z, surprise, seasoned, min_peak_z=3.0, z_drop=0.3, max_surprise=30.0)
    torch.testing.assert_close(
        weight, torch.tensor([(4 / 12) ** 2, (1.5 / 12) ** 2, 0.0, 0.0, 0.25], dtype=torch.float64)
    )


def test_a_health_made_without_held_scores_holds_none_and_a_wrong_one_is_refused():
    import pytest

    from enmi_torch import ECR
    from enmi_torch.tracking.health import Health, check_health

    fresh = check_health(None, 2, torch.device("cpu"))
    assert fresh.held == (None, None)
    made = Health(*fresh[:4])  # as made before the held scores: none held
    assert made.held is None and check_health(made, 2, torch.device("cpu")).held == (None, None)
    kept = fresh._replace(held=(ECR(model_variance=3.0), None))
    assert check_health(kept, 2, torch.device("cpu")) is kept
    for held in ((None,), (None, "ecr"), [None, None]):
        with pytest.raises(ValueError, match=r"2 held scores \(or None\) from the previous step"):
            check_health(fresh._replace(held=held), 2, torch.device("cpu"))
