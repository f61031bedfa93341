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


def _points(tmp_path):
    points = tmp_path / "points.csv"
    points.write_text("noise_power,nmi,enmi\n0.01,0.2479,0.0048\n")
    return f"--paper_points={points}"


def _one_line_error(capsys, arguments):
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1, error
    return error


def test_an_earlier_run_is_not_overwritten_unless_asked(tmp_path, capsys):
    arguments = ["--trials=8", _points(tmp_path), "--scores=[nmi]", f"--output-dir={tmp_path / 'out'}"]
    main(arguments)
    csv_file = tmp_path / "out" / "paper_simulation.csv"
    csv_file.write_text("mine\n")
    capsys.readouterr()
    error = _one_line_error(capsys, arguments)
    assert "already holds paper_simulation.csv, paper_simulation.png" in error and "--overwrite true" in error
    assert csv_file.read_text() == "mine\n"
    main([*arguments, "--overwrite", "true"])
    assert csv_file.read_text().startswith("noise_power")


@pytest.mark.parametrize(
    ("flag", "message"),
    [
        ("--threads=0", "--threads must be an int >= 1, got 0"),
        ("--workers=0", "--workers must be an int >= 1, got 0"),
        ("--scores=[]", "--scores must name at least one score"),
    ],
)
def test_empty_or_zero_options_end_in_one_line_and_write_nothing(tmp_path, capsys, flag, message):
    error = _one_line_error(capsys, ["--trials=8", _points(tmp_path), f"--output-dir={tmp_path / 'out'}", flag])
    assert message in error
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("camera: [1, 2\n", "is not readable YAML: expected ',' or ']'"),
        ('camera: !!python/object/apply:os.system ["echo hi"]\n', "tags such as !!python/... are refused"),
        ("camera: {a: b: c}\n", "is not readable YAML"),
    ],
)
def test_a_malformed_camera_config_ends_in_one_line_naming_the_flag_and_file(tmp_path, capsys, text, message):
    camera = tmp_path / "camera.yaml"
    camera.write_text(text)
    arguments = ["--trials=8", _points(tmp_path), f"--output-dir={tmp_path / 'out'}", f"--camera-config={camera}"]
    error = _one_line_error(capsys, arguments)
    assert f"--camera-config: camera config file '{camera}'" in error and message in error


@pytest.mark.parametrize("spelling", ["separate", "equals"])
def test_a_binary_config_ends_in_one_line_naming_the_flag_and_file(tmp_path, capsys, spelling):
    config = tmp_path / "config.yaml"
    config.write_bytes(bytes(range(128, 256)))
    given = ["--config", str(config)] if spelling == "separate" else [f"--config={config}"]
    error = _one_line_error(capsys, [*given, f"--output-dir={tmp_path / 'out'}"])
    assert f"--config '{config}' is not UTF-8 text (a binary file?)" in error and "codec" not in error
    assert not (tmp_path / "out").exists()
