"""How every command parses, helps and fails: one-line errors with exit code 2, "did you mean", defaults in help.

Shared by the commands of :mod:`enmi_torch.cli` and the training command's parser; the standard library only.
"""

from __future__ import annotations

import argparse
import difflib
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import NoReturn

# Exceptions that mean "the input or the options are wrong" (the library's checks, missing or unreadable files).
USER_ERRORS = (ValueError, TypeError, OSError)

DEBUG_HELP = "show the full traceback of an error instead of one line"


def run_command(prog: str, command: Callable[[list[str]], object], argv: Sequence[str] | None = None) -> None:
    """Run ``command(argv)``; a user mistake ends in one line on stderr and exit code 2.

    ``--debug`` anywhere in ``argv`` (removed before ``command`` sees it) lets the exception through with its
    traceback. ``argv`` defaults to ``sys.argv[1:]``.
    """
    arguments = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in arguments
    arguments = [argument for argument in arguments if argument != "--debug"]
    try:
        command(arguments)
    except USER_ERRORS as error:
        if debug:
            raise
        fail(prog, str(error) or type(error).__name__)


def check_text_files(argv: Sequence[str], flag: str) -> None:
    """Raise ``ValueError`` naming ``flag`` if a file it names (``FLAG FILE`` or ``FLAG=FILE``) is not UTF-8 text.

    A parser that reads the file itself would say only "'utf-8' codec can't decode byte ...".
    """
    for index, argument in enumerate(argv):
        if argument == flag and index + 1 < len(argv):
            path = argv[index + 1]
        elif argument.startswith(f"{flag}="):
            path = argument.partition("=")[2]
        else:
            continue
        try:
            Path(path).read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{flag} {path!r} is not UTF-8 text (a binary file?): pass a YAML file") from None
        except OSError:
            continue  # the parser says that a file is missing, in its own words


def fail(prog: str, message: str) -> NoReturn:
    """Print ``prog: error: message`` on one line to stderr and exit with code 2."""
    sys.stderr.write(f"{prog}: error: {' '.join(message.split())}\n")
    raise SystemExit(2)


def dashed_aliases(argv: Sequence[str], names: Sequence[str]) -> list[str]:
    """``argv`` with each option of ``names`` spelt either way accepted: ``--output-dir`` and ``--output_dir``.

    ``names`` are the spellings the parser knows; the other spelling (dashes for underscores or the reverse) is the
    hidden alias.
    """
    aliases = {}
    for name in names:
        for other in (name.replace("_", "-"), name.replace("-", "_")):
            if other != name:
                aliases[f"--{other}"] = f"--{name}"
    rewritten = []
    for argument in argv:
        option, equals, value = argument.partition("=")
        rewritten.append(aliases.get(option, option) + equals + value if option in aliases else argument)
    return rewritten


def with_flag_names(message: str, flags: Mapping[str, str]) -> str:
    """``message`` with the parameter it starts with named as the flag the user typed (``count``: ``--pairs``)."""
    match = re.match(r"(\w+)\b", message)
    if match and match.group(1) in flags:
        return flags[match.group(1)] + message[match.end() :]
    return message


def plain_parser_message(message: str, known: Sequence[str] = ()) -> str:
    """A jsonargparse message in plain words: the flag the user typed, the types by name, no Union dump.

    ``Parser key "trainer.max_epochs": Does not validate against any of the Union subtypes ... Given value: abc`` ->
    ``--trainer.max_epochs expects int or null, got 'abc'``. A key is named as the option in ``known`` that spells it
    (``output_dir``: ``--output-dir`` where the parser knows that one).
    """
    message = " ".join(message.split())
    message = re.sub(r"<class '(?:[\w.]+\.)?(\w+)'>", r"\1", message).replace("NoneType", "null")
    key = re.match(r'Parser key "([^"]+)":\s*', message)
    if key is None:
        return message
    flag, rest = "--" + key.group(1), message[key.end() :]
    if flag not in known and flag.replace("_", "-") in known:
        flag = flag.replace("_", "-")
    missing = re.search(r"File does not exist: (.*)$", rest)
    if missing is not None:
        return f"{flag}: no such file {missing.group(1)}"
    union = re.search(r"Subtypes: \[([^\]]*)\].*Given value: (.*)$", rest)
    if union is not None:
        return f"{flag} expects {' or '.join(union.group(1).split(', '))}, got {union.group(2)!r}"
    expected = re.match(r"Expected a (\w+)\.? ?(?:Got value: )?(.*)$", rest)
    if expected is not None:
        return f"{flag} expects {expected.group(1)}, got {expected.group(2)!r}"
    return f"{flag}: {rest}"


def parser_error(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """One line for a command-line mistake, with the closest known option for a misspelt one."""
    known = [option for action in parser._actions for option in action.option_strings]
    message = plain_parser_message(message, known)
    guesses = []
    if "unrecognized arguments" in message:
        for word in message.split(":", 1)[1].split():
            if word.startswith("-"):
                guesses += difflib.get_close_matches(word.split("=", 1)[0], known, n=1, cutoff=0.6)
    hint = f" (did you mean {', '.join(guesses)}?)" if guesses else ""
    fail(parser.prog, f"{message}{hint}; see {parser.prog} --help")


def plain_text(text: str) -> str:
    """Docstring markup as plain text: ``:class:`~a.B``` -> ``B``, ``:mod:`a.b``` -> ``a.b``, no double backquotes."""
    text = re.sub(r":mod:`~?([^`]+)`", r"\1", text)
    text = re.sub(r":\w+:`~?([^`]+)`", lambda match: match.group(1).rsplit(".", 1)[-1], text)
    return text.replace("``", "")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's line breaks and appends each option's default (unless ``None`` or ``False``)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_text = action.help or ""
        unset = action.default is None or action.default is False or action.default == argparse.SUPPRESS
        if "%(default)" in help_text or unset or not action.option_strings:
            return help_text
        return f"{help_text} (default: %(default)s)"


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` with one-line errors, "did you mean" and defaults in the help."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        # Values such as --yaws -6:6:1 or --value -1e-3 start with "-" and a digit: read them as values, not options.
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def parse_known_args(self, args=None, namespace=None):
        """Parse, with ``--debug`` (handled by :func:`run_command`) listed last among the options."""
        if not any("--debug" in action.option_strings for action in self._actions):
            self.add_argument("--debug", action="store_true", help=DEBUG_HELP)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        """One line on stderr, exit code 2."""
        parser_error(self, message)
