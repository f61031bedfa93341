"""What search and registration ask a score: the two-stage search's stages and the least-squares fit, refused by name
where a family has none; the package's family functions."""

import importlib

import pytest
import torch

import enmi_torch.scores as scores
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Mixture
from enmi_torch.scores.base import LeastSquaresFit, ResponseBasis

RANGE = (0.0, 256.0)


@pytest.mark.parametrize(
    ("score", "expected"),
    [(ECR(), True), (ECR(response="binned"), True), (ECR(response="linear"), False), (NMI(), False), (NCC(), False)],
)
def test_a_score_says_whether_it_supports_the_two_stage_search(score, expected):
    assert score.supports_two_stage is expected


@pytest.mark.parametrize("score", [NMI(), ENMI(), NCC(), Mixture()], ids=lambda score: score.name)
def test_scores_without_a_cheap_form_refuse_each_stage_by_name(score):
    window = torch.rand(1, 1, 12, 12) * 256
    captured = window[..., 2:8, 3:9]
    variance = 1.0 if score.uses_variance else None
    with pytest.raises(ValueError, match=rf"score {type(score).__name__}\(.*has no first stage for a two-stage search"):
        score.rough_score(4, window)
    with pytest.raises(ValueError, match="has no rough surface for a two-stage search"):
        score.rough_surface(captured, window, variance)
    placements = torch.zeros(1, 3, dtype=torch.int64)
    with pytest.raises(ValueError, match="has no exact rescoring for a two-stage search"):
        score.placement_scores(placements, rotations=(), window=(), min_overlap=0.5, rough=torch.zeros(1, 7, 7))


def test_the_linear_ecr_refuses_the_two_stage_stages():
    window = torch.rand(1, 1, 12, 12) * 256
    with pytest.raises(ValueError, match="two-stage ECR search needs a binned or shrunk response, got 'linear'"):
        ECR(response="linear").rough_score(4, window)


def test_the_rough_score_spans_the_window_and_refuses_a_window_in_one_bin():
    window = torch.arange(101.0).reshape(1, 1, 1, 101)
    rough = ECR(bins=16).rough_score(4, window)
    assert rough == ECR(bins=4, value_range=(2.0, 98.0), model_variance=None)
    with pytest.raises(ValueError, match=r"reference varies .* but all its valid pixels fall in one of the 2 bins"):
        ECR(bins=2).rough_score(2, torch.rand(1, 1, 6, 6))  # values in [0, 1] against (0, 256)


def test_least_squares_scores_give_their_response_and_weights():
    assert ECR(bins=8).response_basis() == ResponseBasis(8, RANGE)
    assert ECR(response="linear").response_basis() == ResponseBasis(0, None)
    assert NCC().response_basis().size == 2 and ECR(bins=8).response_basis().size == 8
    captured = torch.rand(2, 1, 4, 5, dtype=torch.float64) * 256
    valid = torch.rand(2, 1, 4, 5) > 0.3
    fit = NCC().least_squares_fit(captured, captured, None, valid)
    assert fit == LeastSquaresFit(fit.weights) and torch.equal(fit.weights, valid.reshape(2, -1).double())
    variance = torch.full_like(captured, 4.0)
    fixed = ECR(bins=8, model_variance=12.0, response="binned").least_squares_fit(captured, captured, variance, valid)
    torch.testing.assert_close(fixed.weights, valid.reshape(2, -1).double() / 16.0)
    assert fixed.line_penalty is None
    shrunk = ECR(bins=8, model_variance=12.0, response_variance=2.0).least_squares_fit(
        captured, captured, variance, valid
    )
    torch.testing.assert_close(shrunk.line_penalty, torch.full((2,), 0.5, dtype=torch.float64))


@pytest.mark.parametrize("score", [NMI(), ENMI(), Mixture()], ids=lambda score: score.name)
def test_histogram_scores_are_no_least_squares_fit(score):
    with pytest.raises(ValueError, match=rf"score must be ECR or NCC for register .* got '{score.name}'"):
        score.response_basis()
    image = torch.rand(1, 1, 4, 4)
    with pytest.raises(ValueError, match="score must be ECR or NCC for register"):
        score.least_squares_fit(image, image, None, torch.ones_like(image, dtype=torch.bool))


def test_the_family_functions_live_in_their_modules_and_functional_and_the_modules_stay_modules():
    functional = importlib.import_module("enmi_torch.functional")
    for family in ("ecr", "enmi", "nmi", "ncc"):
        module = importlib.import_module(f"enmi_torch.scores.{family}")
        assert getattr(scores, family) is module
        for suffix in ("", "_surface", "_loss"):
            assert getattr(functional, family + suffix) is getattr(module, family + suffix)
    mixture = importlib.import_module("enmi_torch.scores.mixture")
    for name in ("mixture_information", "mixture_surface", "mixture_loss"):
        assert getattr(functional, name) is getattr(mixture, name)
