"""The examples of README, docs/examples.md and docs/getting_started.md print what they say; README stays short.

An example is a ``python`` block followed by the ``text`` block of its output, or a ``console`` block of ``$ ``
commands, each followed by its output; a console script (``enmi-localize``) runs as ``python -m`` of its module
(pyproject.toml's ``[project.scripts]``), as the installed script would. ``...`` in an output stands for any text
(doctest's ELLIPSIS). An example after a ``<!-- slow -->`` line runs with ``pytest -m slow``. Each document's examples
run in a folder of their own that sees the repository's ``configs``, ``data_tools`` and ``train``, in the document's
order (the mask example reads what the command before it wrote); a slow example first runs the fast ones before it
that have not run in this session (``pytest -m slow`` deselects them, and the slow steps of docs/getting_started.md
read what they wrote).
"""

import contextlib
import doctest
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"^(<!-- slow -->\n)?```(\w+)\n(.*?)^```\n", re.MULTILINE | re.DOTALL)
DOCUMENTS = ("README.md", "docs/examples.md", "docs/getting_started.md")
SECTION = (ROOT / "pyproject.toml").read_text().split("[project.scripts]\n")[1].split("\n[")[0]
SCRIPTS = dict(re.findall(r'^([\w-]+) = "([\w.]+):main"$', SECTION, re.MULTILINE))  # console script: its module
README_LINES = 150


def readme_examples(document: str = "README.md") -> list:
    """``pytest.param((document, language, code, expected))`` per example, marked slow where the document says so."""
    text = (ROOT / document).read_text()
    blocks = list(BLOCK.finditer(text))
    examples = []
    for index, block in enumerate(blocks):
        language, body, slow = block.group(2), block.group(3), block.group(1) is not None
        line = text.count("\n", 0, block.start()) + 1
        if language == "python":
            after = blocks[index + 1] if index + 1 < len(blocks) else None
            assert after is not None and after.group(2) == "text", (
                f"{document} line {line}: no output after the example"
            )
            assert text[block.end() : after.start()].strip() == "", f"{document} line {line}: text before the output"
            example = (document, "python", body, after.group(3), len(examples), slow)
        elif language == "console":
            example = (document, "console", body, None, len(examples), slow)
        else:
            continue
        marks = [pytest.mark.slow] if slow else []
        examples.append(pytest.param(example, id=f"{Path(document).stem}-line{line}-{language}", marks=marks))
    return examples


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict:
    """One working folder per document, made on first use; ``folder.ran`` holds each document's examples run there."""
    made = {}

    def folder(document: str) -> Path:
        if document not in made:
            working = tmp_path_factory.mktemp(Path(document).stem)
            for name in ("configs", "data_tools", "train"):
                (working / name).symlink_to(ROOT / name)
            made[document] = working
        return made[document]

    folder.ran = {document: set() for document in DOCUMENTS}
    return folder


def check_output(expected: str, actual: str, what: str) -> None:
    actual = "".join(line.rstrip() + "\n" for line in actual.splitlines())  # nothing printed: ""
    if not doctest.OutputChecker().check_output(expected, actual, doctest.ELLIPSIS):
        pytest.fail(f"{what} printed\n{actual}\nbut the document says\n{expected}")


def console_commands(body: str) -> list[tuple[str, str]]:
    """``(command, expected output)`` pairs of a console block."""
    pairs = []
    for line in body.splitlines(keepends=True):
        if line.startswith("$ "):
            pairs.append([line[2:].strip(), ""])
        else:
            pairs[-1][1] += line
    return [(command, expected) for command, expected in pairs]


def test_examples_exist():
    languages = [param.values[0][1] for param in readme_examples()]
    assert languages.count("python") >= 5 and languages.count("console") >= 1
    languages = [param.values[0][1] for param in readme_examples("docs/examples.md")]
    assert languages.count("python") >= 2 and languages.count("console") >= 3
    languages = [param.values[0][1] for param in readme_examples("docs/getting_started.md")]
    assert languages.count("python") >= 2 and languages.count("console") >= 3
    assert {"enmi-example", "enmi-localize", "enmi-fit-mask"} <= set(SCRIPTS)


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= README_LINES, (
        f"README.md has {lines} lines, at most {README_LINES}: move examples to docs/examples.md"
    )


@pytest.mark.parametrize("example", [param for document in DOCUMENTS for param in readme_examples(document)])
def test_readme_example(example, folders, monkeypatch):
    document, _, _, _, index, slow = example
    folder = folders(document)
    monkeypatch.chdir(folder)
    if slow:
        for earlier in readme_examples(document)[:index]:
            if not earlier.values[0][5] and earlier.values[0][4] not in folders.ran[document]:
                run_example(earlier.values[0], folder)
                folders.ran[document].add(earlier.values[0][4])
    run_example(example, folder)
    folders.ran[document].add(index)


def run_example(example: tuple, folder: Path) -> None:
    """Run one example in ``folder`` (the current folder) and compare what it prints with the document."""
    document, language, body, expected, _, _ = example
    if language == "python":
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            exec(compile(body, document, "exec"), {"__name__": "__readme__"})
        check_output(expected, printed.getvalue(), "the example")
        return
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    for command, output in console_commands(body):
        python_command = re.sub(r"^python ", f"{sys.executable} ", command)
        script = command.split()[0]
        if script in SCRIPTS:  # the console script as its module: this checkout's, installed or not
            python_command = f"{sys.executable} -m {SCRIPTS[script]} {command[len(script) :].strip()}"
        completed = subprocess.run(
            python_command, shell=True, cwd=folder, env=environment, capture_output=True, text=True, timeout=600
        )
        assert completed.returncode == 0, f"{command} failed:\n{completed.stderr}"
        check_output(output, completed.stdout, command)
