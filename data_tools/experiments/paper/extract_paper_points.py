r"""Extract the plotted points of the paper's Fig. simPerformance (committed as ``configs/paper_points.csv``).

The figure's data is the pgfplots file ``FiguresNMI/plot.tex``, appended at the end of the paper's source
(``aspconArXiv.tex``): two ``\addplot coordinates{...}`` blocks, NMI first, ENMI second, over the same N0 values.

    python -m data_tools.experiments.paper.extract_paper_points path/to/aspconArXiv.tex  # writes runs/paper_points.csv
    python -m data_tools.experiments.paper.extract_paper_points path/to/aspconArXiv.tex \
        --output configs/paper_points.csv
"""

from __future__ import annotations

import argparse
import csv
import re
from pathlib import Path

PLOT_MARKER = "%% file: FiguresNMI/plot.tex"
DEFAULT_OUTPUT = Path("runs/paper_points.csv")


def extract_points(tex: str) -> list[tuple[str, str, str]]:
    """Rows ``(noise_power, nmi, enmi)`` as the strings the paper prints, in its order."""
    if PLOT_MARKER not in tex:
        raise ValueError(f"the paper source must contain the plot part {PLOT_MARKER!r}; it does not")
    blocks = re.findall(r"coordinates\s*\{(.*?)\}", tex[tex.index(PLOT_MARKER) :], re.S)
    if len(blocks) != 2:
        raise ValueError(f"the plot part must hold 2 coordinate blocks (NMI, ENMI), found {len(blocks)}")
    nmi, enmi = ([tuple(point) for point in re.findall(r"\(\s*([^,\s]+)\s*,\s*([^)\s]+)\s*\)", b)] for b in blocks)
    if [n0 for n0, _ in nmi] != [n0 for n0, _ in enmi]:
        raise ValueError("the NMI and ENMI curves must be plotted over the same N0 values; they are not")
    return [(n0, nmi_rate, enmi_rate) for (n0, nmi_rate), (_, enmi_rate) in zip(nmi, enmi, strict=True)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("tex", type=Path, help="the paper's LaTeX source (aspconArXiv.tex)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT, help="CSV to write")
    args = parser.parse_args()
    rows = extract_points(args.tex.read_text())
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with args.output.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["noise_power", "nmi", "enmi"])
        writer.writerows(rows)
    print(f"wrote {len(rows)} points to {args.output}")


if __name__ == "__main__":
    main()
