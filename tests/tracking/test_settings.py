"""TrackerSettings: bad settings are refused naming the setting."""

from __future__ import annotations

import pytest

from enmi_torch.tracking import TrackerSettings


def _bad_call(case: str):
    calls = {
        "temperature": lambda: TrackerSettings(temperature=0.0),
        "temperature name": lambda: TrackerSettings(temperature="grid"),
        "patience": lambda: TrackerSettings(patience=0),
        "coasting": lambda: TrackerSettings(coasting="constant"),
        "weak update": lambda: TrackerSettings(weak_update="use"),
        "motion noise": lambda: TrackerSettings(motion_noise=(0.1, 0.1)),
    }
    return calls[case]


@pytest.mark.parametrize(
    ("case", "error", "match"),
    [
        ("temperature", ValueError, "temperature must be a finite number > 0"),
        ("temperature name", ValueError, "temperature must be 'auto' or a finite number > 0, got 'grid'"),
        ("patience", ValueError, "patience must be an int >= 1"),
        ("coasting", ValueError, r"coasting must be one of \['linear', 'random_walk'\], got 'constant'"),
        ("weak update", ValueError, r"weak_update must be one of \['nudge', 'skip'\], got 'use'"),
        ("motion noise", ValueError, "motion_noise must be three standard deviations >= 0"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()


@pytest.mark.parametrize(
    ("field", "value", "error", "match"),
    [
        (
            "z_drop",
            1.5,
            ValueError,
            r"z_drop must be a fraction in \(0, 1\] of the recent matches' peak z-score, got 1.5",
        ),
        ("z_drop", 0.0, ValueError, "z_drop must be a finite number > 0, got 0.0"),
        ("z_drop", float("nan"), ValueError, "z_drop must be a finite number > 0"),
        ("min_peak_z", 0, ValueError, "min_peak_z must be a finite number > 0, got 0"),
        ("min_peak_z", float("inf"), ValueError, "min_peak_z must be a finite number > 0"),
        ("max_surprise", -1.0, ValueError, "max_surprise must be a finite number > 0"),
        ("patience", 1.5, TypeError, "patience must be an int"),
        ("relocalize_shifts", -1, ValueError, "relocalize_shifts must be an int >= 0"),
        ("relocalize_yaw_bins", 0, ValueError, "relocalize_yaw_bins must be an int >= 1"),
        ("coarse_factor", 0, ValueError, "coarse_factor must be an int >= 1"),
        ("relocalize_odds", float("inf"), ValueError, "relocalize_odds must be a finite number > 0"),
        ("refine", "yes", TypeError, "refine must be a bool"),
        ("mismatch_probability", 1.0, ValueError, "mismatch_probability must be"),
        ("mismatch_probability", -0.1, ValueError, "mismatch_probability must be"),
        ("motion_noise", (0.5, -0.1, 0.5), ValueError, "motion_noise must be three standard deviations >= 0"),
        ("motion_noise", (0.5, float("nan"), 0.5), ValueError, "motion_noise must be three standard deviations >= 0"),
        ("temperature", float("inf"), ValueError, "temperature must be a finite number > 0"),
    ],
)
def test_every_field_is_refused_outside_its_documented_range(field, value, error, match):
    with pytest.raises(error, match=match):
        TrackerSettings(**{field: value})
    with pytest.raises(error, match=match):  # a changed copy is checked again
        TrackerSettings().replace(**{field: value})


def test_the_edges_of_the_documented_ranges_are_taken():
    settings = TrackerSettings(z_drop=1, relocalize_shifts=0, mismatch_probability=0.0, motion_noise=(0, 0, 0))
    assert settings.z_drop == 1.0 and isinstance(settings.z_drop, float) and settings.relocalize_shifts == 0


def test_a_keyword_that_moved_to_the_settings_is_refused_naming_them_by_tracker_and_track_step():
    import dataclasses

    import torch

    from enmi_torch import Tracker
    from enmi_torch.tracking import initial_belief, track_step

    reference = torch.rand(1, 1, 48, 48, generator=torch.Generator().manual_seed(0)) * 256
    belief = initial_belief(torch.tensor([[24.0, 24.0, 0.0]]), shifts=3, yaw_bins=1)
    frame = (reference[..., 16:32, 16:32], reference, torch.zeros(1, 3), 4.0)
    with pytest.raises(TypeError) as refusal:
        Tracker(reference, motion_noise=(1.0, 1.0, 0.5))
    assert str(refusal.value) == (
        "Tracker() takes motion_noise in settings=TrackerSettings(...): pass "
        "settings=TrackerSettings(..., motion_noise=(1.0, 1.0, 0.5)) (enmi_torch.TrackerSettings)"
    )
    with pytest.raises(TypeError) as refusal:
        track_step(belief, *frame, motion_noise=(1.0, 1.0, 0.5), z_drop=0.5)
    assert str(refusal.value) == (
        "track_step() takes motion_noise, z_drop in settings=TrackerSettings(...): pass "
        "settings=TrackerSettings(..., motion_noise=(1.0, 1.0, 0.5), z_drop=0.5) (enmi_torch.TrackerSettings)"
    )
    for field in dataclasses.fields(TrackerSettings):  # every one of them moved
        value = getattr(TrackerSettings(), field.name)
        with pytest.raises(TypeError, match=rf"^Tracker\(\) takes {field.name} in settings=TrackerSettings\(\.\.\.\)"):
            Tracker(reference, **{field.name: value})
        with pytest.raises(TypeError, match=rf"^track_step\(\) takes {field.name} in settings=TrackerSettings"):
            track_step(belief, *frame, **{field.name: value})
    with pytest.raises(
        TypeError, match=r"^Tracker\(\) takes metric, bins in score=NMI\(\.\.\.\): pass score=NMI\(\.\.\., bins=8\)"
    ):
        Tracker(reference, metric="nmi", bins=8)
    settings = TrackerSettings(motion_noise=(1.0, 1.0, 0.5), z_drop=0.5)
    _, output, _ = track_step(belief, *frame, settings=settings)
    assert output.pose.round().tolist() == [[24.0, 24.0, 0.0]]


def test_checked_settings_cannot_be_changed_past_their_checks():
    import dataclasses

    settings = TrackerSettings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.z_drop = 1.5
    with pytest.raises(ValueError, match="z_drop must be a fraction"):  # a changed copy is checked again
        dataclasses.replace(settings, z_drop=1.5)
