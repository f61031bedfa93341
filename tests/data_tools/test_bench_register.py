"""data_tools.benchmarks.bench_register runs on a tiny cell and refuses bad cells in one line."""

from __future__ import annotations

import pytest

from data_tools.benchmarks import bench_register


@pytest.fixture(scope="module")
def bench():
    return bench_register


def test_a_tiny_run_prints_its_table(bench, capsys):
    methods = ["quadratic fit", "register ECR true", "register ECR uniform"]
    bench.main(["--trials", "4", "--cells", "camera-like@15+tone", "--methods", *methods])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| camera-like@15+tone |")]
    assert [row.split(" | ")[1] for row in rows] == methods
    found = int(rows[0].split(" | ")[2])
    assert 0 <= found <= 4


@pytest.mark.parametrize("cell", ["camera@60", "camera-like", "lidar-like@"])
def test_a_bad_cell_is_one_line_and_exit_code_2(bench, cell, capsys):
    with pytest.raises(SystemExit) as stopped:
        bench.main(["--cells", cell])
    assert stopped.value.code == 2
    assert "a cell is sensor@sigma[+change]" in capsys.readouterr().err
