"""SearchStrategy: every field takes effect or is refused naming the field that makes it moot; keywords that moved."""

import pytest
import torch

from enmi_torch import ECR, ENMI, localize
from enmi_torch.localization import Localizer, SearchStrategy
from enmi_torch.localization.strategy import SEARCH_RULES


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (
            {"cheap_bins": 8},
            "cheap_bins=8 has no effect with method='exhaustive': it is the bins of the two-stage search's first "
            "stage; drop it or pass method='two_stage'",
        ),
        ({"coarse_factor": 2, "cheap_bins": 8}, "cheap_bins=8 has no effect with method='exhaustive'"),
        (
            {"coarse_peaks": 5},
            "coarse_peaks=5 has no effect with coarse_factor=1: it is the number of coarse candidates a "
            "coarse-to-fine search refines; drop it or pass coarse_factor > 1 (a coarse-to-fine search)",
        ),
        ({"method": "two_stage", "coarse_peaks": 5}, "coarse_peaks=5 has no effect with coarse_factor=1"),
    ],
)
def test_a_field_that_another_makes_moot_is_refused_in_one_line(fields, message):
    with pytest.raises(ValueError) as refusal:
        SearchStrategy(**fields)
    assert str(refusal.value) == message or str(refusal.value).startswith(message + ":")


def test_fields_where_they_apply_and_defaults_are_taken():
    assert SearchStrategy("two_stage", cheap_bins=8).cheap_bins == 8
    assert SearchStrategy(coarse_factor=2, coarse_peaks=5).coarse_peaks == 5
    assert SearchStrategy("exhaustive", cheap_bins=4, coarse_peaks=3) == SearchStrategy()  # the defaults, given
    assert [rule.option for rule in SEARCH_RULES] == ["cheap_bins", "coarse_peaks"]


def test_each_field_takes_effect_where_it_applies(generator):
    """cheap_bins changes the two-stage search's rough surface; coarse_peaks the candidates refined coarse to fine."""
    reference = torch.rand(1, 1, 96, 80, generator=generator) * 256
    captured = reference[..., 30:62, 20:52] + 6 * torch.randn(1, 1, 32, 32, generator=generator)
    options = {"score": ECR(bins=16), "shifts": 14, "center": (46, 36)}

    def surface(search):
        return localize(captured, reference, 36.0, search=search, **options).surface

    rough = [torch.isfinite(surface(SearchStrategy("two_stage", cheap_bins=bins))) for bins in (2, 16)]
    assert not torch.equal(*rough)  # other placements rescored
    refined = [torch.isfinite(surface(SearchStrategy(coarse_factor=4, coarse_peaks=peaks))) for peaks in (1, 6)]
    assert int(refined[0].sum()) < int(refined[1].sum())


def test_localize_and_localizer_refuse_the_score_keywords_of_0_1_naming_the_score_to_pass():
    reference = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0)) * 255
    captured = reference[..., 8:24, 8:24].clone()
    with pytest.raises(TypeError) as refusal:
        localize(captured, reference, 4.0, shifts=2, metric="enmi", bins=16, kernel="density")
    assert str(refusal.value) == (
        "localize() takes metric, bins, kernel in score=ENMI(...): pass score=ENMI(..., bins=16, kernel='density') "
        "(a score of enmi_torch: ECR, ENMI, NMI, NCC or Mixture)"
    )
    with pytest.raises(TypeError, match=r"^Localizer\(\) takes model_variance in score=ECR\(\.\.\.\): pass score=ECR"):
        Localizer(model_variance=4.0)
    with pytest.raises(TypeError, match=r"localize\(\) takes coarse_peaks in search=SearchStrategy\(\.\.\.\)"):
        localize(captured, reference, 4.0, shifts=2, coarse_peaks=2)
    found = localize(captured, reference, 4.0, shifts=2, score=ENMI(bins=16, kernel="density"))
    assert [*found.shift[0].round().tolist(), float(found.yaw[0])] == [0.0, 0.0, 0.0]


def test_a_checked_strategy_cannot_be_changed_past_its_checks():
    import dataclasses

    search = SearchStrategy()
    with pytest.raises(dataclasses.FrozenInstanceError):
        search.cheap_bins = 8
    with pytest.raises(ValueError, match="cheap_bins=8 has no effect"):  # a changed copy is checked again
        dataclasses.replace(search, cheap_bins=8)
