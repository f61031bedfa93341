"""What search and registration ask a score: its declared traits (the two-stage search's stages, the least-squares
fit), refused by name where a family has none; the package's family functions."""

import importlib

import pytest
import torch

import enmi_torch.scores as scores
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Mixture
from enmi_torch.scores.base import LeastSquaresFit, ResponseBasis, Score

RANGE = (0.0, 256.0)


TRAIT_METHODS = {
    "two_stage": ("rough_score", "rough_surface", "placement_scores"),
    "least_squares": ("response_basis", "least_squares_fit"),
}


@pytest.mark.parametrize(
    ("score", "expected"),
    [
        (ECR(), {"two_stage", "least_squares"}),
        (ECR(response="binned"), {"two_stage", "least_squares"}),
        (ECR(response="linear"), {"least_squares"}),
        (NCC(), {"least_squares"}),
        (NMI(), set()),
        (ENMI(), set()),
        (Mixture(), set()),
    ],
    ids=repr,
)
def test_a_score_declares_its_traits_and_has_exactly_their_methods(score, expected):
    assert score.traits == expected and set(TRAIT_METHODS) == set(scores.base.TRAITS)
    for trait, methods in TRAIT_METHODS.items():
        for method in methods:
            # The base class declares no stub: a family without the trait has no such method at all.
            assert not hasattr(Score, method)
            if trait in expected:
                assert callable(getattr(score, method))
        assert (trait in expected) <= (trait in type(score).trait_holders)


@pytest.mark.parametrize(
    ("score", "trait", "holders"),
    [(NMI(), "two_stage", "ecr"), (ECR(response="linear"), "two_stage", "ecr"), (ENMI(), "least_squares", "ecr, ncc")],
    ids=repr,
)
def test_require_names_the_use_the_trait_its_methods_and_the_scores_that_have_it(score, trait, holders):
    with pytest.raises(ValueError, match=rf"^the use needs a score with the '{trait}' trait \(") as error:
        score.require(trait, "the use")
    assert f"got score={score!r}; scores that have it: {holders} (" in str(error.value)
    ECR().require("two_stage", "the use")  # no error
    with pytest.raises(ValueError, match="trait must be one of"):
        ECR().require("fast", "the use")


def test_the_linear_ecr_refuses_the_two_stage_stages():
    window = torch.rand(1, 1, 12, 12) * 256
    with pytest.raises(ValueError, match=r"the first stage of a two-stage search needs a score with the 'two_stage'"):
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


@pytest.mark.parametrize("score", [NMI(bins=16), ECR(bins=16), ENMI(bins=16)], ids=repr)
def test_the_default_finalists_score_each_aligned_pair_of_the_crops_with_both_masks(score, generator):
    window = torch.rand(1, 1, 14, 19, generator=generator, dtype=torch.float64) * 256
    window_mask = torch.rand(1, 1, 14, 19, generator=generator) > 0.2
    captured = torch.rand(2, 1, 5, 7, generator=generator, dtype=torch.float64) * 256
    captured_mask = torch.rand(2, 1, 5, 7, generator=generator) > 0.1
    variance = (
        (10 + 90 * torch.rand(2, 1, 5, 7, generator=generator, dtype=torch.float64)) if score.uses_variance else None
    )
    placements = torch.tensor([[0, 0, 0], [1, 9, 12], [0, 4, 2], [1, 0, 11]])
    expected = []
    for index, row, col in placements.tolist():  # a direct loop over the placements
        crop = window[..., row : row + 5, col : col + 7]
        valid = captured_mask[index : index + 1] & window_mask[..., row : row + 5, col : col + 7]
        noise = None if variance is None else variance[index : index + 1]
        expected.append(float(score(captured[index : index + 1], crop, noise, valid_mask=valid)))
    found = score.finalists(
        captured, window, placements, variance, captured_mask=captured_mask, window_mask=window_mask
    )
    torch.testing.assert_close(found, torch.tensor(expected, dtype=torch.float64))


@pytest.mark.parametrize(
    ("score", "exact"),
    [
        (NMI(), True),
        (NCC(), True),
        (ENMI(), True),
        (ECR(), False),
        (ECR(model_variance=9.0, response_variance=4.0), False),  # saturated readings are censored
        (ECR(model_variance=9.0, saturation=None), False),  # delta^2 estimated
        (ECR(model_variance=9.0, response_variance=4.0, saturation=None), True),
        (ECR(model_variance=9.0, response="binned", saturation=None), True),
    ],
    ids=repr,
)
def test_a_score_says_whether_its_surface_is_its_value_on_each_aligned_pair(score, exact):
    assert score.surface_is_exact is exact


def test_a_score_that_estimates_nothing_from_the_pair_is_held_as_it_is():
    image = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
    for score, variance in ((NCC(), None), (NMI(bins=8), None)):
        assert score.held_fit(image, image.mT, variance) is score
    with pytest.raises(ValueError, match="variance is not used by score 'ncc'"):
        NCC().held_fit(image, image, 1.0)


@pytest.mark.parametrize(
    "score",
    [
        ECR(),
        ECR(response="binned"),
        ECR(response="linear"),
        ECR(model_variance=100.0),
        ECR(model_variance=100.0, response="binned"),
        ECR(response_variance=30.0),
        ECR(model_variance=100.0, response_variance=30.0),
        ECR(model_variance=100.0, response_variance=30.0, saturation=None),
        NMI(),
        ENMI(),
        NCC(),
        Mixture(),
    ],
    ids=repr,
)
def test_a_score_estimates_a_noise_model_exactly_where_holding_one_changes_it(score):
    generator = torch.Generator().manual_seed(5)
    reference = torch.rand(1, 1, 12, 14, generator=generator, dtype=torch.float64) * 256
    captured = reference + 20 * torch.randn(reference.shape, generator=generator, dtype=torch.float64)
    held = score.held_fit(captured, reference, 64.0 if score.uses_variance else None)
    assert score.estimates_noise_model == (held != score)
    assert not held.estimates_noise_model  # what it held is fixed: nothing left to hold
