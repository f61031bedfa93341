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
