"""The drives over photographs of two dates of ``data_tools.experiments.drive.photo_drive``."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch

from data_tools.experiments.drive import photo_drive


def _texture(generator: torch.Generator, shape: tuple[int, int]) -> torch.Tensor:
    """A smooth random texture in grey levels: peaks a few cells wide, like a road surface."""
    noise = torch.rand(1, 1, *shape, generator=generator, dtype=torch.float64)
    smooth = torch.nn.functional.avg_pool2d(noise, 3, 1, 1, count_include_pad=False)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 255


def _photo_pair(folder, generator) -> None:
    """A pair folder as prepare_scene_change writes it; the other date is the map in another tone (0.7 v + 40)."""
    reference = _texture(generator, (120, 132))[0, 0].numpy()
    folder.mkdir(parents=True)
    np.save(folder / "reference.npy", reference.astype(np.float32))
    np.save(folder / "captured.npy", (40 + 0.7 * reference).astype(np.float32))


@pytest.mark.parametrize("misfit", ["independent", "correlated"])
def test_the_photograph_drive_tracks_a_pair_and_reports_every_method(tmp_path, capsys, generator, misfit):
    _photo_pair(tmp_path / "another-date" / "pair-a", generator)
    tool = photo_drive
    arguments = ["--pairs", str(tmp_path), "--frames", "12", "--radius", "6", "--sigma", "8", "--uniform-scales", "1"]
    oracle = misfit == "correlated"  # the oracle gating rows once
    tool.main([*arguments, "4", "--misfit", misfit, *(["--oracle"] if oracle else [])])
    assert tool.method_score("ecr_true", misfit=misfit)[0].misfit == misfit
    table = {}
    output = capsys.readouterr().out
    assert f"ECR's misfit {misfit}, mismatch probability 0, filter temperature auto;" in output
    for line in output.splitlines():
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if len(cells) == 6 and cells[2][:1].isdigit():
            table[cells[0], cells[1]] = cells[2:]
    labels = ["ECR, true variance", "ECR, uniform variance x 1", "ECR, uniform variance x 4", "NMI", "NCC"]
    estimators = ("filter", "per-frame argmax", *(["oracle gating"] if oracle else []))
    assert set(table) == {(label, estimator) for label in labels for estimator in estimators}
    within, lost, _, raised = table["ECR, true variance", "filter"]
    assert float(within) >= 0.9 and float(lost) == 0.0 and raised == "0"  # one drive: no standard error
    if oracle:
        within, lost, covers, raised = table["ECR, true variance", "oracle gating"]
        assert float(within) >= 0.9 and float(lost) == 0.0 and covers == "-" and raised == "0"
    record = json.loads(output.strip().splitlines()[-1])
    assert record["misfit"] == misfit and record["drives"]["ECR, true variance | filter"]["lost"] == [0.0]
    assert ("filter by match" in record) == oracle and record["mismatch probability"] == 0.0
    assert record["temperatures"] == ["auto"]
    if oracle:  # every frame but the start is in one of the two parts
        parts = record["filter by match"]["ECR, true variance"]
        assert parts["right"]["frames"][0] + parts["wrong"]["frames"][0] == 11
        assert record["filter split by match"] == "filter"


def test_the_photograph_drive_runs_the_filter_at_each_temperature_it_is_given(tmp_path, capsys, generator, monkeypatch):
    _photo_pair(tmp_path / "pair-a", generator)
    tool = photo_drive
    given = []

    class Recording(tool.Tracker):
        def __init__(self, *args, **kwargs):
            given.append(kwargs["settings"].temperature)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(tool, "Tracker", Recording)
    arguments = ["--pairs", str(tmp_path), "--frames", "8", "--radius", "6", "--sigma", "8", "--methods", "ecr_true"]
    tool.main([*arguments, "--seeds", "0", "1", "--temperatures", "10", "auto", "10", "1e9", "--oracle"])
    assert given == [10.0, "auto", 1e9] * 2  # a repeated temperature runs once
    output = capsys.readouterr().out
    assert "filter temperature 10, auto, 1e+09;" in output
    rows = [line.split("|")[2].strip() for line in output.splitlines() if line.startswith("| ECR, true variance |")]
    assert rows[:4] == ["filter, temperature 10", "filter", "filter, temperature 1e+09", "per-frame argmax"]
    assert "The filter, temperature 10 over the frames whose best match" in output  # the first filter is split
    record = json.loads(output.strip().splitlines()[-1])
    assert record["temperatures"] == [10.0, "auto", 1e9]
    assert record["filter split by match"] == "filter, temperature 10"
    parts = record["filter by match"]["ECR, true variance"]
    assert [a + b for a, b in zip(parts["right"]["frames"], parts["wrong"]["frames"], strict=True)] == [7, 7]
    assert len(record["drives"]["ECR, true variance | filter, temperature 10"]["lost"]) == 2
    assert record["drives"]["ECR, true variance | filter"]["lost"] == [0.0, 0.0]
    assert tool.parse_temperature("auto") == "auto" and tool.parse_temperature("2.5") == 2.5


def test_the_photograph_drive_pairs_each_row_with_the_first_on_the_same_drives():
    tool = photo_drive
    rows = {
        "ECR | filter": {"within 1 cell": [0.5, 0.7], "lost": [0.2, 0.1]},
        "NMI | filter": {"within 1 cell": [0.6, 0.9], "lost": [0.1, 0.1]},
        "NCC | filter": {"within 1 cell": [0.6], "lost": [0.1]},  # a drive raised: left out of the pairing
    }
    lines = tool.paired_rows(rows, drives=2)
    assert "each row less ECR | filter" in lines[0]
    assert lines[3:] == ["| NMI | filter | 0.150 ± 0.050 | -0.050 ± 0.050 |"]
    assert tool.paired_rows(rows, drives=1) == []


def test_the_photograph_drive_oracle_takes_only_right_matches_and_dead_reckons_through_the_rest(tmp_path, generator):
    _photo_pair(tmp_path / "pair-a", generator)
    tool = photo_drive
    (_, reference, captured), *_ = tool.load_pairs(tmp_path)
    settings = argparse.Namespace(frames=12, radius=6.0, sigma=8.0)
    drive = tool.PhotoDrive(reference, captured, 0, settings)
    other = torch.from_numpy(captured)
    wrong = [4, 5, 6]
    for index in wrong:  # the other date 6 cells right and 2 down of the truth: its best match is that place
        moved = drive.truth[index] + torch.tensor([6.0, 2.0, 0.0], dtype=torch.float64)
        drive.frames[index] = tool.cut(other, moved)[0]
    poses = tool.run_oracle_gating(drive, "ecr_true")["pose"]
    error = (poses[:, :2] - drive.truth[:, :2]).abs().amax(1)
    assert bool((error[[i for i in range(12) if i not in wrong]] <= 1).all())
    for index in wrong:  # the last taken pose moved by the odometry, not the wrong match
        torch.testing.assert_close(poses[index, :2], poses[index - 1, :2] + drive.odometry[index, :2])
    argmax = tool.run_argmax(drive, "ecr_true")["pose"]  # per-frame argmax takes the wrong match
    assert float((argmax[4, :2] - drive.truth[4, :2] - torch.tensor([6.0, 2.0], dtype=torch.float64)).abs().max()) <= 1


def test_the_photograph_drive_splits_the_filter_by_whether_the_frames_match_is_right():
    tool = photo_drive
    truth = torch.zeros(5, 3, dtype=torch.float64)
    pose = torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [3, 0, 0], [0, 5, 0], [0, 1, 0]], dtype=torch.float64)
    right = torch.tensor([True, True, True, False, False])
    split = tool.split_by_match(truth, {"pose": pose, "covariance": None}, right)
    assert split["right"] == {"frames": 2, "within 1 cell": 0.5, "lost": 0.0}  # frame 0, the start, is left out
    assert split["wrong"] == {"frames": 2, "within 1 cell": 0.5, "lost": 0.5}
    none = tool.split_by_match(truth, {"pose": pose, "covariance": None}, torch.ones(5, dtype=torch.bool))["wrong"]
    assert none["frames"] == 0 and math.isnan(none["within 1 cell"]) and math.isnan(none["lost"])
    drives = {part: {measure: [value, value] for measure, value in split[part].items()} for part in split}
    drives["wrong"]["lost"][1] = 0.0  # a second drive: mean ± SE over the two
    assert (
        tool.split_rows({"ECR": drives})[-1]
        == "| ECR | 4 | 0.500 ± 0.000 | 0.000 ± 0.000 | 4 | 0.500 ± 0.000 | 0.250 ± 0.250 |"
    )
    wrong = {measure: [value] for measure, value in none.items()}
    assert tool.split_rows({"ECR": {"right": drives["right"], "wrong": wrong}})[-1].endswith("| 0 | - | - |")


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--radius", "40"], "--radius 40.0: the loop and its frames leave the map of ['pair-a']"),
        (["--sigma", "0"], "--sigma must be finite numbers > 0, got 0.0"),
        (["--uniform-scales", "1", "nan"], "--uniform-scales must be finite numbers > 0, got nan"),
        (["--frames", "1"], "--frames must be an int >= 2, got 1"),
        (["--mismatch-probability", "-0.1"], "--mismatch-probability must be in [0, 1), got -0.1"),
        (["--temperatures", "auto", "hot"], "--temperatures must be 'auto' or finite numbers > 0, got 'hot'"),
        (["--temperatures", "0"], "--temperatures must be 'auto' or finite numbers > 0, got '0'"),
        (["--temperatures", "inf"], "--temperatures must be 'auto' or finite numbers > 0, got 'inf'"),
        (["--mismatched"], "--pairs: "),
    ],
)
def test_the_photograph_drive_refuses_a_bad_argument_in_one_line(tmp_path, capsys, generator, arguments, message):
    _photo_pair(tmp_path / "pair-a", generator)
    if arguments == ["--mismatched"]:  # a pair whose two dates differ in shape
        np.save(tmp_path / "pair-a" / "captured.npy", np.zeros((5, 5), dtype=np.float32))
        arguments = []
    tool = photo_drive
    with pytest.raises(SystemExit) as stop:
        tool.main(["--pairs", str(tmp_path), *arguments])
    assert stop.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert message in error[-1] and not any("Traceback" in line for line in error)
