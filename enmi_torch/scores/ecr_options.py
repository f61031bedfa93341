"""ECR's options: each one checked, and the table of which options take effect under which values of the others.

:data:`ECR_RULES` is the one place that decides which combinations mean something: :class:`~enmi_torch.ECR`'s
constructor checks it (:func:`check_ecr_options`), and so does every function that takes ECR's options
(:func:`~enmi_torch.scores.ecr.ecr`, :func:`~enmi_torch.scores.ecr.ecr_surface`,
:func:`~enmi_torch.scores.ecr.ecr_from_bin_sums`, ...; :data:`ecr_options_checked`). An option that another makes moot
is refused in one line naming both, unless it is left at its default.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import Tensor

from enmi_torch.scores.censoring import check_saturation
from enmi_torch.scores.ecr_model_variance import (
    MISFITS,
    MODEL_VARIANCE_ESTIMATE,
    check_model_variance,
    check_response_variance,
)
from enmi_torch.utils.checks import check_bins, check_option, check_value_range
from enmi_torch.utils.options import OptionRule, check_option_rules, options_checked

RESPONSES = ("shrunk", "binned", "linear")

# Which options take effect under which values of the others; a new option that depends on another is one more row.
ECR_RULES = (
    OptionRule("response_variance", "response", ("shrunk",), "the shrunk response's delta^2"),
    OptionRule(
        "misfit",
        "model_variance",
        (MODEL_VARIANCE_ESTIMATE,),
        "how an estimated tau^2 treats the misfit's spatial correlation (a fixed model_variance is used as it is)",
    ),
)


def check_ecr_options(options: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict[str, Any]:
    """ECR's options among ``options`` each checked, then against :data:`ECR_RULES`; returns them checked.

    ``defaults``: those of the function or constructor that took them (an option at its default breaks no rule).
    ``model_variance=None`` stays ``None`` (``bin_width^2 / 12``); a tensor ``response_variance`` (a surface's per
    image ``delta^2``) is taken as it is.

    Example:
        >>> check_ecr_options({"response": "linear", "response_variance": 3.0}, {"response_variance": "estimate"})
        Traceback (most recent call last):
        ...
        enmi_torch.utils.options.OptionConflict: response_variance=3.0 has no effect with response='linear': ...
    """
    checked = dict(options)  # the rows may name any of them (a new option: one more row, and its check here)
    if "bins" in checked:
        checked["bins"] = check_bins(checked["bins"])
    if "value_range" in checked:
        checked["value_range"] = check_value_range(checked["value_range"])
    if checked.get("model_variance") is not None:  # None's value needs the bins, never refused
        checked["model_variance"] = check_model_variance(checked["model_variance"], None, None)
    if "response" in checked:
        check_option("response", checked["response"], RESPONSES)
    if "misfit" in checked:
        check_option("misfit", checked["misfit"], MISFITS)
    if "response_variance" in checked and not isinstance(checked["response_variance"], Tensor):
        checked["response_variance"] = check_response_variance(checked["response_variance"])
    if "saturation" in checked:  # takes effect under every value of the others: no row
        checked["saturation"] = check_saturation(checked["saturation"])
    check_option_rules(ECR_RULES, checked, defaults)
    return checked


# The decorator of the functions that take ECR's options.
ecr_options_checked = options_checked(check_ecr_options)
