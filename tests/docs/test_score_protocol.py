"""The score-family page's example runs and prints what the page says; a family defined so works in every search.

Run in a process of its own: the example's family registers its name for ``as_score``, which the rest of the suite
must not see.
"""

import os
import subprocess
import sys

from tests.test_readme import ROOT, check_output, readme_examples

PAGE = "docs/score_protocol.md"


def _run(code: str, folder) -> str:
    """What ``code`` prints, run in a Python process of its own in ``folder``; it must exit 0."""
    completed = subprocess.run(
        [sys.executable, "-c", code],
        cwd=folder,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert completed.returncode == 0, completed.stderr
    return completed.stdout


def test_the_page_example_prints_what_the_page_shows(tmp_path):
    examples = [param.values[0] for param in readme_examples(PAGE)]
    assert [example[1] for example in examples] == ["python"]
    code, expected = examples[0][2], examples[0][3]
    check_output(expected, _run(code, tmp_path), PAGE)


def test_a_family_without_a_trait_is_refused_by_name_where_one_is_needed(tmp_path):
    code = readme_examples(PAGE)[0].values[0][2]
    probe = code + (
        "\ntry:\n    Residual().require('least_squares', 'register')\nexcept ValueError as error:\n"
        "    print(str(error).split(';')[0])\n"
    )
    last = _run(probe, tmp_path).splitlines()[-1]
    assert last.startswith(
        "register needs a score with the 'least_squares' trait (response_basis and least_squares_fit), got "
        "score=Residual()"
    )
