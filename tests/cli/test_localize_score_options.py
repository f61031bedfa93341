"""enmi-localize --score-option: the score's constructor decides, and its refusal comes back in the command's words."""

import numpy as np
import pytest
import torch

from enmi_torch.cli.localize import main


@pytest.fixture
def files(tmp_path):
    generator = torch.Generator().manual_seed(3)
    prior = (torch.rand(48, 40, generator=generator) * 255).numpy()
    np.save(tmp_path / "map.npy", prior)
    local = 255 * (prior[12:36, 10:30] / 255) ** 2 + 2 * torch.randn(24, 20, generator=generator).numpy()
    local[4:12, 3:11] += 60  # a changed patch of the scene
    np.save(tmp_path / "local.npy", local)
    return ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--variance", "4"]


def one_line_error(capsys, arguments) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    captured = capsys.readouterr()
    assert exit_info.value.code == 2 and captured.out == "" and captured.err.count("\n") == 1
    assert captured.err.startswith("enmi-localize: error: ")
    return captured.err.removeprefix("enmi-localize: error: ").rstrip("\n")


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            ["--score-option", "misfit=regional", "--score-option", "model_variance=100.0"],
            "--score-option misfit=regional has no effect with --score-option model_variance=100.0: it is how an "
            "estimated tau^2 treats the misfit's spatial correlation (a fixed model_variance is used as it is); drop "
            "it or pass --score-option model_variance=estimate",
        ),
        (
            ["--score-option", "model_variance=None", "--score-option", "misfit=correlated"],
            "--score-option misfit=correlated has no effect with --score-option model_variance=None",
        ),
        (
            ["--score-option", "response=linear", "--score-option", "response_variance=3"],
            "--score-option response_variance=3.0 has no effect with --score-option response=linear: it is the shrunk "
            "response's delta^2; drop it or pass --score-option response=shrunk",
        ),
        (
            ["--score-option", "model_variance=-1"],
            "--score-option model_variance must be 'estimate', a number >= 0 or None, got -1",
        ),
        (["--bins", "1"], "--bins must be an int >= 2, got 1"),
        (["--score", "enmi", "--score-option", "kernel=gauss"], "--score-option kernel must be one of"),
    ],
)
def test_a_moot_or_bad_score_option_ends_in_one_line_in_the_commands_spelling(capsys, files, options, message):
    error = one_line_error(capsys, [*files, *options])
    assert error == message or error.startswith(message), error


def test_the_score_is_refused_before_any_file_is_read(capsys, tmp_path):
    missing = ["--map", str(tmp_path / "none.npy"), "--local", str(tmp_path / "none.npy")]
    error = one_line_error(
        capsys, [*missing, "--score-option", "response=linear", "--score-option", "response_variance=2"]
    )
    assert error.startswith("--score-option response_variance=2.0 has no effect")


def test_options_where_they_apply_take_effect(capsys, files):
    def score(*options):
        main([*files, "--shifts", "3", *options])
        return capsys.readouterr().out

    default = score()
    for option in (
        "misfit=regional",
        "misfit=correlated",
        "response=binned",
        "response_variance=0",
        "model_variance=9",
    ):
        assert score("--score-option", option) != default, option
    assert score("--score-option", "misfit=independent", "--score-option", "model_variance=9") == score(
        "--score-option", "model_variance=9"
    )  # an option given at its default is no conflict
