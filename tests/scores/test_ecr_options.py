"""No score option silently ignored: each takes effect under every value of each other option, or is refused in one
line naming both; ECR's table (ECR_RULES) is the one place that decides, for the constructor and every function."""

import pytest
import torch

from enmi_torch import ECR, ENMI, NCC, NMI, Mixture
from enmi_torch.functional import ecr, ecr_from_bin_sums, ecr_loss, ecr_surface, gaussian_log_prior
from enmi_torch.localization import SearchStrategy
from enmi_torch.scores import ecr_options
from enmi_torch.scores.ecr import BinSums, ecr_model_variance, ecr_surface_model_variance
from enmi_torch.utils.options import OptionConflict, OptionRule


def _pairs():
    """Four aligned pairs ``(4, 1, 24, 20)`` float64 that tell the options apart, and their per-pixel variance.

    Changed patches of the scene (a spatially correlated misfit), a curved and a falling response, values past 256,
    readings clipped at 0, a per-pixel variance that varies, and a clean pair whose misfit is below any bin's
    quantisation: each option of each family moves the score of one of them at least.
    """
    generator = torch.Generator().manual_seed(7)
    rows, cols = torch.meshgrid(torch.arange(24.0), torch.arange(20.0), indexing="ij")
    pattern = 128 + 90 * torch.sin(rows / 3.0) * torch.cos(cols / 4.0)
    reference = (pattern + 20 * torch.rand(4, 1, 24, 20, generator=generator)).double()
    curved, falling = 255 * (reference[1] / 255) ** 2, 300 - reference[2]
    response = torch.stack([reference[0], curved, falling, reference[3]])
    variance = (4.0 + 60.0 * torch.rand(4, 1, 24, 20, generator=generator)).double()
    variance[3] = 0.5 + torch.rand(1, 24, 20, generator=generator, dtype=torch.float64)
    captured = response + variance.sqrt() * torch.randn(4, 1, 24, 20, generator=generator, dtype=torch.float64)
    captured[0, :, 4:14, 3:11] += 70.0  # a changed patch: a misfit that covers neighbouring pixels
    captured[2, :, 12:20, 8:18] -= 60.0
    captured[1] = (captured[1] - 40.0).clamp_min(0.0)  # a sensor that saturates at 0: readings censored there
    return captured, reference, variance


def _log_prior(options):
    return gaussian_log_prior(128.0, 40.0, options.get("bins", 32), options.get("value_range", (0.0, 256.0)))


# Values away from the defaults, per family and option (a callable takes the other options given).
ALTERNATIVES = {
    ECR: {
        "bins": [8],
        "value_range": [(0.0, 320.0)],
        "model_variance": [40.0, None],
        "response": ["binned", "linear"],
        "misfit": ["correlated", "regional"],
        "response_variance": [3.0],
        "saturation": [None, (0.0, 250.0)],
    },
    ENMI: {
        "bins": [8],
        "value_range": [(0.0, 320.0)],
        "kernel": ["density", "truncated"],
        "log_prior": [_log_prior],
        "reliability": [True],
        "reference_kernel": ["triangular"],
    },
    NMI: {"bins": [8], "value_range": [(0.0, 320.0)], "kernel": ["hard", "xu"], "reference_kernel": ["triangular"]},
    Mixture: {"bins": [8], "value_range": [(0.0, 320.0)], "em_steps": [2]},
}


def _value(family, options, pairs):
    captured, reference, variance = pairs
    score = family(**options)
    return score(captured, reference, variance if score.uses_variance else None)


@pytest.mark.parametrize("family", list(ALTERNATIVES), ids=lambda family: family.__name__)
def test_every_option_takes_effect_under_every_value_of_each_other_option_or_is_refused_naming_both(family):
    pairs = _pairs()
    alternatives = ALTERNATIVES[family]
    assert set(alternatives) == set(family.option_names())  # every option of the family is tried
    refused = []
    for option, values in alternatives.items():
        for other, other_values in alternatives.items():
            if other == option:
                continue
            for other_value in [DEFAULT, *other_values]:
                base = {} if other_value is DEFAULT else {other: _given(other_value, {})}
                for value in values:
                    # A log prior has one entry per bin: each is made for the bins and range beside it.
                    given = {} if other_value is DEFAULT else {other: _given(other_value, {option: value})}
                    given[option] = _given(value, base)
                    try:
                        changed = _value(family, given, pairs)
                    except OptionConflict as conflict:  # the one refusal there is: it names both
                        assert {conflict.rule.option, conflict.rule.needs} == {option, other}, str(conflict)
                        assert f"{option}=" in str(conflict) and f"{other}=" in str(conflict)
                        refused.append((option, other))
                        continue
                    unchanged = _value(family, base, pairs)
                    assert not torch.allclose(changed, unchanged, rtol=1e-9, atol=0), (given, changed, unchanged)
    if family is ECR:  # the rows of ECR_RULES, and only they, refuse (whichever of the two leaves its default)
        rows = {("response_variance", "response"), ("misfit", "model_variance")}
        assert set(refused) == rows | {(needs, option) for option, needs in rows}
    else:
        assert refused == []


DEFAULT = object()  # an option left out


def _given(value, others):
    return value(others) if callable(value) else value


def test_ncc_has_no_option_to_ignore():
    assert NCC.option_names() == ()
    with pytest.raises(TypeError):
        NCC(bins=8)


@pytest.mark.parametrize(
    ("given", "message"),
    [
        (
            {"model_variance": 100.0, "misfit": "regional"},
            "misfit='regional' has no effect with model_variance=100.0: it is how an estimated tau^2 treats the "
            "misfit's spatial correlation (a fixed model_variance is used as it is); drop it or pass "
            "model_variance='estimate'",
        ),
        (
            {"model_variance": 100.0, "misfit": "correlated"},
            "misfit='correlated' has no effect with model_variance=100.0",
        ),
        (
            {"model_variance": None, "misfit": "correlated"},
            "misfit='correlated' has no effect with model_variance=None",
        ),
        (
            {"response": "linear", "response_variance": 3.0},
            "response_variance=3.0 has no effect with response='linear': it is the shrunk response's delta^2; drop it "
            "or pass response='shrunk'",
        ),
        ({"response": "binned", "response_variance": 0}, "response_variance=0.0 has no effect with response='binned'"),
    ],
)
def test_the_constructor_and_every_function_refuse_a_moot_option_with_one_line(given, message):
    captured, reference, variance = _pairs()
    window = reference[:1]
    calls = {
        "ECR": lambda: ECR(**given),
        "replace": lambda: ECR().replace(**given),
        "ecr": lambda: ecr(captured, reference, variance, **given),
        "ecr_model_variance": lambda: ecr_model_variance(captured, reference, variance, **given),
        "ecr_loss": lambda: ecr_loss(captured, reference, variance, **given),
        "ecr_surface": lambda: ecr_surface(captured[:1, :, 2:20, 3:17], window, variance[:1, :, 2:20, 3:17], **given),
        "ecr_surface_model_variance": lambda: ecr_surface_model_variance(
            captured[:1, :, 2:20, 3:17], window, variance[:1, :, 2:20, 3:17], **given
        ),
    }
    if "response_variance" in given:  # the model variance's functions take no delta^2
        del calls["ecr_model_variance"], calls["ecr_surface_model_variance"]
    for name, call in calls.items():
        with pytest.raises(ValueError) as refusal:
            call()
        assert str(refusal.value) == message or str(refusal.value).startswith(message), name
        assert "\n" not in str(refusal.value)


def test_ecr_from_bin_sums_refuses_a_delta2_for_the_binned_response_and_takes_it_for_the_shrunk_one():
    sums = BinSums(torch.tensor([[2.0, 2.0, 3.0]]), torch.tensor([[2.0, 2.0, 3.0]]), torch.tensor([[-4.0, 1.0, 5.0]]))
    with pytest.raises(ValueError, match=r"^response_variance=3.0 has no effect with response='binned'"):
        ecr_from_bin_sums(sums, response="binned", response_variance=3.0)
    with pytest.raises(ValueError, match=r"^response_variance=tensor\(\[3.\]\) has no effect with response='binned'"):
        ecr_from_bin_sums(sums, response="binned", response_variance=torch.tensor([3.0]))
    binned = ecr_from_bin_sums(sums, response="binned")
    assert torch.equal(ecr_from_bin_sums(sums, response="binned", response_variance="estimate"), binned)
    line, free = (ecr_from_bin_sums(sums, value_range=(0.0, 3.0), response_variance=delta2) for delta2 in (0.0, 1e9))
    assert not torch.allclose(line, free)  # where it applies, it takes effect


def test_options_at_their_defaults_never_trip_a_rule():
    captured, reference, variance = _pairs()
    assert ECR(response="linear", response_variance="estimate") == ECR(response="linear")
    assert ECR(model_variance=40.0, misfit="independent") == ECR(model_variance=40.0)
    torch.testing.assert_close(
        ecr(captured, reference, variance, response="binned", response_variance="estimate"),
        ecr(captured, reference, variance, response="binned"),
    )
    for score in (ECR(model_variance=None), ECR(response="linear"), ECR(misfit="regional"), ECR(response_variance=0)):
        assert score.replace() == score and type(score)(**score.options) == score


def test_the_table_is_the_one_place_that_decides(monkeypatch):
    """A row added to ECR_RULES is refused by the constructor and the functions alike; without rows, nothing is."""
    captured, reference, variance = _pairs()
    row = OptionRule("bins", "response", ("binned",), "a row of this test")
    monkeypatch.setattr(ecr_options, "ECR_RULES", (row,))
    for call in (
        lambda: ECR(bins=8),
        lambda: ecr(captured, reference, variance, bins=8),
        lambda: ecr_surface(captured[:1, :, 2:20, 3:17], reference[:1], variance[:1, :, 2:20, 3:17], bins=8),
    ):
        with pytest.raises(OptionConflict, match=r"bins=8 has no effect with response='shrunk': it is a row of this"):
            call()
    assert ECR(bins=8, response="binned").bins == 8
    monkeypatch.setattr(ecr_options, "ECR_RULES", ())
    assert ECR(model_variance=3.0, misfit="regional").misfit == "regional"


def test_a_two_stage_search_with_a_correlated_misfit_keeps_it_where_it_applies(generator):
    """The two-stage search's rough score has a fixed tau^2: it drops the misfit instead of being refused."""
    from enmi_torch import localize

    reference = torch.rand(1, 1, 48, 40, generator=generator) * 256
    captured = reference[..., 10:34, 8:28] + 4 * torch.randn(1, 1, 24, 20, generator=generator)
    score = ECR(bins=16, misfit="correlated")
    rough = score.rough_score(4, reference)
    assert rough.misfit == "independent" and rough.model_variance is None and rough.bins == 4
    found = localize(
        captured, reference, 16.0, score=score, shifts=6, center=(22, 18), search=SearchStrategy("two_stage")
    )
    assert [*found.shift[0].round().tolist(), float(found.yaw[0])] == [0.0, 0.0, 0.0]
