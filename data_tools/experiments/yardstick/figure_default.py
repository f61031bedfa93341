"""Draw where the default score wins and loses: each control minus ``ECR()``, paired per trial, per cell of real pairs.

    python -m data_tools.experiments.yardstick.figure_default --figure docs/images/default_vs_controls.png

Reads the ``results.csv`` files that ``scene_change.py`` writes (one outcome bit per trial and method; the committed
ones are in ``data_tools/results/``), pairs every method with ``ECR true`` (the default ``ECR()`` with the sensor's
variance) trial by trial, and draws the mean difference with one standard error per cell: left, the controls a user
would try (a uniform variance, the linear response, NCC, the binned response); right, the default without each of
its parts (the last release's default, the surface without the finalist stage, saturated readings as Gaussian) and,
in issue 33's files (``scene_change_issue33*.csv``), the remedies tried for the other-date cells then (a fixed large
``tau^2``, the misfit counted per patch, the variance capped at the clipping range, the regional misfit read at the
first pass's peak and, an oracle, at the true placement).
A point right of zero is a control ahead of the default. Prints the same numbers as a table.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from data_tools.experiments.yardstick import scene_change

RESULTS = Path(__file__).resolve().parents[2] / "results"
DEFAULT_INPUTS = (RESULTS / "scene_change_default.csv", RESULTS / "scene_change_default_heldout.csv")
DEFAULT = "ECR true"
PANELS = {
    "controls a user would try": ("ECR uniform x1", "ECR linear true", "NCC", "ECR binned true"),
    # Issue 41's parts of the default (their rows in its runs), and issue 33's remedies (in its runs' files).
    "the default without its parts, and other remedies": (
        "ECR before true",
        "ECR surface true",
        "ECR Gaussian true",
        "ECR tau 4096",
        "ECR correlated true",
        "ECR capped true",
        "ECR regional true",
        "ECR regional at truth",
    ),
}
LABELS = {
    "ECR before true": "the last release's default",
    "ECR surface true": "without the finalist stage",
    "ECR Gaussian true": "saturated readings as Gaussian",
    "ECR uniform x1": "uniform variance (its mean)",
    "ECR linear true": 'ECR(response="linear"), true variance',
    "NCC": "NCC",
    "ECR binned true": 'ECR(response="binned") (former default)',
    "ECR tau 4096": "tau^2 fixed at 4096",
    "ECR correlated true": 'ECR(misfit="correlated")',
    "ECR capped true": "variance capped at (clip range)^2 / 4",
    "ECR regional true": 'ECR(misfit="regional")',
    "ECR regional at truth": "regional misfit read at the truth (oracle)",
}


def read_cells(paths: list[Path], held_out: list[bool]) -> dict[str, dict[str, np.ndarray]]:
    """Per cell label (``case, sensor, sigma``, marked held-out), each method's outcomes per trial."""
    cells: dict[str, dict[str, np.ndarray]] = {}
    for path, is_held_out in zip(paths, held_out, strict=True):
        for case, sensor, level, method, _, _, bits, _ in scene_change.read_rows(path):
            label = f"{case}, {sensor}, sigma {level:g}" + (" (held out)" if is_held_out else "")
            cells.setdefault(label, {})[method] = scene_change.outcome_bits(bits)
    for label, methods in cells.items():
        if DEFAULT not in methods:
            raise ValueError(f"cell {label!r} has no {DEFAULT!r} outcomes to pair with")
    return cells


def differences(cells: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, tuple[float, float]]]:
    """Per method, per cell: the method minus the default, mean and standard error."""
    table: dict[str, dict[str, tuple[float, float]]] = {}
    for label, methods in cells.items():
        for method, outcomes in methods.items():
            if method != DEFAULT:
                table.setdefault(method, {})[label] = scene_change.paired_difference(outcomes, methods[DEFAULT])
    return table


def draw(cells: dict[str, dict[str, np.ndarray]], table: dict, path: Path) -> None:
    """Two panels of per-cell points with one-SE bars, cells as rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(cells)
    figure, axes = plt.subplots(1, len(PANELS), figsize=(13, 0.5 * len(labels) + 1.8), sharey=True)
    for axis, (title, methods) in zip(axes, PANELS.items(), strict=True):
        shown = [method for method in methods if method in table]
        for offset, method in enumerate(shown):
            rows = [(index, *table[method][label]) for index, label in enumerate(labels) if label in table[method]]
            position = [len(labels) - 1 - index + 0.5 - (offset + 1) / (len(shown) + 1) for index, _, _ in rows]
            axis.errorbar(
                [mean for _, mean, _ in rows],
                position,
                xerr=[se for _, _, se in rows],
                fmt="o",
                markersize=4,
                capsize=2,
                label=LABELS.get(method, method),
            )
        axis.axvline(0, color="black", linewidth=0.8)
        axis.set_title(title, fontsize=10)
        axis.set_xlabel("success minus the default's (paired, one SE)")
        axis.legend(fontsize=7, loc="lower left")
        for boundary in range(1, len(labels)):
            axis.axhline(boundary - 0.5, color="0.9", linewidth=0.5)
    axes[0].set_yticks([len(labels) - 1 - index for index in range(len(labels))], labels, fontsize=7)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def print_table(cells: dict[str, dict[str, np.ndarray]], table: dict) -> None:
    methods = [method for panel in PANELS.values() for method in panel if method in table]
    print("| cell | ECR() | " + " | ".join(f"{LABELS.get(method, method)} - ECR()" for method in methods) + " |")
    print("|---" * (len(methods) + 2) + "|")
    for label, outcomes in cells.items():
        rate = float(outcomes[DEFAULT].mean())
        parts = []
        for method in methods:
            mean, se = table[method].get(label, (math.nan, math.nan))
            parts.append(f"{mean:+.3f} ± {se:.3f}" + (" **" if abs(mean) > 2 * se else ""))
        print(f"| {label} | {rate:.2f} | " + " | ".join(parts) + " |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    parser.add_argument("--results", type=Path, nargs="+", default=list(DEFAULT_INPUTS), help="results.csv files")
    parser.add_argument(
        "--held-out", type=int, nargs="*", default=[1], help="indices of --results that are held-out sets (default 1)"
    )
    parser.add_argument("--figure", type=Path, default=Path("runs/default_vs_controls.png"), help="PNG to write")
    args = parser.parse_args(argv)
    for path in args.results:
        if not path.is_file():
            parser.error(f"--results: {path} is not a file")
    if any(not 0 <= index < len(args.results) for index in args.held_out):
        parser.error(f"--held-out: indices must lie in 0..{len(args.results) - 1}, got {args.held_out}")
    held_out = [index in args.held_out for index in range(len(args.results))]
    try:
        cells = read_cells(args.results, held_out)
    except (IndexError, ValueError) as error:
        parser.error(f"--results: {error}")
    table = differences(cells)
    print_table(cells, table)
    draw(cells, table, args.figure)
    print(f"\nwrote {args.figure}")


if __name__ == "__main__":
    main()
