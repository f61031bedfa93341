"""enmi_torch.functional: the functions behind the scores and losses, the same objects as in their modules."""

import importlib

import pytest
import torch

from enmi_torch import functional

HOMES = {
    "enmi_torch.binning": [
        "bin_centers",
        "bin_edges",
        "gaussian_log_prior",
        "likelihood_weights",
        "parzen_weights",
        "truncated_likelihood_weights",
    ],
    "enmi_torch.histogram": ["joint_histogram"],
    "enmi_torch.information": ["entropies", "nmi_from_joint_histogram"],
    "enmi_torch.scores.ecr": ["ecr", "ecr_from_bin_sums", "ecr_loss", "ecr_surface"],
    "enmi_torch.scores.enmi": ["enmi", "enmi_loss", "enmi_surface"],
    "enmi_torch.scores.mixture": ["mixture_information", "mixture_loss", "mixture_surface"],
    "enmi_torch.scores.ncc": ["ncc", "ncc_loss", "ncc_surface"],
    "enmi_torch.scores.nmi": ["nmi", "nmi_loss", "nmi_surface"],
}


def test_the_functions_are_those_of_their_modules():
    names = [name for names in HOMES.values() for name in names]
    assert sorted(functional.__all__) == sorted(names)
    for module, module_names in HOMES.items():
        for name in module_names:
            assert getattr(functional, name) is getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("family", ["nmi", "enmi", "ecr", "ncc", "mixture_information"])
def test_each_function_is_its_score_object(family):
    from enmi_torch.scores import as_score

    generator = torch.Generator().manual_seed(5)
    reference = torch.rand(2, 1, 12, 12, generator=generator, dtype=torch.float64) * 256
    captured = reference + 9 * torch.randn(2, 1, 12, 12, generator=generator, dtype=torch.float64)
    name = "mixture" if family == "mixture_information" else family
    score = as_score(name)
    variance = (81.0,) if score.uses_variance else ()
    torch.testing.assert_close(
        getattr(functional, family)(captured, reference, *variance), score(captured, reference, *variance)
    )
