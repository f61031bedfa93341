"""enmi-example: the map as a GeoTIFF in the pair's CRS, a captured image where it says, with the noise it says, pairs
for enmi-fit-mask, and an answer that enmi-localize finds; every option's mistake in one line before any work."""

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import ndimage

from enmi_torch.cli.example import camera_like_variance, main
from enmi_torch.cli.localize import _command as localize_command
from enmi_torch.data import PairDataset, example_pair

ROOT = Path(__file__).resolve().parents[2]
# Off the default place, heading, shape and seed; odd sides, so the centre pixel (h // 2, w // 2) is the image's
# centre, about which it turns: the direct sampling below needs no convention for even sides.
CENTER, HEADING, SIZE = (671440.0, 3542230.0), -4.0, (45, 39)


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("example") / "nanjing"
    arguments = [str(out), "--center-world", *map(str, CENTER), "--heading", str(HEADING)]
    arguments += ["--size", *map(str, SIZE), "--noise", "15", "--pairs", "12", "--pair-size", "24", "--seed", "3"]
    completed = subprocess.run(
        [sys.executable, "-m", "enmi_torch.cli.example", *arguments], cwd=ROOT, capture_output=True, text=True
    )
    assert completed.returncode == 0 and completed.stderr == "", completed.stderr
    return out, completed.stdout


def truth_cells(world_x: float, world_y: float) -> tuple[float, float]:
    """Map cell (x, y) of a world point, from the ENVI header's corner and 30 m cells, north up."""
    return (world_x - 660585.0) / 30.0 - 0.5, (3551295.0 - world_y) / 30.0 - 0.5


def test_the_answer_is_printed_in_world_coordinates_and_cells(written):
    out, printed = written
    x, y = truth_cells(*CENTER)
    expected = (
        f"the captured image's centre lies on world ({CENTER[0]:.2f}, {CENTER[1]:.2f}), heading {HEADING:.2f} "
        f"degrees: map cell (x, y) = ({x:.2f}, {y:.2f}), yaw {HEADING:.2f}"
    )
    assert printed.splitlines()[-1] == expected
    truth = json.loads((out / "example.json").read_text())["truth"]
    assert truth["x"] == pytest.approx(x, abs=1e-8) and truth["y"] == pytest.approx(y, abs=1e-8)
    assert truth["yaw_deg"] == truth["world_yaw_deg"] == HEADING  # north up: the cell yaw is the heading
    assert [truth["world_x"], truth["world_y"]] == list(CENTER)


def test_the_map_is_a_geotiff_in_the_pairs_crs_and_transform(written):
    rasterio = pytest.importorskip("rasterio")
    out, printed = written
    with rasterio.open(out / "map_2000.tif") as dataset:
        assert dataset.crs.to_string() == "EPSG:32650" and dataset.count == 1 and dataset.dtypes[0] == "uint8"
        assert tuple(dataset.transform)[:6] == (30.0, 0.0, 660585.0, 0.0, -30.0, 3551295.0)
        assert np.array_equal(dataset.read(1), example_pair().earlier[0, 0].numpy().astype(np.uint8))
    assert f"wrote {out / 'map_2000.tif'}: the 2000 image, the map (top-left corner 660585 E, 3551295 N)" in printed


def test_the_captured_image_is_the_2002_image_there_plus_the_noise_of_its_variance(written):
    out, _ = written
    captured = np.load(out / "captured_2002.npy")
    variance = np.load(out / "captured_variance.npy")
    assert captured.shape == variance.shape == SIZE and captured.dtype == variance.dtype == np.float32
    # The variance: 100 times larger on the top row than on the bottom one, mean standard deviation 15.
    assert np.sqrt(variance).mean() == pytest.approx(15.0, rel=1e-5)
    assert variance[0, 0] / variance[-1, 0] == pytest.approx(100.0, rel=1e-5)
    assert np.all(variance == variance[:, :1]) and np.all(np.diff(variance[:, 0]) < 0)
    # The clean image, sampled directly: pixel (row v, column u) shows the map at the centre plus the pixel's offset
    # turned by the heading (the image's top points HEADING degrees clockwise from north), by a cubic spline.
    x, y = truth_cells(*CENTER)
    rows, cols = np.mgrid[: SIZE[0], : SIZE[1]].astype(np.float64)
    du, dv = cols - SIZE[1] // 2, rows - SIZE[0] // 2
    angle = math.radians(HEADING)
    map_x = x + math.cos(angle) * du - math.sin(angle) * dv
    map_y = y + math.sin(angle) * du + math.cos(angle) * dv
    later = example_pair(torch.float64).later[0, 0].numpy()
    clean = ndimage.map_coordinates(later, [map_y, map_x], order=3, mode="mirror")
    assert 0 <= captured.min() and captured.max() <= 255.999
    inside = (captured > 0) & (captured < 255.999)  # not clipped
    assert inside.mean() > 0.9
    standardised = (captured - clean)[inside] / np.sqrt(variance[inside])
    assert abs(standardised.mean()) < 0.1 and standardised.std() == pytest.approx(1.0, abs=0.08)
    # Sampled a cell off along either axis (or with the heading's sign flipped), the residual is far larger.
    for shifted in ([map_y, map_x + 1], [map_y + 1, map_x]):
        wrong = ndimage.map_coordinates(later, shifted, order=3, mode="mirror")
        assert ((captured - wrong)[inside] / np.sqrt(variance[inside])).std() > 1.5


def test_the_pairs_are_crops_of_both_dates_with_the_noise_meta_json_names(written):
    out, printed = written
    dataset = PairDataset(out / "pairs")
    assert len(dataset) == 12 and dataset.shape == (24, 24)
    variance = camera_like_variance((24, 24), 15.0)
    torch.testing.assert_close(dataset.truth.variance, variance)
    pair = example_pair(torch.float64)
    earlier, later = pair.earlier[0, 0].numpy(), pair.later[0, 0].numpy()
    windows = np.lib.stride_tricks.sliding_window_view(earlier, (24, 24))
    standardised, places = [], set()
    for item in (dataset[index] for index in range(len(dataset))):
        prior, local = item["prior"][0].double().numpy(), item["local"][0].double().numpy()
        tops, lefts = np.nonzero((windows == prior).all(axis=(-2, -1)))
        assert len(tops) == 1  # the prior is the 2000 image's cells at one place
        top, left = int(tops[0]), int(lefts[0])
        places.add((top, left))
        inside = (local > 0) & (local < 255.999)
        residual = local - later[top : top + 24, left : left + 24]
        standardised.append(residual[inside] / np.sqrt(variance.numpy()[inside]))
    standardised = np.concatenate(standardised)
    assert len(places) == 12 and abs(standardised.mean()) < 0.1 and standardised.std() == pytest.approx(1, abs=0.08)
    assert f"wrote {out / 'pairs'}: 12 pairs of 24 x 24 (2002 with the same noise, 2000)" in printed


def test_enmi_localize_finds_the_answer_from_a_prior_tens_of_metres_off(written):
    pytest.importorskip("rasterio")
    out, _ = written
    arguments = ["--map", str(out / "map_2000.tif"), "--local", str(out / "captured_2002.npy")]
    arguments += ["--variance", str(out / "captured_variance.npy"), "--shifts", "8", "--yaws", "-8:8:2"]
    report = localize_command([*arguments, "--prior-world", str(CENTER[0] - 50), str(CENTER[1] + 40)])
    x, y = truth_cells(*CENTER)
    assert abs(report["world_x"] - CENTER[0]) < 15 and abs(report["world_y"] - CENTER[1]) < 15  # half a cell
    assert abs(report["x"] - x) < 0.5 and abs(report["y"] - y) < 0.5
    assert abs(report["world_yaw_deg"] - HEADING) < 1.5 and report["crs"] == "EPSG:32650"


def test_the_same_seed_writes_the_same_files_and_the_pairs_do_not_change_the_captured_image(tmp_path, capsys):
    main([str(tmp_path / "a"), "--pairs", "2", "--pair-size", "16"])
    main([str(tmp_path / "b"), "--pairs", "0"])
    main([str(tmp_path / "c"), "--pairs", "0", "--seed", "1"])
    capsys.readouterr()
    captured = {name: np.load(tmp_path / name / "captured_2002.npy") for name in "abc"}
    assert np.array_equal(captured["a"], captured["b"]) and not np.array_equal(captured["a"], captured["c"])
    assert not (tmp_path / "b" / "pairs").exists()


def test_without_rasterio_a_note_names_the_extra_and_the_map_is_written_as_npy(tmp_path):
    script = (
        "import sys\nsys.modules['rasterio'] = None\n"
        "from enmi_torch.cli.example import main\n"
        f"main([{str(tmp_path / 'out')!r}, '--pairs', '0'])\n"
    )
    completed = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True)
    assert completed.returncode == 0, completed.stderr
    assert completed.stderr.count("\n") == 1 and 'pip install "enmi_torch[geo]"' in completed.stderr
    assert "enmi-localize --around X Y" in completed.stderr
    assert not (tmp_path / "out" / "map_2000.tif").exists()
    assert np.array_equal(np.load(tmp_path / "out" / "map_2000.npy"), example_pair().earlier[0, 0].numpy())
    assert "map cell (x, y) = (336.33, 144.67)" in completed.stdout


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--size", "4", "64"], "--size must be from 8 to 512 cells, got 4 64"),
        (["--size", "64", "513"], "--size must be from 8 to 512 cells, got 64 513"),
        (["--pair-size", "7"], "--pair-size must be from 8 to 512 cells, got 7"),
        (["--noise", "0"], r"--noise must be a standard deviation in \(0, 1000\] grey levels, got 0.0"),
        (["--noise", "nan"], r"--noise must be a standard deviation in \(0, 1000\] grey levels, got nan"),
        (["--pairs", "-1"], "--pairs must be 0 or more, got -1"),
        (["--seed", "-2"], "--seed must be 0 or more, got -2"),
        (["--heading", "inf"], "--heading must be a finite number of degrees, got inf"),
        (["--center-world", "670690", "nan"], r"--center-world must be two finite numbers \(metres\), got 670690 nan"),
        (
            ["--center-world", "660600", "3546940"],
            r"--center-world 660600 3546940 \(map cell x 0.0, y 144.7\) puts part of the 64 x 64 captured image off "
            "the 512 x 512 map, which spans easting 660585 to 675945 and northing 3535935 to 3551295",
        ),
        (["--size", "64"], "argument --size: expected 2 arguments"),
        (["--noise", "x"], "argument --noise: invalid float value: 'x'"),
        (["--sizes", "3"], r"unrecognized arguments: --sizes 3 \(did you mean --size\?\)"),
    ],
)
def test_every_mistake_is_one_line_and_exit_2_before_any_work(tmp_path, capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "out"), *arguments])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1, error
    assert re.match(f"enmi-example: error: {message}", error), error
    assert not (tmp_path / "out").exists()


def test_out_must_be_a_new_or_empty_folder(tmp_path, capsys):
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "x.txt").write_text("x")
    (tmp_path / "file").write_text("x")
    for out, message in (
        ("taken", "OUT must be a new or empty folder, got '.*taken', which holds files"),
        ("file", "OUT must be a folder, got '.*file', which is a file"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main([str(tmp_path / out)])
        assert exit_info.value.code == 2 and re.match(f"enmi-example: error: {message}", capsys.readouterr().err)
    assert sorted(path.name for path in (tmp_path / "taken").iterdir()) == ["x.txt"]
    (tmp_path / "empty").mkdir()
    main([str(tmp_path / "empty"), "--pairs", "0"])
    assert (tmp_path / "empty" / "captured_2002.npy").is_file()


@pytest.mark.parametrize("shape", [(5, 3), (8, 13), (64, 64)])
def test_the_camera_like_variance_in_closed_form(shape):
    variance = camera_like_variance(shape, 7.0)
    height = shape[0]
    depth = [1 + (100 ** (1 / 3) - 1) * (height - 1 - row) / (height - 1) for row in range(height)]
    profile = np.array([value**3 for value in depth])
    scale = 7.0 / np.sqrt(profile).mean()
    expected = np.repeat((scale**2 * profile)[:, None], shape[1], axis=1)
    np.testing.assert_allclose(variance.numpy(), expected, rtol=1e-12)
    assert variance.dtype == torch.float64 and variance.shape == shape
