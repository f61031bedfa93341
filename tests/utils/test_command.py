import pytest

from enmi_torch.utils.command import ArgumentParser, dashed_aliases, plain_parser_message, plain_text, run_command


def parser() -> ArgumentParser:
    parser = ArgumentParser(prog="enmi-example", description="An example.")
    parser.add_argument("--yaws", default="0", help="degrees")
    parser.add_argument("--bins", type=int, default=32, help="histogram bins")
    parser.add_argument("--output", help="a file")
    return parser


def test_values_that_start_with_a_minus_and_a_digit_are_values():
    assert parser().parse_args(["--yaws", "-6:6:1"]).yaws == "-6:6:1"
    assert parser().parse_args(["--yaws", "-.5,0"]).yaws == "-.5,0"


def test_help_lists_defaults_that_are_set_and_debug_last(capsys):
    with pytest.raises(SystemExit):
        parser().parse_args(["--help"])
    text = capsys.readouterr().out
    assert "histogram bins (default: 32)" in text and "a file (default" not in text
    assert text.rindex("--debug") > text.rindex("--output")


def test_a_misspelt_option_gets_one_line_with_the_closest_option(capsys):
    with pytest.raises(SystemExit) as exit_info:
        parser().parse_args(["--bisn", "8"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1
    assert (
        error
        == "enmi-example: error: unrecognized arguments: --bisn 8 (did you mean --bins?); see enmi-example --help\n"
    )


def test_run_command_turns_user_errors_into_one_line_unless_debug(capsys):
    def command(argv):
        raise ValueError("bins must be an int >= 2,\n  got 1")

    with pytest.raises(SystemExit) as exit_info:
        run_command("enmi-example", command, ["--bins", "1"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == "enmi-example: error: bins must be an int >= 2, got 1\n"
    with pytest.raises(ValueError, match="bins must be"):
        run_command("enmi-example", command, ["--bins", "1", "--debug"])

    def bug(argv):
        raise KeyError("not a user mistake")

    with pytest.raises(KeyError):
        run_command("enmi-example", bug, [])


def test_plain_text_drops_docstring_markup():
    assert plain_text(":class:`~enmi_torch.data.PairDataModule` in ``pixel`` form") == "PairDataModule in pixel form"
    assert plain_text("see :mod:`enmi_torch.data.truth`") == "see enmi_torch.data.truth"


def test_dashed_aliases_accept_either_spelling_of_an_option():
    names = ["output-dir", "paper-points"]
    argv = [
        "--output_dir",
        "out",
        "--paper_points=p.csv",
        "--output-dir",
        "x",
        "--trials",
        "2",
        "value_with_underscore",
    ]
    assert dashed_aliases(argv, names) == [
        "--output-dir",
        "out",
        "--paper-points=p.csv",
        "--output-dir",
        "x",
        "--trials",
        "2",
        "value_with_underscore",
    ]
    assert dashed_aliases(["--ckpt-path", "a"], ["ckpt_path"]) == ["--ckpt_path", "a"]


def test_parser_messages_in_plain_words_name_the_flag():
    union = (
        'Parser key "trainer.max_epochs":\n  Does not validate against any of the Union subtypes\nSubtypes: '
        "[<class 'int'>, <class 'NoneType'>]\nErrors:\n  - Expected a <class 'int'>\n  - Expected a <class "
        "'NoneType'>\nGiven value type: <class 'str'>\nGiven value: abc"
    )
    assert plain_parser_message(union) == "--trainer.max_epochs expects int or null, got 'abc'"
    assert plain_parser_message("Parser key \"size\":\n  Expected a <class 'int'>. Got value: x") == (
        "--size expects int, got 'x'"
    )
    missing = "Parser key \"paper_points\":\n  Not of type Path_fr: File does not exist: '/a.csv'"
    assert plain_parser_message(missing, ["--paper-points"]) == "--paper-points: no such file '/a.csv'"
    assert plain_parser_message("unrecognized arguments: --x") == "unrecognized arguments: --x"
