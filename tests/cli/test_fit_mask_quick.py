"""enmi-fit-mask answers --help and option mistakes without importing Lightning, as the full parser would (issue 34).

The speed itself is measured by data_tools/benchmarks/bench_command_start.py, not here.
"""

import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from enmi_torch.cli.fit_mask_quick import HELP_COLUMNS, QUICK_REFERENCE, quick_answer
from enmi_torch.training.fit_mask import fit_mask, quick_reference

ROOT = Path(__file__).resolve().parents[2]


def test_the_quick_reference_is_that_of_the_full_parser():
    written = json.loads(QUICK_REFERENCE.read_text())
    assert written == json.loads(json.dumps(quick_reference(HELP_COLUMNS))), (
        "regenerate it: PYTHONPATH=. python -m enmi_torch.cli.fit_mask_quick"
    )


def answer(function, arguments) -> tuple[int | None, str, str]:
    out, err = io.StringIO(), io.StringIO()
    code = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            function(arguments)
        except SystemExit as exit_info:
            code = exit_info.code
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize(
    "arguments",
    [
        ["--data.flavor", "camera", "--model.lrr", "3"],
        ["--data.size", "abc"],
        ["--data.size=1.5"],
        ["--trainer.max_epochs", "abc"],
        ["--model.match_intensity", "maybe"],
        ["--overwrite", "maybe"],
        ["--torch-threads", "many"],
    ],
)
def test_a_mistake_gets_the_full_parsers_line(arguments):
    quick = answer(quick_answer, arguments)
    assert quick[0] == 2 and quick[1] == "" and quick[2].count("\n") == 1
    assert quick == answer(fit_mask, arguments)


@pytest.mark.parametrize(
    "arguments",
    [
        ["--model.lr", "1e-3", "--data.size", "16"],
        ["--trainer.max_epochs", "null", "--trainer.logger.init_args.save_dir", "x"],
        ["--trainer.callbacks+=lightning.pytorch.callbacks.EarlyStopping", "--config", "any.yaml"],
        ["--ckpt-path", "a.ckpt", "--data.root", "PAIRS", "--debug"],
    ],
)
def test_what_the_list_cannot_judge_goes_to_the_full_parser(arguments):
    assert quick_answer(arguments) is None


def test_help_and_mistakes_do_not_import_lightning():
    script = (
        "import sys\n"
        "from enmi_torch.cli.fit_mask import main\n"
        "for arguments in (['--help'], ['--data.flavor', 'camera']):\n"
        "    try:\n"
        "        main(arguments)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print(sorted(name for name in sys.modules if name.split('.')[0] in ('lightning', 'matplotlib')))\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert completed.stdout.strip().splitlines()[-1] == "[]", completed.stderr[-2000:]
