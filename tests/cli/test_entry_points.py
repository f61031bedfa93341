import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SECTION = (ROOT / "pyproject.toml").read_text().split("[project.scripts]\n")[1].split("\n\n")[0]
SCRIPTS = {name.strip(): value.strip().strip('"') for name, value in (line.split("=") for line in SECTION.splitlines())}
# Each command's Python forms: the module itself, and the clone's script where there is one.
WRAPPERS = {
    "enmi-fit-mask": [["-m", "enmi_torch.cli.fit_mask"], ["train/fit_mask.py"]],
    "enmi-localize": [["-m", "enmi_torch.cli.localize"]],
    "enmi-reproduce-paper": [["-m", "enmi_torch.cli.reproduce_paper"], ["-m", "data_tools.reproduce_paper"]],
    "enmi-make-pairs": [["-m", "enmi_torch.cli.make_pairs"], ["-m", "data_tools.make_pairs"]],
    "enmi-example": [["-m", "enmi_torch.cli.example"]],
}


def test_every_console_script_has_a_python_form():
    assert set(SCRIPTS) == set(WRAPPERS)
    for name, forms in WRAPPERS.items():
        assert forms[0] == ["-m", SCRIPTS[name].split(":")[0]]


def test_every_command_module_runs_as_python_m():
    for path in sorted((ROOT / "enmi_torch" / "cli").glob("*.py")):
        if path.name != "__init__.py":
            assert '\nif __name__ == "__main__":\n' in path.read_text(), path.name
    assert all(value.startswith("enmi_torch.cli.") for value in SCRIPTS.values())


@pytest.mark.parametrize("name", sorted(WRAPPERS))
def test_entry_point_and_python_form_print_the_same_help(name, capsys):
    module, function = SCRIPTS[name].split(":")
    with pytest.raises(SystemExit) as exit_info:
        getattr(importlib.import_module(module), function)(["--help"])
    text = capsys.readouterr().out
    assert exit_info.value.code == 0 and text.startswith(f"usage: {name} ")
    # The python forms, as the README shows them, in a fresh process from the repository root.
    for form in WRAPPERS[name]:
        completed = subprocess.run(
            [sys.executable, *form, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120
        )
        assert completed.returncode == 0 and completed.stdout == text, form
    installed = shutil.which(name)
    if installed is not None and Path(installed).resolve().is_relative_to(Path(sys.prefix).resolve()):
        completed = subprocess.run([installed, "--help"], capture_output=True, text=True, timeout=120)
        assert completed.returncode == 0 and completed.stdout.startswith(f"usage: {name} ")
