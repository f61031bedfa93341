"""How soon ``enmi-fit-mask`` answers ``--help`` and a mistake, against the floors of starting Python and torch.

    python -m data_tools.benchmarks.bench_command_start              # 5 rounds, about a minute
    python -m data_tools.benchmarks.bench_command_start --rounds 3

Each command runs in a fresh process from the repository root (``python train/fit_mask.py ...``, the clone's
package); a round runs every command once, in turn, so that the machine's other load falls on all of them alike.
The table gives each command's median wall time and its median per-round ratio to ``python -c pass`` and to
``python -c "import torch"`` (the floor while ``import enmi_torch`` imports torch). Rows:

- ``--help`` and a misspelt option, a word where a number goes: answered from the quick reference, without
  Lightning;
- ``--help_all``: the full parser (Lightning's Trainer options), the time every answer took before.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = str(ROOT / "train" / "fit_mask.py")
COMMANDS = {
    "python -c pass": [sys.executable, "-c", "pass"],
    'python -c "import torch"': [sys.executable, "-c", "import torch"],
    "fit_mask.py --help": [sys.executable, SCRIPT, "--help"],
    "fit_mask.py --data.flavor camera": [sys.executable, SCRIPT, "--data.flavor", "camera"],
    "fit_mask.py --data.size abc": [sys.executable, SCRIPT, "--data.size", "abc"],
    "fit_mask.py --help_all (full parser)": [sys.executable, SCRIPT, "--help_all"],
}


def seconds(command: list[str]) -> float:
    """Wall time of ``command`` in a fresh process."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, check=False)
    return time.perf_counter() - start


def main() -> None:
    """Time every command ``--rounds`` times and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="rounds of every command (default: 5)")
    rounds = parser.parse_args().rounds
    times: dict[str, list[float]] = {name: [] for name in COMMANDS}
    for _ in range(rounds):
        for name, command in COMMANDS.items():
            times[name].append(seconds(command))
    floors = ("python -c pass", 'python -c "import torch"')
    print(
        f"{'command':<38}{'median s':>10}{'x pass':>9}{'x import torch':>16}   (load average {os.getloadavg()[0]:.1f})"
    )
    for name, values in times.items():
        ratios = [
            statistics.median(value / floor for value, floor in zip(values, times[name_of_floor], strict=True))
            for name_of_floor in floors
        ]
        print(f"{name:<38}{statistics.median(values):>10.2f}{ratios[0]:>9.1f}{ratios[1]:>16.2f}")


if __name__ == "__main__":
    main()
