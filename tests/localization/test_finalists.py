"""The search's finalist stage: the surface's best local maxima rescored exactly, each with its own fit."""

import math
import re

import numpy as np
import pytest
import torch
from kornia.geometry.transform import rotate
from skimage import data

from enmi_torch import ECR, NCC, NMI
from enmi_torch.localization import Finalists, SearchStrategy
from enmi_torch.localization.search import Localizer, localize

CLIP = (0.0, 255.999)


@pytest.fixture(scope="module")
def photo_map() -> torch.Tensor:
    """A non-square 120 x 150 crop of scikit-image's camera photograph, (1, 1, 120, 150) float64."""
    return torch.from_numpy(data.camera()[200:320, 180:330].astype(np.float64)).reshape(1, 1, 120, 150)


def _captured(photo_map, row, col, height, width, generator, sigma=70.0):
    """A clipped noisy crop whose pixel (h // 2, w // 2) lies on map cell (row, col), and its variance map."""
    crop = photo_map[..., row - height // 2 : row - height // 2 + height, col - width // 2 : col - width // 2 + width]
    variance = (sigma * torch.linspace(0.5, 1.5, height, dtype=torch.float64)[:, None].expand(height, width)) ** 2
    noisy = crop + variance.sqrt() * torch.randn(crop.shape, generator=generator, dtype=torch.float64)
    return noisy.clamp(*CLIP), variance[None, None]


def _direct_scores(result, captured, photo_map, variance, center, radius, yaws):
    """Each finalist's score by cropping the map directly and scoring the aligned pair with ECR()."""
    height, width = captured.shape[2:]
    scores = []
    for sample in range(captured.shape[0]):
        row0 = center[0] - height // 2 - radius[0]
        col0 = center[1] - width // 2 - radius[1]
        for yaw_index, row, col in result.finalists.placements[sample].tolist():
            if yaw_index < 0:
                scores.append(-math.inf)
                continue
            crop = photo_map[..., row0 + row : row0 + row + height, col0 + col : col0 + col + width]
            image, noise = captured[sample : sample + 1], variance
            valid = torch.ones_like(image, dtype=torch.bool)
            if yaws[yaw_index] != 0:  # the search turns the captured image by -yaw (nearest neighbour)
                angle = torch.tensor([-yaws[yaw_index]], dtype=image.dtype)
                stacked = torch.cat([image, noise.expand_as(image), torch.ones_like(image)], 1)
                turned = rotate(stacked, angle, mode="nearest")
                image, noise, valid = turned[:, :1], turned[:, 1:2], turned[:, 2:3] >= 0.5
            scores.append(float(ECR()(image, crop, torch.where(valid, noise, 1.0), valid_mask=valid)))
    return torch.tensor(scores, dtype=torch.float64).view(captured.shape[0], -1)


@pytest.mark.parametrize("yaws", [[0.0], [-3.0, 0.0, 3.0]], ids=["one yaw", "three yaws"])
def test_each_finalist_is_scored_by_the_score_on_its_aligned_pair_and_the_best_is_the_pose(photo_map, yaws, generator):
    height, width, radius, center = 24, 32, (5, 7), (60, 75)
    captured, variance = zip(
        *(_captured(photo_map, 60 + dy, 75 + dx, height, width, generator) for dx, dy in ((3, -2), (-6, 4))),
        strict=True,
    )
    captured, variance = torch.cat(captured), variance[0]
    result = localize(captured, photo_map, variance, shifts=radius, around=center[::-1], yaws=yaws)
    finalists = result.finalists
    assert isinstance(finalists, Finalists) and finalists.placements.shape == (2, 8, 3)
    assert int((captured == CLIP[1]).sum() + (captured == 0).sum()) > 50  # saturated readings: a censored fit
    torch.testing.assert_close(
        finalists.scores, _direct_scores(result, captured, photo_map, variance, center, radius, yaws)
    )
    assert torch.equal(finalists.chosen, finalists.scores.argmax(1))
    # The pose is read at the chosen placement: the sub-cell fit about it (re-centred once at most) stays within
    # one and a half cells of that placement's shift.
    best = finalists.best()
    assert bool(((result.shift[:, 0] - (best[:, 2] - radius[1])).abs() <= 1.5).all())
    assert bool(((result.shift[:, 1] - (best[:, 1] - radius[0])).abs() <= 1.5).all())
    surface_values = result.surface[torch.arange(2), best[:, 0], best[:, 1], best[:, 2]]
    torch.testing.assert_close(result.score, surface_values)
    # The finalists are local maxima of the surface, best surface value first.
    yaw, row, col = finalists.placements.unbind(-1)
    ranked = result.surface[torch.arange(2)[:, None], yaw, row, col]
    assert bool((ranked[:, :-1] >= ranked[:, 1:]).all())


class _PrefersTheSecond(ECR):
    """ECR whose finalist stage ranks the surface's second local maximum first (to see the search follow it)."""

    def finalists(self, captured, window, placements, variance=None, *, captured_mask=None, window_mask=None):
        scores = torch.zeros(placements.shape[0], dtype=torch.float64)
        scores[1] = 1.0
        return scores


def test_the_pose_follows_the_chosen_finalist_even_where_the_surface_ranks_another_higher(photo_map, generator):
    captured, variance = _captured(photo_map, 62, 70, 24, 32, generator, sigma=20.0)
    plain = localize(captured, photo_map, variance, shifts=(5, 7), around=(75, 60), search=SearchStrategy(finalists=0))
    assert plain.finalists is None
    result = localize(captured, photo_map, variance, shifts=(5, 7), around=(75, 60), score=_PrefersTheSecond())
    second = result.finalists.placements[0, 1]
    assert int(result.finalists.chosen[0]) == 1
    shift = torch.tensor([int(second[2]) - 7, int(second[1]) - 5], dtype=result.pose.dtype)
    assert bool(((result.shift[0] - shift).abs() <= 1.5).all())
    assert float(result.margin[0]) < 0  # the surface ranked the first finalist higher
    assert result.shift[0].round().tolist() != plain.shift[0].round().tolist()


@pytest.mark.parametrize(
    "score",
    [NMI(), NCC(), ECR(model_variance=100.0, response_variance=50.0, saturation=None)],
    ids=["nmi", "ncc", "ecr fixed"],
)
def test_a_search_whose_surface_is_exact_has_no_finalist_stage(photo_map, score, generator):
    captured, variance = _captured(photo_map, 62, 70, 24, 32, generator, sigma=10.0)
    assert score.surface_is_exact
    result = localize(
        captured, photo_map, variance if score.uses_variance else None, shifts=4, around=(75, 60), score=score
    )
    assert result.finalists is None


@pytest.mark.parametrize(
    "score",
    [NMI(), NCC(), ECR(model_variance=100.0, response_variance=50.0, saturation=None)],
    ids=["nmi", "ncc", "ecr fixed"],
)
def test_a_finalist_count_is_refused_naming_the_score_whose_surface_is_exact(photo_map, score, generator):
    captured, variance = _captured(photo_map, 62, 70, 24, 32, generator, sigma=10.0)
    variance = variance if score.uses_variance else None
    options = {"shifts": 4, "around": (75, 60), "score": score}
    with pytest.raises(ValueError, match=rf"^finalists=3 has no effect with score={re.escape(repr(score))}: its "):
        localize(captured, photo_map, variance, search=SearchStrategy(finalists=3), **options)
    with pytest.raises(ValueError, match=r"^finalists=3 has no effect"):
        Localizer(score=score, shifts=4, search=SearchStrategy(finalists=3))(captured, photo_map, variance)
    for search in (SearchStrategy(finalists=0), SearchStrategy()):  # no stage, as the search does anyway
        assert localize(captured, photo_map, variance, search=search, **options).finalists is None
    # A score that fits a model to each pair takes any count.
    assert localize(captured, photo_map, 100.0, shifts=4, around=(75, 60), search=SearchStrategy(finalists=3))


def test_the_strategies_and_localizer_carry_the_finalist_count(photo_map, generator):
    captured, variance = _captured(photo_map, 62, 70, 24, 32, generator, sigma=40.0)
    for search in (
        SearchStrategy(finalists=3),
        SearchStrategy("two_stage", finalists=3),
        SearchStrategy(coarse_factor=2, finalists=3),
    ):
        result = localize(captured, photo_map, variance, shifts=8, around=(75, 60), search=search)
        assert result.finalists.placements.shape == (1, 3, 3)
        placements = result.finalists.placements[0]
        found = placements[:, 0] >= 0  # fewer local maxima than asked for: the rest is padding
        assert bool(found[0]) and torch.equal(found, found.sort(descending=True).values)
        assert bool(torch.isinf(result.finalists.scores[0, ~found]).all())
        rescored = result.surface[0][tuple(placements[found].T)]
        assert bool(torch.isfinite(rescored).all())  # finalists lie where the strategy scored
    found = Localizer(score=ECR(), shifts=8, search=SearchStrategy(finalists=2))(
        captured, photo_map, variance, around=(75, 60)
    )
    assert found.finalists.placements.shape == (1, 2, 3)
    with pytest.raises(ValueError, match="finalists must be"):
        SearchStrategy(finalists=-1)
