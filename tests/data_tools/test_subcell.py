"""data_tools.experiments.registration.subcell: the truth is exact, a tiny run prints its tables, mistakes refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from skimage import data

from data_tools.experiments.registration import subcell


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """Two photographs in a folder, an RGB and a grey PNG (scikit-image's astronaut and camera), and a text file."""
    folder = tmp_path_factory.mktemp("photos")
    Image.fromarray(data.astronaut()).save(folder / "astronaut.png")
    Image.fromarray(data.camera()).save(folder / "camera.png")
    (folder / "notes.txt").write_text("not a photograph")
    return folder


def test_the_photographs_are_read_as_luma(photos):
    paths = subcell.photo_paths([str(photos)])
    assert [path.name for path in paths] == ["astronaut.png", "camera.png"]
    rgb = data.astronaut().astype(np.float64)
    expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    np.testing.assert_allclose(subcell.luma(paths[0]).numpy(), expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(subcell.luma(paths[1]).numpy(), data.camera().astype(np.float64), atol=1e-9)
    assert subcell.photo_paths([str(photos / "*.png")]) == paths


def test_the_captured_image_is_the_maps_cells_moved_by_the_truth_exactly(photos):
    # Where the move is a whole number of cells the captured image is the map's own cells there; a third of a cell
    # is one source pixel: block means of the photograph, no interpolation. A swapped axis or a sign fails.
    maps, clean, truth, draws = subcell.make_trials(subcell.photo_paths([str(photos)]), 24, seed=3)
    assert maps.shape == (24, 1, 80, 80) and clean.shape == (24, 1, 64, 64) and draws.shape == clean.shape
    moves = ((truth[:, :2] - 40) * 3).round()
    torch.testing.assert_close(moves / 3, truth[:, :2] - 40, rtol=0, atol=1e-12)
    assert bool((moves.abs() <= 17).all()) and bool((truth[:, 2] == 0).all())
    whole = ((moves % 3) == 0).all(1).nonzero()[:, 0].tolist()
    assert whole  # some trials move by whole cells on both axes
    for trial in whole:
        x, y = (int(value) for value in truth[trial, :2].tolist())  # the captured centre pixel (32, 32) on cell (y, x)
        torch.testing.assert_close(clean[trial, 0], maps[trial, 0, y - 32 : y + 32, x - 32 : x + 32], rtol=0, atol=0)
    captured, variance = subcell.noisy(clean, draws, "camera-like", 30.0)
    assert float(captured.min()) >= 0 and float(captured.max()) <= 255.999
    assert float(variance[0, 0, 0].mean()) == pytest.approx(100 * float(variance[0, 0, -1].mean()))  # far row 100x
    assert float(variance[0, 0].sqrt().mean()) == pytest.approx(30.0)


def test_a_tiny_run_prints_its_tables_and_draws_its_figure(photos, tmp_path, capsys):
    figure = tmp_path / "subcell.png"
    methods = ["parabola", "register ECR true", "register ECR uniform", "register NCC"]
    arguments = ["--photos", str(photos), "--trials", "4", "--levels", "10", "--sensors", "lidar-like"]
    subcell.main([*arguments, "--methods", *methods, "--figure", str(figure)])
    lines = capsys.readouterr().out.splitlines()
    rows = [line for line in lines if line.startswith("| lidar-like | 10 |")]
    assert len(rows) == 2  # the table and the claims
    cells = rows[0].split(" | ")
    assert 0 <= int(cells[2]) <= 4 and float(cells[3]) >= 0  # found, the parabola's RMS
    assert all("±" in cell for cell in cells[4:])
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--photos", "/nonexistent/folder"], "names no PNG, JPEG or TIFF file"),
        (["--trials", "1"], "--trials must be >= 2"),
        (["--levels", "-1"], "--levels finite numbers >= 0"),
    ],
)
def test_mistakes_are_one_line_and_exit_code_2(photos, arguments, message, capsys):
    if arguments[0] != "--photos":
        arguments = ["--photos", str(photos), *arguments]
    with pytest.raises(SystemExit) as stopped:
        subcell.main(arguments)
    assert stopped.value.code == 2 and message in capsys.readouterr().err
