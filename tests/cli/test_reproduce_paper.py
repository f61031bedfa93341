import csv

import pytest

from enmi_torch.cli.reproduce_paper import main
from enmi_torch.simulation import SCORES


def test_writes_csv_figure_and_tensorboard(tmp_path, capsys):
    points = tmp_path / "points.csv"
    points.write_text("noise_power,nmi,enmi\n0.001,0.0,0.0\n0.01,0.2479,0.0048\n0.1,0.4907,0.3486\n")
    arguments = ["--trials=40", f"--paper_points={points}", "--workers=1"]
    main([*arguments, f"--output_dir={tmp_path / 'out'}", f"--tensorboard={tmp_path / 'tb'}"])
    with (tmp_path / "out" / "paper_simulation.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["noise_power"] for row in rows] == ["0.001", "0.01", "0.1"]
    assert set(SCORES) <= set(rows[0])
    assert (tmp_path / "out" / "paper_simulation.png").stat().st_size > 10_000
    assert any((tmp_path / "tb").rglob("events.out.tfevents.*"))
    assert f"wrote {tmp_path / 'out' / 'paper_simulation.csv'}" in capsys.readouterr().out


def test_output_goes_to_runs_of_the_current_folder_by_default(tmp_path, monkeypatch):
    points = tmp_path / "points.csv"
    points.write_text("noise_power,nmi,enmi\n0.01,0.2479,0.0048\n")
    monkeypatch.chdir(tmp_path)
    main(["--trials=8", f"--paper_points={points}", "--scores=[nmi]"])
    assert (tmp_path / "runs" / "paper_simulation" / "paper_simulation.csv").is_file()


def test_help_has_plain_types_and_an_example(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert text.startswith("usage: enmi-reproduce-paper") and "<function" not in text and "examples:" in text
    assert text.index("Reproduce the paper's Fig. simPerformance") < text.index("\noptions:")


def test_mistakes_end_in_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--trails", "5"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and "(did you mean --trials?)" in error
    with pytest.raises(SystemExit):
        main(["--trials", "4", "--scores", "[nmi, mi]"])
    assert capsys.readouterr().err.startswith("enmi-reproduce-paper: error: score must be one of")


def test_relative_paths_in_a_config_are_read_from_its_folder_and_flags_use_dashes(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "points.csv").write_text("noise_power,nmi,enmi\n0.01,0.2479,0.0048\n0.02,0.3,0.01\n")
    (folder / "config.yaml").write_text("paper_points: points.csv\nscores: [nmi]\ntrials: 8\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    main(["--config", str(folder / "config.yaml"), "--output-dir", "out"])
    with (elsewhere / "out" / "paper_simulation.csv").open(newline="") as handle:
        assert [row["noise_power"] for row in csv.DictReader(handle)] == ["0.01", "0.02"]
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--output-dir" in text and "--paper-points" in text and "--output_dir" not in text
