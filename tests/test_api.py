"""The public API's tiers: about twenty names at the top level, the functions in enmi_torch.functional, the rest in
their modules; names that left the top level still resolve there for one release, with a DeprecationWarning."""

import importlib
import re
import warnings

import pytest

import enmi_torch
import enmi_torch.functional

TOP_LEVEL = {
    *("NMI", "ENMI", "ECR", "NCC", "Mixture"),
    *("ScoreLoss", "NMILoss", "ENMILoss", "ECRLoss"),
    *("PerspectiveVariance", "LearnedVariance", "EmpiricalVariance", "ConstantVariance"),
    *("RoadCamera", "GroundGrid", "rectify", "unrectify"),
    *("localize", "Localization", "register", "Registration", "Tracker", "TrackerSettings"),
}


def test_the_top_level_holds_the_user_s_names():
    assert set(enmi_torch.__all__) == TOP_LEVEL and len(enmi_torch.__all__) == 23
    for name in enmi_torch.__all__:
        assert getattr(enmi_torch, name).__name__ == name
    assert "functional" in dir(enmi_torch) and enmi_torch.functional is enmi_torch.functional


@pytest.mark.parametrize("name", sorted(enmi_torch._MOVED))
def test_a_moved_name_warns_with_its_new_place_and_resolves(name):
    place = enmi_torch._MOVED[name]
    expected = getattr(importlib.import_module(place), name)
    message = re.escape(f"enmi_torch.{name} is deprecated and will be removed in 0.3; use {place}.{name}") + "$"
    with pytest.warns(DeprecationWarning, match=message):
        value = getattr(enmi_torch, name)
    assert value is expected
    assert name not in enmi_torch.__all__ and name not in dir(enmi_torch)
    with pytest.warns(DeprecationWarning):  # every use warns, not the first only
        getattr(enmi_torch, name)


def test_from_import_of_a_moved_name_warns():
    with pytest.warns(DeprecationWarning, match="use enmi_torch.functional.nmi_surface"):
        from enmi_torch import nmi_surface
    assert nmi_surface is enmi_torch.functional.nmi_surface


def test_the_top_level_names_do_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in enmi_torch.__all__:
            getattr(enmi_torch, name)
        enmi_torch.functional.nmi  # noqa: B018


def test_every_name_that_left_the_top_level_has_a_shim():
    # The 67 names of the flat API, less those that stay (TrackerSettings is new).
    former = set(enmi_torch._MOVED) | (TOP_LEVEL - {"TrackerSettings"})
    assert len(former) == 67 and not set(enmi_torch._MOVED) & set(enmi_torch.__all__)
