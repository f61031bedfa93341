"""Draw the speed page's figure from the measured ratios in ``data_tools/results/speed.csv`` (no timing here).

    python -m data_tools.benchmarks.figure_speed --figure docs/images/speed.png

Each bar is how many times faster the library's call is than its baseline (below 1: slower), on a log scale. The
ratios are copied by hand from the benchmarks' printed tables (the ``source`` column names the benchmark); rerun a
benchmark, update its row, then redraw.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results" / "speed.csv"


def read_rows(path: Path) -> list[dict]:
    """The rows of the ratios file, each with ``speedup`` as a float."""
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        row["speedup"] = float(row["speedup"])
    return rows


def draw(rows: list[dict], path: Path) -> None:
    """One horizontal bar per row: the speed-up over the baseline, log scale, 1 marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{row['comparison']}: {row['method']}\nagainst {row['baseline']}" for row in rows]
    values = [row["speedup"] for row in rows]
    colours = ["tab:green" if value >= 1 else "tab:red" for value in values]
    figure, axes = plt.subplots(figsize=(10, 0.55 * len(rows) + 1))
    positions = range(len(rows))[::-1]
    axes.barh(list(positions), values, color=colours)
    axes.set_yticks(list(positions), labels, fontsize=7)
    axes.set_xscale("log")
    axes.axvline(1, color="black", linewidth=0.8)
    for position, value in zip(positions, values, strict=True):
        axes.text(value, position, f" {value:g}x", va="center", fontsize=8)
    axes.set_xlabel("times faster than the baseline (log scale; below 1: slower)")
    axes.set_xlim(0.1, 1000)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=RESULTS, help="the ratios (CSV)")
    parser.add_argument("--figure", type=Path, default=Path("runs/speed.png"), help="PNG to write")
    args = parser.parse_args(argv)
    draw(read_rows(args.results), args.figure)
    print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
