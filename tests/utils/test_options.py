"""The option tables' machinery: rules, their refusal spelt either way, defaults, keywords that moved."""

import pytest

from enmi_torch.utils.options import (
    MovedKeywords,
    OptionConflict,
    OptionError,
    OptionRule,
    check_option_rules,
    options_checked,
    refuse_moved_keywords,
    signature_defaults,
)

RULES = (
    OptionRule("delta", "response", ("shrunk", "smooth"), "the pull toward a line"),
    OptionRule("peaks", "factor", lambda factor: factor > 1, "the coarse peaks refined", "factor > 1"),
)


def make(*, response="shrunk", delta="estimate", factor=1, peaks=3, flag=False):
    return response, delta, factor, peaks, flag


DEFAULTS = signature_defaults(make)


def test_a_rule_refuses_an_option_away_from_its_default_where_the_other_makes_it_moot():
    with pytest.raises(OptionConflict) as refusal:
        check_option_rules(RULES, {"response": "linear", "delta": 2.0}, DEFAULTS)
    assert str(refusal.value) == (
        "delta=2.0 has no effect with response='linear': it is the pull toward a line; drop it or pass "
        "response='shrunk' or response='smooth'"
    )
    assert refusal.value.rule is RULES[0] and (refusal.value.value, refusal.value.other) == (2.0, "linear")
    with pytest.raises(OptionConflict, match=r"^peaks=5 has no effect with factor=1: .*; drop it or pass factor > 1$"):
        check_option_rules(RULES, {"factor": 1, "peaks": 5}, DEFAULTS)
    for fine in (
        {"response": "smooth", "delta": 2.0},  # the option applies
        {"response": "linear", "delta": "estimate"},  # at its default, given or not
        {"response": "linear"},
        {"factor": 2, "peaks": 5},
        {"factor": 1, "peaks": 3.0},  # a default compares by value
        {"delta": 2.0},  # the other option is not among those given (a function that takes one of them)
    ):
        check_option_rules(RULES, fine, DEFAULTS)


def test_a_bool_or_tensor_is_its_default_only_by_identity():
    import torch

    rules = (OptionRule("flag", "response", ("shrunk",), "a flag"),)
    with pytest.raises(OptionConflict, match="flag=0 has no effect"):
        check_option_rules(rules, {"response": "linear", "flag": 0}, DEFAULTS)  # 0 == False, but not False
    check_option_rules(rules, {"response": "linear", "flag": False}, DEFAULTS)
    rules = (OptionRule("delta", "response", ("shrunk",), "a tensor"),)
    with pytest.raises(OptionConflict, match=r"delta=tensor\(1.\) has no effect"):
        check_option_rules(rules, {"response": "linear", "delta": torch.tensor(1.0)}, {"delta": torch.tensor(1.0)})
    rules = (OptionRule("peaks", "response", ("shrunk",), "a tensor beside"),)  # a tensor is no value in a tuple
    with pytest.raises(OptionConflict):
        check_option_rules(rules, {"response": torch.tensor(1.0), "peaks": 5}, DEFAULTS)


def test_a_refusal_is_spelt_as_its_caller_takes_the_options():
    with pytest.raises(OptionConflict) as refusal:
        check_option_rules(RULES, {"response": "linear", "delta": 2.0}, DEFAULTS)

    def flag(name, value):
        return f"--option {name}={value}"

    assert refusal.value.spelled(flag) == (
        "--option delta=2.0 has no effect with --option response=linear: it is the pull toward a line; drop it or "
        "pass --option response=shrunk or --option response=smooth"
    )
    error = OptionError(lambda spell: f"too small for {spell('shift', 4)}")
    assert isinstance(error, ValueError) and str(error) == "too small for shift=4"
    assert error.spelled(lambda name, value: f"--model.{name} {value}") == "too small for --model.shift 4"


def test_a_function_checked_by_a_family_check_refuses_what_the_check_refuses():
    seen = []

    def check(options, defaults):
        seen.append((options, defaults))
        check_option_rules(RULES, options, defaults)

    @options_checked(check)
    def score(captured, *, response="shrunk", delta="estimate"):
        return captured

    assert score(1.0) == 1.0 and seen[-1] == ({"response": "shrunk", "delta": "estimate", "captured": 1.0}, seen[-1][1])
    assert seen[-1][1] == {"response": "shrunk", "delta": "estimate"}
    with pytest.raises(OptionConflict, match="delta=1 has no effect with response='linear'"):
        score(1.0, response="linear", delta=1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'bins'"):  # Python's own words for a wrong call
        score(1.0, bins=8)
    assert score.__name__ == "score" and signature_defaults(score) == {"response": "shrunk", "delta": "estimate"}


SEARCH = MovedKeywords(("coarse_factor", "cheap_bins"), "search", "SearchStrategy", "enmi_torch.localization")
SCORE = MovedKeywords(
    ("metric", "bins"), "score", "ECR", "enmi_torch", lambda given: (given["metric"].upper(), ("metric",))
)


class Finder:
    @refuse_moved_keywords(SEARCH, SCORE)
    def __init__(self, *, search=None, score=None):
        self.search, self.score = search, score


def test_moved_keywords_are_refused_naming_their_new_home_and_the_call_that_takes_them():
    with pytest.raises(TypeError) as refusal:
        Finder(cheap_bins=8)
    assert str(refusal.value) == (
        "Finder() takes cheap_bins in search=SearchStrategy(...): pass search=SearchStrategy(..., cheap_bins=8) "
        "(enmi_torch.localization)"
    )
    with pytest.raises(TypeError) as refusal:
        Finder(coarse_factor=2, metric="nmi", bins=16)
    assert str(refusal.value) == (
        "Finder() takes coarse_factor in search=SearchStrategy(...): pass search=SearchStrategy(..., coarse_factor=2) "
        "(enmi_torch.localization); Finder() takes metric, bins in score=NMI(...): pass score=NMI(..., bins=16) "
        "(enmi_torch)"
    )
    with pytest.raises(
        TypeError, match=r"takes metric in score=NMI\(\.\.\.\): pass score=NMI\(\.\.\.\) \(enmi_torch\)$"
    ):
        Finder(metric="nmi")
    assert Finder(search="two_stage").search == "two_stage"
