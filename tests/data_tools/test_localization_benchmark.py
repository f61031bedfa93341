"""The example writer of ``data_tools.experiments.yardstick.localization_benchmark`` and the command's epilog."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TOOL = [sys.executable, "-m", "data_tools.experiments.yardstick.localization_benchmark"]


def test_command_line_example_names_the_files_the_example_writer_makes(tmp_path):
    from enmi_torch.cli.localize import _EPILOG

    completed = subprocess.run(
        [*TOOL, "--example", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert completed.returncode == 0, completed.stderr
    named = set(re.findall(r"runs/example/(\w+\.npy)", _EPILOG))
    assert named and named <= {path.name for path in tmp_path.iterdir()}
    # A second call refuses to replace the files (one line, exit 2) unless --overwrite.
    before = {path.name: path.stat().st_mtime_ns for path in tmp_path.iterdir()}
    again = subprocess.run([*TOOL, "--example", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 2 and "already holds" in again.stderr and "--overwrite" in again.stderr
    assert "Traceback" not in again.stderr
    assert {path.name: path.stat().st_mtime_ns for path in tmp_path.iterdir()} == before
    replaced = subprocess.run(
        [*TOOL, "--example", str(tmp_path), "--overwrite"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert replaced.returncode == 0, replaced.stderr
