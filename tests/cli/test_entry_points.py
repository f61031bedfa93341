import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SECTION = (ROOT / "pyproject.toml").read_text().split("[project.scripts]\n")[1].split("\n\n")[0]
SCRIPTS = {name.strip(): value.strip().strip('"') for name, value in (line.split("=") for line in SECTION.splitlines())}
WRAPPERS = {
    "enmi-fit-mask": ["train/fit_mask.py"],
    "enmi-localize": ["-m", "enmi_torch.localization"],
    "enmi-reproduce-paper": ["-m", "data_tools.reproduce_paper"],
    "enmi-make-pairs": ["-m", "data_tools.make_pairs"],
}


def test_every_console_script_has_a_python_form():
    assert set(SCRIPTS) == set(WRAPPERS)


@pytest.mark.parametrize("name", sorted(WRAPPERS))
def test_entry_point_and_python_form_print_the_same_help(name, capsys):
    module, function = SCRIPTS[name].split(":")
    with pytest.raises(SystemExit) as exit_info:
        getattr(importlib.import_module(module), function)(["--help"])
    text = capsys.readouterr().out
    assert exit_info.value.code == 0 and text.startswith(f"usage: {name} ")
    # The python form, as the README shows it, in a fresh process from the repository root.
    completed = subprocess.run(
        [sys.executable, *WRAPPERS[name], "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert completed.returncode == 0 and completed.stdout == text
    installed = shutil.which(name)
    if installed is not None and Path(installed).resolve().is_relative_to(Path(sys.prefix).resolve()):
        completed = subprocess.run([installed, "--help"], capture_output=True, text=True, timeout=120)
        assert completed.returncode == 0 and completed.stdout.startswith(f"usage: {name} ")
