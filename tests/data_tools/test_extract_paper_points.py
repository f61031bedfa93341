"""The paper's plotted points, read from its LaTeX source by ``data_tools.experiments.paper.extract_paper_points``."""

import pytest

from data_tools.experiments.paper import extract_paper_points


def test_extract_paper_points_reads_the_plot_part():
    tool = extract_paper_points
    tex = (
        "\\begin{document} (0.5,0.9) \\end{document}\n%% file: FiguresNMI/plot.tex\n"
        "\\addplot [blue] coordinates{ (0.001,0.0) (0.01, 0.25)\n(2.0,0.5) };\n"
        "\\addplot [black] coordinates{\n(0.001,0.0)\n(0.01,0.0048)\n(2.0,0.49)\n};\n"
    )
    assert tool.extract_points(tex) == [("0.001", "0.0", "0.0"), ("0.01", "0.25", "0.0048"), ("2.0", "0.5", "0.49")]
    with pytest.raises(ValueError, match="plot part"):
        tool.extract_points("no plot here")
    with pytest.raises(ValueError, match="same N0"):
        tool.extract_points(tex.replace("(2.0,0.49)", "(3.0,0.49)"))
