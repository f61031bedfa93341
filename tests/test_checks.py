"""Checks shared by every public function: an empty batch is refused the same way everywhere."""

import pytest
import torch

from enmi_torch import (
    ENMILoss,
    NMILoss,
    direct_surface,
    ecr,
    enmi,
    enmi_surface,
    joint_histogram,
    mixture_information,
    ncc_surface,
    nmi,
    nmi_surface,
)
from enmi_torch.data import match_intensity
from enmi_torch.histogram import hard_entropies
from enmi_torch.localization.search import localize
from enmi_torch.variance import EmpiricalVariance, LearnedVariance, empirical_variance, gaussian_nll

EMPTY = torch.zeros(0, 1, 4, 4)
WINDOW = torch.zeros(1, 1, 8, 8)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        ("captured", lambda: nmi(EMPTY, EMPTY)),
        ("captured", lambda: nmi(EMPTY, EMPTY, kernel="triangular")),
        ("captured", lambda: enmi(EMPTY, EMPTY, 1.0)),
        ("captured", lambda: joint_histogram(EMPTY, EMPTY)),
        ("captured", lambda: hard_entropies(EMPTY, EMPTY)),
        ("captured", lambda: NMILoss()(EMPTY, EMPTY)),
        ("captured", lambda: ENMILoss()(EMPTY, EMPTY, variance=1.0)),
        ("captured", lambda: nmi(torch.zeros(2, 1, 0, 4), torch.zeros(2, 1, 0, 4))),
        ("captured", lambda: enmi_surface(EMPTY, WINDOW, 1.0)),
        ("captured", lambda: nmi_surface(EMPTY, WINDOW)),
        ("captured", lambda: ncc_surface(EMPTY, WINDOW)),
        ("captured", lambda: direct_surface("nmi", EMPTY, WINDOW)),
        ("captured", lambda: localize(EMPTY, WINDOW, 1.0, shifts=1)),
        ("residual", lambda: gaussian_nll(EMPTY, torch.zeros(4, 4))),
        ("captured", lambda: LearnedVariance((4, 4)).nll(EMPTY, EMPTY)),
        ("captured", lambda: empirical_variance(EMPTY, EMPTY)),
        ("captured", lambda: EmpiricalVariance((4, 4)).update(EMPTY, EMPTY)),
        ("captured", lambda: match_intensity(EMPTY, EMPTY)),
    ],
)
def test_an_empty_batch_is_refused_the_same_way_everywhere(name, call):
    with pytest.raises(ValueError, match=rf"^{name} must hold at least one sample and one pixel, got shape \("):
        call()


def test_images_in_unit_range_against_the_default_bins_are_refused_everywhere():
    import enmi_torch
    from enmi_torch import enmi_surface, nmi_surface

    unit = torch.rand(2, 1, 12, 10, generator=torch.Generator().manual_seed(0))
    message = r"captured varies .* but all its valid pixels fall in one of the 32 bins of value_range=\(0.0, 256.0\)"
    calls = [
        lambda: enmi_torch.nmi(unit, unit),
        lambda: enmi_torch.enmi(unit, unit, 0.01),
        lambda: enmi_torch.joint_histogram(unit, unit),
        lambda: enmi_torch.NMILoss()(unit, unit),
        lambda: enmi_torch.ENMILoss()(unit, unit, variance=0.01),
        lambda: enmi_torch.mixture_information(unit, unit, 0.01),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=message):
            call()
    local_message = r"captured varies .* all its valid pixels fall in one of the 32 bins"
    for call in (
        lambda: nmi_surface(unit[..., :6, :5], unit),
        lambda: enmi_surface(unit[..., :6, :5], unit, 0.01),
        lambda: enmi_torch.localize(unit[..., :6, :5], unit, 0.01, shifts=1, score="enmi"),
    ):
        with pytest.raises(ValueError, match=local_message):
            call()
    # The right range scores them; a constant image is still a valid (uninformative) input.
    assert enmi_torch.nmi(unit, unit, value_range=(0.0, 1.0)).tolist() == pytest.approx([2.0, 2.0])
    assert enmi_torch.nmi(torch.full_like(unit, 0.5), unit * 255).tolist() == [1.0, 1.0]
    # ECR models the captured values themselves (any units); only its reference is binned.
    assert torch.isfinite(enmi_torch.ecr(unit, unit * 255, 0.01)).all()


def test_value_checks_switch_turns_value_checks_off_and_on_everywhere():
    import enmi_torch

    unit = torch.rand(1, 1, 6, 6, generator=torch.Generator().manual_seed(1))
    with enmi_torch.value_checks(False):
        assert enmi_torch.nmi(unit, unit).tolist() == [1.0]  # unchecked: the caller's responsibility
    with pytest.raises(ValueError, match="captured varies"):
        enmi_torch.nmi(unit, unit)
    with enmi_torch.value_checks(True), pytest.raises(ValueError, match="captured varies"):
        enmi_torch.nmi(unit, unit)
    with pytest.raises(TypeError, match="enabled must be True, False or None"):
        with enmi_torch.value_checks("off"):
            pass


@pytest.mark.parametrize(
    "call",
    [
        lambda value_range: nmi(WINDOW, WINDOW, value_range=value_range),
        lambda value_range: enmi(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: joint_histogram(WINDOW, WINDOW, value_range=value_range),
        lambda value_range: ecr(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: mixture_information(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: nmi_surface(WINDOW[..., :4, :4], WINDOW, value_range=value_range),
    ],
)
def test_a_value_range_whose_width_overflows_is_refused_by_every_binned_function(call):
    with pytest.raises(ValueError, match=r"value_range must have a finite width .* got \(-1e\+308, 1e\+308\)"):
        call((-1e308, 1e308))
