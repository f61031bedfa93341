"""Checks shared by every public function: an empty batch is refused the same way everywhere."""

import pytest
import torch

from enmi_torch import ENMILoss, NMILoss, enmi, joint_histogram, nmi
from enmi_torch.data import match_intensity
from enmi_torch.histogram import hard_entropies
from enmi_torch.localize import localize
from enmi_torch.score_surface import direct_surface, enmi_surface, ncc_surface, nmi_surface
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
        ("captured", lambda: ENMILoss()(EMPTY, EMPTY, 1.0)),
        ("captured", lambda: nmi(torch.zeros(2, 1, 0, 4), torch.zeros(2, 1, 0, 4))),
        ("local", lambda: enmi_surface(EMPTY, WINDOW, 1.0)),
        ("local", lambda: nmi_surface(EMPTY, WINDOW)),
        ("local", lambda: ncc_surface(EMPTY, WINDOW)),
        ("local", lambda: direct_surface(EMPTY, WINDOW, metric="nmi")),
        ("local", lambda: localize(EMPTY, WINDOW, 1.0, shifts=1)),
        ("residual", lambda: gaussian_nll(EMPTY, torch.zeros(4, 4))),
        ("local", lambda: LearnedVariance((4, 4)).nll(EMPTY, EMPTY)),
        ("local", lambda: empirical_variance(EMPTY, EMPTY)),
        ("local", lambda: EmpiricalVariance((4, 4)).update(EMPTY, EMPTY)),
        ("prior", lambda: match_intensity(EMPTY, EMPTY)),
    ],
)
def test_an_empty_batch_is_refused_the_same_way_everywhere(name, call):
    with pytest.raises(ValueError, match=rf"^{name} must hold at least one sample and one pixel, got shape \("):
        call()
