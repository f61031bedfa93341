"""make_example_pair: the luma of bands 3, 2, 1 through one stretch for both dates, the crop's transform, the sidecar;
and, where the raw Landsat files are on this machine, exactly the bundled files."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from data_tools.make_example_pair import main
from enmi_torch.data import example_pair
from enmi_torch.data.example import FILES, SIDECAR

RAW = Path("/work/data/landsat")
SCENES = ("LT51200382000124BJC00_Nanjing", "LT51200382002193BJC00_Nanjing")


def write_source(folder: Path, earlier: np.ndarray, later: np.ndarray, change: np.ndarray) -> None:
    """Raw BSQ files of 6 uint8 bands (TM 1, 2, 3, 4, 5, 7) of 800 x 800 and change.bmp, as the source holds them."""
    folder.mkdir()
    for name, bands in zip(SCENES, (earlier, later), strict=True):
        bands.astype(np.uint8).tofile(folder / name)
    Image.fromarray(change.astype(np.uint8)).save(folder / "change.bmp")


def test_luma_of_red_green_blue_through_one_stretch_and_the_crops_transform(tmp_path, capsys):
    generator = np.random.default_rng(0)
    earlier = generator.integers(0, 256, (6, 800, 800))
    later = generator.integers(0, 256, (6, 800, 800))
    later[3:] = 0  # bands 4, 5, 7 play no part in the grey image
    change = np.zeros((800, 800))
    change[700, 30] = 255
    write_source(tmp_path / "source", earlier, later, change)
    main(
        ["--source", str(tmp_path / "source"), "--out", str(tmp_path / "out"), "--size", "100", "--offset", "20", "650"]
    )
    assert "100 x 100 cells of both dates" in capsys.readouterr().out
    # Direct: TM band 3 is red (index 2), band 2 green (1), band 1 blue (0); the 2000 luma's percentiles over the
    # whole subset set one linear map for both dates.
    luma = [0.299 * bands[2] + 0.587 * bands[1] + 0.114 * bands[0] for bands in (earlier, later)]
    low, high = np.percentile(luma[0], [0.5, 99.5])
    for role, image in zip(("earlier", "later"), luma, strict=True):
        written = np.asarray(Image.open(tmp_path / "out" / FILES[role]))
        expected = np.clip((image[650:750, 20:120] - low) / (high - low) * 255, 0, 255)
        assert written.dtype == np.uint8 and np.abs(written - expected).max() <= 0.5 + 1e-9
    written_change = np.asarray(Image.open(tmp_path / "out" / FILES["change"]))
    assert np.argwhere(written_change).tolist() == [[50, 10]] and written_change.max() == 255
    info = json.loads((tmp_path / "out" / SIDECAR).read_text())
    # Cell (0, 0) of the crop is column 20, row 650 of the subset: its corner 600 m east, 19500 m south of 660585,
    # 3551295.
    assert info["transform"] == [30.0, 0.0, 660585.0 + 600.0, 0.0, -30.0, 3551295.0 - 19500.0]
    assert info["shape"] == [100, 100] and info["crs"] == "EPSG:32650"
    assert info["stretch"] == {"low": pytest.approx(low, abs=1e-6), "high": pytest.approx(high, abs=1e-6)}


@pytest.mark.skipif(not (RAW / SCENES[0]).is_file(), reason="the raw Landsat files are not on this machine")
def test_the_raw_files_give_the_bundled_pair(tmp_path, capsys):
    main(["--source", str(RAW), "--out", str(tmp_path)])
    capsys.readouterr()
    bundled = example_pair()
    for role in FILES:
        written = np.asarray(Image.open(tmp_path / FILES[role]))
        expected = getattr(bundled, role)[0, 0].numpy()
        assert np.array_equal(written > 0 if role == "change" else written, expected)
    info = json.loads((tmp_path / SIDECAR).read_text())
    assert {key: value for key, value in info.items() if key != "sha256"} == {
        key: value for key, value in bundled.info.items() if key != "sha256"
    }


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--size", "600", "--offset", "300", "0"], "--size 600 from --offset 300 0 must fit in the 800 x 800"),
        (["--source", "nowhere"], "--source: no file 'nowhere/LT51200382000124BJC00_Nanjing'"),
    ],
)
def test_mistakes_in_one_line(tmp_path, capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path / "out"), *arguments])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.startswith(f"python -m data_tools.make_example_pair: error: {message}")
    assert not (tmp_path / "out").exists()


def test_a_file_of_another_size_is_named(tmp_path, capsys):
    (tmp_path / "source").mkdir()
    (tmp_path / "source" / SCENES[0]).write_bytes(b"\0" * 100)
    with pytest.raises(SystemExit):
        main(["--source", str(tmp_path / "source"), "--out", str(tmp_path / "out")])
    assert "holds 100 bytes, expected 3840000 (6 uint8 bands of 800 x 800, BSQ)" in capsys.readouterr().err
