"""``enmi-fit-mask``'s quick answers: ``--help`` and the mistakes the option list alone shows, without Lightning.

They are answered from ``fit_mask_quick.json``, written from the full parser (:func:`write_quick_reference`; a test
checks that it is current): in a fraction of the full parser's time. ``python -m enmi_torch.cli.fit_mask_quick``
rewrites the file (it needs the train extra).
"""

from __future__ import annotations

import difflib
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from enmi_torch.utils.command import dashed_aliases, fail

PROG = "enmi-fit-mask"
QUICK_REFERENCE = Path(__file__).with_name("fit_mask_quick.json")
# The width the cached help is formatted at (argparse's own comes from the terminal).
HELP_COLUMNS = 120
# Options whose keys nest further (a class and its init_args): an unknown key under them is the full parser's to judge.
OPEN_PREFIXES = ("--config", "--print_config", "--help_all")


def quick_answer(arguments: Sequence[str]) -> None:
    """Print the help or a mistake's one line and exit, where the option list alone decides; else return.

    Anything the list cannot judge (a ``--config`` file's keys, a class's init_args, a value's range) is left to the
    full parser, as is everything when the list was written for another Lightning than the installed one.
    """
    reference = _reference()
    if reference is None:
        return
    words = dashed_aliases([word for word in arguments if word != "--debug"], reference["run_keys"])
    if any(word in ("-h", "--help") for word in words) and "--help_all" not in words:
        sys.stdout.write(reference["help"])
        raise SystemExit(0)
    options: dict[str, str | None] = reference["options"]
    unknown: list[str] = []
    index = 0
    while index < len(words):
        word = words[index]
        index += 1
        if not word.startswith("--"):
            continue
        key, equals, value = word.partition("=")
        if key.startswith(OPEN_PREFIXES) or key.endswith("+") or _nested_under_open(key, options):
            continue
        if key not in options:
            unknown.append(word)
            while index < len(words) and not words[index].startswith("--"):
                unknown.append(words[index])
                index += 1
            continue
        if not equals and index < len(words) and not words[index].startswith("--"):
            value, equals = words[index], "="
            index += 1
        if equals and options[key] is not None and not _fits(value, options[key]):
            fail(PROG, f"{key} expects {options[key].replace('|', ' or ')}, got {value!r}; see {PROG} --help")
    if unknown:
        known = list(options)
        guesses = [
            guess
            for word in unknown
            if word.startswith("--")
            for guess in difflib.get_close_matches(word.split("=", 1)[0], known, n=1, cutoff=0.6)
        ]
        hint = f" (did you mean {', '.join(guesses)}?)" if guesses else ""
        fail(PROG, f"unrecognized arguments: {' '.join(unknown)}{hint}; see {PROG} --help")


def _reference() -> dict | None:
    """The quick reference, if it was written for the installed Lightning and jsonargparse."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        reference = json.loads(QUICK_REFERENCE.read_text())
        installed = {name: version(name) for name in reference["versions"]}
    except (OSError, ValueError, KeyError, PackageNotFoundError):
        return None
    return reference if installed == reference["versions"] else None


def _nested_under_open(key: str, options: dict[str, str | None]) -> bool:
    """Whether ``key`` extends a class-valued option (``--trainer.logger.init_args.save_dir``)."""
    parts = key.split(".")
    return any(
        ".".join(parts[:end]) in options and options[".".join(parts[:end])] is None for end in range(2, len(parts))
    )


def _fits(value: str, kind: str) -> bool:
    """Whether the full parser could take ``value`` (read as YAML) for ``kind``; doubtful cases count as fitting."""
    import yaml

    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError:
        return True
    if parsed is None or not isinstance(parsed, (str, int, float)):
        return True  # null, lists, dates: the full parser's to judge
    kinds = kind.split("|")
    if isinstance(parsed, bool):
        return "bool" in kinds
    if isinstance(parsed, int):
        return "int" in kinds or "float" in kinds
    if isinstance(parsed, float):
        return "float" in kinds or ("int" in kinds and parsed.is_integer())
    try:
        float(parsed)  # 1e-3: a string to YAML, a number to the full parser
    except ValueError:
        return False  # a word where a number or a bool goes
    return "bool" not in kinds


def write_quick_reference(path: Path = QUICK_REFERENCE) -> dict:
    """Write the quick reference from the full parser: its help and each option's simple type (or ``None``)."""
    from enmi_torch.training.fit_mask import quick_reference

    reference = quick_reference(HELP_COLUMNS)
    path.write_text(json.dumps(reference, indent=1, sort_keys=True) + "\n")
    return reference


if __name__ == "__main__":
    write_quick_reference()
