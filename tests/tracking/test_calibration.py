"""Temperatures: the grid temperature, calibrate_temperature, and Calibration files."""

from __future__ import annotations

import math

import pytest
import torch

from enmi_torch.tracking import Calibration, calibrate_temperature, grid_temperature


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grid_temperature_caps_each_axis_at_one_bin(dtype):
    # Curvatures 30 (yaw), 6 (rows) and 96 (columns) per bin^2 on a non-square grid whose peak is off-centre: the
    # sharpest axis, the columns, sets 1 + 96 / 12 = 9; a swapped or missed axis gives another number.
    yaw, rows, cols = torch.meshgrid(torch.arange(3.0) - 1, torch.arange(7.0) - 2, torch.arange(9.0) - 5, indexing="ij")
    sharp = -0.5 * (30.0 * yaw**2 + 6.0 * rows**2 + 96.0 * cols**2)
    flat = torch.zeros(3, 7, 9)
    dipped = 0.5 * 96.0 * cols**2  # the maximum at a border, the curvature upwards: counts zero
    log_likelihood = torch.stack([sharp, flat, dipped]).to(dtype)
    assert grid_temperature(log_likelihood).tolist() == pytest.approx([9.0, 1.0, 1.0])
    assert grid_temperature(sharp[:, :, :2][None].to(dtype)).tolist() == pytest.approx([1 + 30.0 / 12])
    at_border = sharp[None, :, :, 1:].clone()  # the peak on the window's first column: read one bin inwards
    assert grid_temperature(at_border.to(dtype)).tolist() == pytest.approx([9.0])
    sharp[0, 0, 0] = -math.inf  # a candidate left out: the smallest finite value, the peak's curvature unchanged
    assert grid_temperature(sharp[None].to(dtype)).tolist() == pytest.approx([9.0])


def test_calibrate_temperature_recovers_the_scale_of_an_overconfident_likelihood():
    generator = torch.Generator().manual_seed(3)
    count, scale = 600, 8.0
    truth = torch.randint(3, 8, (count, 2), generator=generator).double()
    peaks = truth + torch.randn(count, 2, generator=generator, dtype=torch.float64)
    rows, cols = torch.meshgrid(torch.arange(11.0), torch.arange(11.0), indexing="ij")
    log_likelihood = -0.5 * scale * ((rows - peaks[:, :1, None]) ** 2 + (cols - peaks[:, 1:, None]) ** 2)
    index = torch.cat([truth, torch.zeros(count, 1, dtype=torch.float64)], 1)
    # The measured peaks scatter by 1 cell, the likelihood claims 1 / sqrt(8): the right temperature is near 8.
    assert calibrate_temperature(log_likelihood[:, None].double(), index) == pytest.approx(scale, rel=0.3)


@pytest.mark.parametrize("noise_model", [None, "held", "per_frame"])
def test_calibration_round_trips_through_json(tmp_path, noise_model):
    calibration = Calibration("ecr", 123.5, 2.5, noise_model)
    assert Calibration.load(calibration.save(tmp_path / "calibration.json")) == calibration
    (tmp_path / "bad.json").write_text('{"metric": "ecr"}')
    with pytest.raises(ValueError, match="needs keys"):
        Calibration.load(tmp_path / "bad.json")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[1, 2]", "must hold a JSON object .* got a list"),
        ("3", "must hold a JSON object .* got a number 3"),
        ("null", "must hold a JSON object .* got null"),
        ("[" * 100_000 + "]" * 100_000, "nests too deeply"),
        ("{not json", "is not readable JSON"),
        (
            '{"score": "ecr", "temperature": "2", "min_peak_z": 2.5}',
            "temperature must be a finite number, got a string",
        ),
        ('{"score": "ecr", "temperature": NaN, "min_peak_z": 2.5}', "temperature must be a finite number, got nan"),
        (
            '{"score": "ecr", "temperature": Infinity, "min_peak_z": 2.5}',
            "temperature must be a finite number, got inf",
        ),
        ('{"score": "ecr", "temperature": 0, "min_peak_z": 2.5}', r"temperature must be a finite number > 0, got 0"),
        ('{"score": "ecr", "temperature": -3, "min_peak_z": 2.5}', r"temperature must be a finite number > 0, got -3"),
        ('{"score": "ecr", "temperature": 2, "min_peak_z": NaN}', "min_peak_z must be a finite number, got nan"),
        (
            '{"score": "ecr", "temperature": true, "min_peak_z": 1}',
            "temperature must be a finite number, got a boolean",
        ),
        ('{"score": "nope", "temperature": 2, "min_peak_z": 1}', "score must be one of"),
        (
            '{"score": "ecr", "temperature": 2, "min_peak_z": 1, "noise_model": "fixed"}',
            r"noise_model must be one of \['held', 'per_frame'\] or None, got 'fixed'",
        ),
        ('{"score": "ecr", "temperature": 2, "min_peak_z": 1, "bins": 16}', r"may have 'noise_model'\), got \['bins'"),
    ],
)
def test_a_bad_calibration_file_is_refused_naming_the_file_and_the_key(tmp_path, text, match):
    path = tmp_path / "calibration.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as raised:
        Calibration.load(path)
    assert "calibration file" in str(raised.value) and str(path) in str(raised.value)


def test_a_binary_calibration_file_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "calibration.json"
    path.write_bytes(b"\x80\x81\xff\x00")
    with pytest.raises(ValueError, match=r"calibration file .* is not readable JSON: it is not UTF-8 text"):
        Calibration.load(path)


@pytest.mark.parametrize(("temperature", "min_peak_z"), [(math.nan, 1.0), (0.0, 1.0), (-1.0, 1.0), (2.0, math.inf)])
def test_a_calibration_that_could_not_load_is_not_saved(tmp_path, temperature, min_peak_z):
    with pytest.raises(ValueError, match="must be a finite number"):
        Calibration("ecr", temperature, min_peak_z).save(tmp_path / "calibration.json")
    assert not (tmp_path / "calibration.json").exists()


def test_a_calibration_written_before_the_noise_model_was_recorded_loads_as_fitted_per_frame(tmp_path):
    (tmp_path / "old.json").write_text('{"score": "ecr", "temperature": 9.5, "min_peak_z": 3.5}')
    old = Calibration.load(tmp_path / "old.json")
    assert old == Calibration("ecr", 9.5, 3.5) and old.noise_model is None and old.fitted_noise_model == "per_frame"
    assert Calibration("ecr", 9.5, 3.5, "held").fitted_noise_model == "held"


def test_a_calibration_file_that_names_its_score_metric_still_loads(tmp_path):
    (tmp_path / "old.json").write_text('{"metric": "nmi", "temperature": 2.0, "min_peak_z": 3.5}')
    assert Calibration.load(tmp_path / "old.json") == Calibration("nmi", 2.0, 3.5)
    (tmp_path / "wrong.json").write_text('{"score": "mi", "temperature": 2.0, "min_peak_z": 3.5}')
    with pytest.raises(ValueError, match="score must be one of"):
        Calibration.load(tmp_path / "wrong.json")


def _bad_call(case: str):
    calls = {
        "truth shape": lambda: calibrate_temperature(torch.zeros(4, 1, 3, 3), torch.zeros(4, 2)),
    }
    return calls[case]


@pytest.mark.parametrize(
    ("case", "error", "match"),
    [
        ("truth shape", ValueError, r"truth \(N, 3\)"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()
