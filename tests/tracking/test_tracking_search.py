"""A frame's searches: the held noise model read at a log-likelihood's peak, the window's surface as the likelihood."""

from __future__ import annotations

import pytest
import torch
from _tracking import FRAME, cut, texture

from enmi_torch import ECR, NCC, localize
from enmi_torch.localization import SearchStrategy
from enmi_torch.localization.candidates import rotate_captured
from enmi_torch.scores.ecr import ecr_model_variance
from enmi_torch.tracking import initial_belief
from enmi_torch.tracking.search import FrameSearch


def _direct_estimates(frame, variance, valid, reference, top, left, yaw, bins=16):
    """``tau^2`` and ``delta^2`` of ECR on the pair at map cell ``(top, left)`` and ``yaw``, in float64, by hand."""
    turned, turned_variance, turned_valid = rotate_captured(frame, variance, valid, [yaw], "nearest")
    height, width = FRAME
    padded = torch.nn.functional.pad(reference.double(), (50, 50, 50, 50))
    on_map = torch.nn.functional.pad(torch.ones_like(reference, dtype=torch.bool), (50, 50, 50, 50))
    section = padded[..., top + 50 : top + 50 + height, left + 50 : left + 50 + width]
    inside = on_map[..., top + 50 : top + 50 + height, left + 50 : left + 50 + width]
    pair = (turned.double(), section, turned_variance.double())
    tau2 = ecr_model_variance(*pair, bins=bins, valid_mask=turned_valid & inside)
    delta2 = ECR(bins=bins).response_variance_of(*pair, valid_mask=turned_valid & inside)
    return float(tau2[0]), float(delta2[0])


@pytest.mark.parametrize(
    ("peak", "yaw"),
    [((1, 0, 0), 0.0), ((1, 4, 6), 0.0), ((0, 2, 1), -4.0), ((2, 3, 5), 4.0)],  # corners, yaw bins either side
)
def test_the_held_noise_model_is_ecrs_own_estimate_on_the_pair_at_the_peak(generator, peak, yaw):
    # A non-square window (ry 2, rx 3) and frame, a noisier left half: a swapped axis, a radius off by one, the wrong
    # yaw bin or turn each read another pair.
    reference = texture(generator, (70, 90)).float()
    frame = cut(reference, 41, 33) + 6 * torch.randn(1, 1, *FRAME, generator=generator)
    variance = torch.full((1, 1, *FRAME), 36.0)
    variance[..., : FRAME[1] // 2] = 100.0
    valid = torch.ones(1, 1, *FRAME, dtype=torch.bool)
    valid[..., :3, :] = False  # the far rows unobserved
    belief = initial_belief(torch.tensor([[40.0, 31.0, 0.0]]), shifts=(2, 3), yaw_bins=3, yaw_step=4.0)
    likelihood = torch.zeros(3, 5, 7, dtype=torch.float64)
    likelihood[peak] = 1.0
    stale = ECR(bins=16, model_variance=5.0, response_variance=1.0)  # held before: read afresh, by the score itself
    search = FrameSearch(frame, reference, variance, valid, ECR(bins=16), (stale,))
    held = search.held_fit(0, belief, likelihood)
    _, row, col = peak
    x, y = 40 + col - 3, 31 + row - 2  # the peak's cell
    top, left = y - FRAME[0] // 2, x - FRAME[1] // 2
    tau2, delta2 = _direct_estimates(frame, variance, valid, reference, top, left, yaw)
    assert held == ECR(bins=16, model_variance=tau2, response_variance=delta2)
    assert held.model_variance == pytest.approx(tau2, rel=1e-12) and held.misfit == "independent"


def test_a_peak_by_the_map_edge_reads_only_the_cells_on_the_map(generator):
    reference = texture(generator, (40, 60)).float()
    frame = cut(reference, 16, 12) + 4 * torch.randn(1, 1, *FRAME, generator=generator)
    belief = initial_belief(torch.tensor([[16.0, 12.0, 0.0]]), shifts=3, yaw_bins=1)
    likelihood = torch.zeros(1, 7, 7, dtype=torch.float64)
    likelihood[0, 0, 0] = 1.0  # the cell (13, 9): the frame's top rows and left columns lie off the map
    held = FrameSearch(frame, reference, 16.0, None, ECR(bins=16)).held_fit(0, belief, likelihood)
    valid = torch.ones(1, 1, *FRAME, dtype=torch.bool)
    tau2, delta2 = _direct_estimates(frame, torch.full((1, 1, *FRAME), 16.0), valid, reference, 9 - 12, 13 - 16, 0.0)
    assert (held.model_variance, held.response_variance) == pytest.approx((tau2, delta2), rel=1e-12)


def test_a_score_that_estimates_nothing_is_held_as_it_is(generator):
    reference = texture(generator, (40, 60)).float()
    belief = initial_belief(torch.tensor([[30.0, 20.0, 0.0]]), shifts=2, yaw_bins=1)
    likelihood = torch.zeros(1, 5, 5, dtype=torch.float64)
    for score in (NCC(), ECR(bins=16, model_variance=30.0, response_variance=2.0)):
        variance = None if score == NCC() else 1.0
        search = FrameSearch(cut(reference, 30, 20), reference, variance, None, score)
        assert search.held_fit(0, belief, likelihood) is score


def test_the_window_surface_is_the_held_scores_exact_value_on_each_pair(generator):
    # With the noise model held, each candidate of the window is ECR of its aligned pair under that model: the
    # likelihood has nothing to rescore (no finalist stage), and its values are those of the direct pairs.
    reference = texture(generator, (50, 70)).float()
    frame = cut(reference, 36, 26) + 5 * torch.randn(1, 1, *FRAME, generator=generator)
    held = ECR(bins=16, model_variance=11.0, response_variance=3.0, saturation=None)
    belief = initial_belief(torch.tensor([[35.0, 25.0, 0.0]]), shifts=(2, 3), yaw_bins=1)
    raw, best, _, _ = FrameSearch(frame, reference, 25.0, None, ECR(bins=16), (held,)).window(belief)
    for row in range(5):
        for col in range(7):
            top, left = 25 + row - 2 - FRAME[0] // 2, 35 + col - 3 - FRAME[1] // 2
            section = reference[..., top : top + FRAME[0], left : left + FRAME[1]]
            expected = held(frame.double(), section.double(), 25.0) * frame.numel()
            torch.testing.assert_close(raw[0, 0, row, col], expected[0], rtol=2e-5, atol=1e-3)
    found = localize(frame, reference, 25.0, score=held, shifts=(2, 3), around=(35, 25))
    assert found.finalists is None and float(best[0]) == pytest.approx(float(found.score[0]))


def test_the_window_search_has_no_finalist_stage_and_the_wide_search_keeps_localizes(generator, monkeypatch):
    # The window's surface is the belief's likelihood; a finalist would only choose a pose, which the belief does
    # not take. The wide search chooses a pose: it keeps localize's finalists.
    import enmi_torch.tracking.search as search_module

    strategies = []

    def recording(*args, **kwargs):
        strategies.append(kwargs.get("search"))
        return localize(*args, **kwargs)

    monkeypatch.setattr(search_module, "localize", recording)
    reference = texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=2, yaw_bins=1)
    search = FrameSearch(cut(reference, 45, 30), reference, 1.0, None, ECR(bins=16))
    search.window(belief)
    search.wide(0, belief, 6, 1, 2)
    assert strategies[0].finalists == 0
    assert strategies[1].finalists == SearchStrategy().finalists and strategies[1].coarse_factor == 2
