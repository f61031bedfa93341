"""enmi-localize on GeoTIFF maps: a prior in world coordinates, the answer in world coordinates and cells, only the
search's window read, the same search as on the whole array, and one-line mistakes."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from _geotiffs import CELL, TRANSFORMS, WORLD_YAW, DatasetReader, texture, write_raster, xy

from enmi_torch.cli.localize import _command, main
from enmi_torch.registration import warp_reference

ROOT = Path(__file__).resolve().parents[2]
TRUTH = (170, 64)  # map cell (x, y) of the local image's centre pixel: x the column, y the row
KEYS = ["x", "y", "yaw_deg", "dx", "dy", "row", "col", "score", "margin", "world_x", "world_y", "world_yaw_deg", "crs"]


def _files(tmp_path: Path, name: str, yaw: float = 0.0) -> tuple[list[str], tuple[float, float]]:
    """A GeoTIFF of the texture on the named transform, a noisy 32 x 40 local image at TRUTH, and the true world."""
    prior_map = texture()
    write_raster(tmp_path / f"{name}.tif", prior_map.astype(np.float32), TRANSFORMS[name])
    reference = torch.from_numpy(prior_map)[None, None]
    local = warp_reference(reference, torch.tensor([[*TRUTH, yaw]], dtype=torch.float64), (32, 40))[0][0, 0]
    local = local + 4 * torch.randn(local.shape, generator=torch.Generator().manual_seed(0), dtype=local.dtype)
    np.save(tmp_path / "local.npy", local.numpy())
    truth = xy(TRANSFORMS[name], TRUTH[1], TRUTH[0], offset="center")
    return ["--map", str(tmp_path / f"{name}.tif"), "--local", str(tmp_path / "local.npy"), "--variance", "16"], truth


@pytest.mark.parametrize("name", list(TRANSFORMS))
def test_a_prior_in_world_coordinates_is_answered_in_world_coordinates_and_cells(tmp_path, capsys, name):
    files, truth = _files(tmp_path, name, yaw=6.0)
    prior = [f"{truth[0] - 2.0}", f"{truth[1] + 1.5}"]  # 2 m west and 1.5 m north of the truth
    report = _command([*files, "--prior-world", *prior, "--shifts", "9", "--yaws", "0:12:3"])
    printed = json.loads(capsys.readouterr().out.splitlines()[0])
    assert printed == report and list(report) == KEYS and report["crs"] == "EPSG:32633"
    assert np.hypot(report["world_x"] - truth[0], report["world_y"] - truth[1]) < 0.2 * CELL, (report, truth)
    assert (report["col"], report["row"]) == pytest.approx(TRUTH, abs=0.2)
    assert report["yaw_deg"] == pytest.approx(6.0, abs=0.5)
    assert report["world_yaw_deg"] == pytest.approx(WORLD_YAW[name](report["yaw_deg"]), abs=0.01)


def test_the_search_reads_only_its_window_and_finds_what_the_whole_array_gives(tmp_path, capsys, monkeypatch):
    files, _ = _files(tmp_path, "rotated")
    np.save(tmp_path / "map.npy", texture().astype(np.float32))
    reads = []
    original = DatasetReader.read

    def recorded(self, *args, **kwargs):
        reads.append((int(kwargs["window"].height), int(kwargs["window"].width)))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(DatasetReader, "read", recorded)
    for options in (["--shifts", "9", "7"], ["--shifts", "12", "--coarse-factor", "4"]):
        geo = _command([*files, "--around", "166", "60", *options])
        assert len(reads) == 1
        rows, cols = reads.pop()
        radius_y, radius_x = int(options[1]), int(options[-1] if len(options) == 3 else options[1])
        needed = (2 * (radius_y + 16) + 1, 2 * (radius_x + 20) + 1)  # every shift with the 32 x 40 image
        assert needed[0] <= rows <= needed[0] + 2 + 2 * 4 and needed[1] <= cols <= needed[1] + 2 + 2 * 4
        whole = _command(["--map", str(tmp_path / "map.npy"), *files[2:], "--around", "166", "60", *options])
        assert {key: geo[key] for key in whole} == whole  # the same pose, score and margin as on the whole map
    capsys.readouterr()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--prior-world", "1", "2", "--around", "5", "5"], r"give the prior as --around X Y \(map cells\) or as"),
        (["--map-mask", "mask.npy"], "--map-mask is for .npy and .png maps; a GeoTIFF marks its own invalid cells"),
        (["--band", "2"], r"band must be a band number from 1 to 1 of --map '.*rotated\.tif', got 2"),
        (
            ["--prior-world", "0", "0"],
            r"the window around cell .* lies off the 200 x 260 map \(--map '.*rotated\.tif'\)",
        ),
        (["--prior-world", "nan", "0"], r"--prior-world must be two finite numbers X Y, got \[nan, 0\.0\]"),
        (["--prior-world", "1"], "argument --prior-world: expected 2 arguments"),
    ],
)
def test_command_line_mistakes_with_a_geotiff_end_in_one_line(tmp_path, capsys, arguments, message):
    files, _ = _files(tmp_path, "rotated")
    with pytest.raises(SystemExit) as exit_info:
        main([*files, *arguments])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and error.startswith("enmi-localize: error: ")
    assert re.search(message, error), error


def test_world_options_on_a_map_in_cells_are_refused_in_one_line(tmp_path, capsys):
    np.save(tmp_path / "map.npy", texture())
    np.save(tmp_path / "local.npy", texture()[10:42, 10:50])
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--variance", "4"]
    for flag, values in (("--prior-world", ["1", "2"]), ("--band", ["1"])):
        with pytest.raises(SystemExit) as exit_info:
            main([*files, flag, *values])
        error = capsys.readouterr().err
        assert exit_info.value.code == 2 and error.count("\n") == 1
        assert f"{flag} is for GeoTIFF maps; --map '{tmp_path / 'map.npy'}' is a .npy image in cells" in error


def test_a_prior_in_world_coordinates_on_a_tiff_without_georeferencing_is_refused(tmp_path, capsys):
    from PIL import Image

    Image.fromarray(texture().astype(np.uint8)).save(tmp_path / "plain.tif")
    np.save(tmp_path / "local.npy", texture()[10:42, 10:50])
    files = ["--map", str(tmp_path / "plain.tif"), "--local", str(tmp_path / "local.npy"), "--variance", "4"]
    with pytest.raises(SystemExit) as exit_info:
        main([*files, "--prior-world", "10", "20"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--prior-world needs a georeferenced map" in error
    report = _command([*files, "--around", "30", "26", "--shifts", "4"])  # in cells it works, without world keys
    assert list(report) == KEYS[:9] and (report["row"], report["col"]) == pytest.approx((26.0, 30.0), abs=0.1)
    capsys.readouterr()


def test_without_rasterio_a_geotiff_map_ends_in_one_line_naming_the_extra(tmp_path):
    files, _ = _files(tmp_path, "north_up")
    script = (
        "import sys\n"
        "sys.modules['rasterio'] = None\n"
        "from enmi_torch.cli.localize import main\n"
        f"main({[*files, '--shifts', '4']!r})\n"
    )
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert completed.returncode == 2 and completed.stderr.count("\n") == 1, completed.stderr
    assert 'reading a GeoTIFF needs rasterio: pip install "enmi_torch[geo]"' in completed.stderr


def test_help_names_the_world_options_and_keys(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--prior-world X Y" in text and "--band BAND" in text
    assert all(key in text for key in ("world_x, world_y", "world_yaw_deg", "crs"))
