"""figure_default pairs each method with the default trial by trial, as a direct loop does."""

import csv
import math

import pytest

from data_tools.experiments.yardstick import figure_default, scene_change

COLUMNS = ["case", "sensor", "mean_sigma", "method", "successes", "trials", "outcomes", "tau2"]


def _write(path, rows):
    """A results.csv as scene_change.py writes it."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        for row in rows:
            bits = row["outcomes"]
            writer.writerow({**row, "successes": bits.count("1"), "trials": len(bits), "tau2": ""})
    return path


def _paired(first: str, second: str) -> tuple[float, float]:
    return scene_change.paired_difference(scene_change.outcome_bits(first), scene_change.outcome_bits(second))


def test_paired_difference_is_the_mean_and_standard_error_of_the_per_trial_differences():
    first, second = "1101001110", "1000011011"
    differences = [int(a) - int(b) for a, b in zip(first, second, strict=True)]  # +1 0 -1 ... asymmetric
    mean = sum(differences) / 10
    se = math.sqrt(sum((d - mean) ** 2 for d in differences) / 9 / 10)
    assert _paired(first, second) == pytest.approx((mean, se))
    # Swapping the arguments flips the sign only: pairing, not two separate rates.
    assert _paired(second, first) == pytest.approx((-mean, se))


def test_paired_difference_refuses_unpaired_outcomes():
    with pytest.raises(ValueError, match="same length"):
        _paired("101", "10")


def test_cells_are_kept_apart_by_case_sensor_level_and_set(tmp_path):
    main = _write(
        tmp_path / "main.csv",
        [
            {"case": "same", "sensor": "camera-like", "mean_sigma": "690.0", "method": "ECR true", "outcomes": "1100"},
            {"case": "same", "sensor": "camera-like", "mean_sigma": "690.0", "method": "NCC", "outcomes": "0111"},
            {"case": "same", "sensor": "lidar-like", "mean_sigma": "450.0", "method": "ECR true", "outcomes": "0000"},
            {"case": "same", "sensor": "lidar-like", "mean_sigma": "450.0", "method": "NCC", "outcomes": "1111"},
        ],
    )
    held = _write(
        tmp_path / "held.csv",
        [
            {"case": "same", "sensor": "camera-like", "mean_sigma": "690.0", "method": "ECR true", "outcomes": "1111"},
            {"case": "same", "sensor": "camera-like", "mean_sigma": "690.0", "method": "NCC", "outcomes": "1111"},
        ],
    )
    cells = figure_default.read_cells([main, held], [False, True])
    table = figure_default.differences(cells)["NCC"]
    assert table["same, camera-like, sigma 690"] == pytest.approx(_paired("0111", "1100"))
    assert table["same, lidar-like, sigma 450"] == (1.0, 0.0)
    assert table["same, camera-like, sigma 690 (held out)"] == (0.0, 0.0)


def test_a_cell_without_the_default_is_refused(tmp_path):
    path = _write(
        tmp_path / "bad.csv",
        [{"case": "same", "sensor": "camera-like", "mean_sigma": "690.0", "method": "NCC", "outcomes": "01"}],
    )
    with pytest.raises(ValueError, match="ECR true"):
        figure_default.read_cells([path], [False])


def test_command_line_mistakes_exit_with_code_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        figure_default.main(["--results", str(tmp_path / "missing.csv"), "--held-out"])
    assert exit_info.value.code == 2
    assert "--results" in capsys.readouterr().err


def test_the_committed_results_draw(tmp_path, capsys):
    figure = tmp_path / "figure.png"
    figure_default.main(["--figure", str(figure)])
    assert figure.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "real:another-modality, lidar-like, sigma 82" in printed
    assert "(held out)" in printed
