import json

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage
from skimage import data

from data_tools.experiments.yardstick import prepare_scene_change


@pytest.fixture(scope="module")
def prep():
    return prepare_scene_change


@pytest.fixture(scope="module")
def photo():
    """A non-square grey photograph (CC0, scikit-image), float64 in [0, 255]."""
    return data.camera()[40:320, 60:460].astype(np.float64)


def _moved(image, dy, dx):
    """The image's content moved down by dy and right by dx (sub-pixel, cubic)."""
    return ndimage.shift(image, (dy, dx), order=3, mode="nearest")


@pytest.mark.parametrize(("dy", "dx"), [(0.0, 0.0), (2.0, -1.0), (0.4, 1.3), (-3.0, 0.0)])
def test_measure_offset_recovers_a_known_shift(prep, photo, dy, dx):
    captured = _moved(photo, dy, dx) + np.random.default_rng(0).normal(0, 8, photo.shape)
    measured = prep.measure_offset(photo, captured)
    np.testing.assert_allclose(measured["whole_image_offset_dy_dx"], [dy, dx], atol=0.2)
    np.testing.assert_allclose(measured["tiles_median_offset_dy_dx"], [dy, dx], atol=0.2)
    assert measured["tiles_agreeing"] >= 6
    assert prep.verdict(measured, 0.5)[0] == (max(abs(dy), abs(dx)) <= 0.5)


@pytest.mark.parametrize(("dy", "dx"), [(0.0, 0.0), (2.0, -1.0), (-1.0, 3.0)])
def test_nmi_finds_a_shift_across_a_non_monotone_tone_change(prep, photo, dy, dx):
    """Mid-grey bright, black and white both dark: correlation fails, mutual information does not."""
    captured = 255 * np.abs(2 * _moved(photo, dy, dx) / 255 - 1) ** 0.8
    measured = prep.measure_offset(photo, np.clip(captured, 0, 255), score="nmi")
    np.testing.assert_allclose(measured["whole_image_offset_dy_dx"], [dy, dx], atol=0.3)
    np.testing.assert_allclose(measured["tiles_median_offset_dy_dx"], [dy, dx], atol=0.3)


def test_pix2pix_test_run_takes_the_flat_image_as_the_map(prep, photo, tmp_path):
    flat = np.where(photo > 128, 240.0, 200.0)  # a rendering: two flat colours
    Image.fromarray(flat.astype(np.uint8)).save(tmp_path / "7_real_B.png")
    Image.fromarray(photo.astype(np.uint8)).save(tmp_path / "7_real_A.png")
    pair = next(prep.read_pix2pix_maps(tmp_path, "pix2pix-maps"))
    assert pair.name == "7"
    np.testing.assert_array_equal(pair.reference, flat)
    np.testing.assert_array_equal(pair.captured, photo)


def test_verdict_rejects_a_rotation_that_no_shift_fixes(prep, photo):
    angle = np.deg2rad(0.5)  # 0.5 degrees about the centre: ~2 px at the corners of a 280 x 400 image
    centre = np.array(photo.shape) / 2
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    captured = ndimage.affine_transform(photo, rotation, offset=centre - rotation @ centre, order=3, mode="nearest")
    measured = prep.measure_offset(photo, captured)
    assert max(abs(v) for v in measured["whole_image_offset_dy_dx"]) <= 0.5  # the centre lines up
    assert max(abs(v) for v in measured["tiles_median_offset_dy_dx"]) <= 0.5
    assert 1.2 < measured["tiles_affine_corner_deviation"] < 2.5
    assert prep.verdict(measured, 0.5) == (False, None)


def test_largest_rectangle_against_brute_force(prep):
    mask = np.random.default_rng(1).random((9, 13)) > 0.25
    rows, cols = prep.largest_rectangle(mask)
    assert mask[rows, cols].all()
    best = max(
        (bottom - top) * (right - left)
        for top in range(9)
        for bottom in range(top + 1, 10)
        for left in range(13)
        for right in range(left + 1, 14)
        if mask[top:bottom, left:right].all()
    )
    assert (rows.stop - rows.start) * (cols.stop - cols.start) == best


def _write_change_folders(root, photo, first="A", second="B"):
    for folder in (first, second, "label"):
        (root / folder).mkdir(parents=True)
    changed = np.zeros(photo.shape, dtype=bool)
    changed[100:160, 200:300] = True
    later = photo.copy()
    later[changed] = 255 - later[changed]  # a "new building"
    for name, captured in (("aligned", later), ("moved", _moved(later, 3.0, 0.0))):
        Image.fromarray(photo.astype(np.uint8)).save(root / first / f"{name}.png")
        Image.fromarray(np.clip(captured, 0, 255).astype(np.uint8)).save(root / second / f"{name}.png")
        Image.fromarray((changed * 255).astype(np.uint8)).save(root / "label" / f"{name}.png")


def test_change_folders_end_to_end(prep, photo, tmp_path):
    _write_change_folders(tmp_path / "levir", photo)
    out = tmp_path / "out"
    prep.main(["--dataset", "levir-cd", "--source", str(tmp_path / "levir"), "--out", str(out)])
    folder = out / "another-date" / "levir-cd-aligned"
    reference, captured = np.load(folder / "reference.npy"), np.load(folder / "captured.npy")
    assert reference.dtype == captured.dtype == np.float32
    assert reference.shape == captured.shape == photo.shape
    assert 0 <= reference.min() and captured.max() <= 255
    assert np.load(folder / "changed.npy").sum() == 60 * 100
    manifest = json.loads((out / "manifest.json").read_text())
    assert [pair["id"] for pair in manifest["pairs"]] == ["aligned"]
    assert [pair["id"] for pair in manifest["rejected"]] == ["moved"]

    prep.main(["--dataset", "levir-cd", "--source", str(tmp_path / "levir"), "--out", str(out), "--correct"])
    meta = json.loads((out / "another-date" / "levir-cd-moved" / "meta.json").read_text())
    assert meta["shape"] == [photo.shape[0] - 3, photo.shape[1]]
    assert "(3, 0)" in meta["notes"][0]
    assert max(abs(v) for v in meta["alignment"]["whole_image_offset_dy_dx"]) <= 0.2
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(pair["id"] for pair in manifest["pairs"]) == ["aligned", "moved"]
    assert manifest["rejected"] == []


def test_whu_cd_prev_and_curr_folders_are_read_as_the_two_dates(prep, photo, tmp_path):
    _write_change_folders(tmp_path / "whu", photo, first="prev", second="curr")
    pairs = {pair.name: pair for pair in prep.read_change_folders(tmp_path / "whu", "whu-cd")}
    assert sorted(pairs) == ["aligned", "moved"]
    np.testing.assert_array_equal(pairs["aligned"].reference, photo)  # the earlier date is the reference
    assert pairs["aligned"].changed.sum() == 60 * 100
    out = tmp_path / "out"
    prep.main(["--dataset", "whu-cd", "--source", str(tmp_path / "whu"), "--out", str(out)])
    meta = json.loads((out / "another-date" / "whu-cd-aligned" / "meta.json").read_text())
    assert meta["dataset"] == "whu-cd" and meta["paths"] == ["prev/aligned.png", "curr/aligned.png"]


def test_tiles_are_cut_named_and_checked_one_by_one(prep, photo, tmp_path):
    _write_change_folders(tmp_path / "whu", photo, first="prev", second="curr")
    out = tmp_path / "out"
    prep.main(["--dataset", "whu-cd", "--source", str(tmp_path / "whu"), "--out", str(out), "--tile", "200"])
    manifest = json.loads((out / "manifest.json").read_text())
    kept = sorted(pair["id"] for pair in manifest["pairs"])
    assert kept == ["aligned_0000_0000", "aligned_0000_0200"]  # 280 x 400: two whole tiles each
    assert sorted(pair["id"] for pair in manifest["rejected"]) == ["moved_0000_0000", "moved_0000_0200"]
    folder = out / "another-date" / "whu-cd-aligned_0000_0200"
    np.testing.assert_array_equal(np.load(folder / "reference.npy"), photo[:200, 200:400].astype(np.float32))
    assert json.loads((folder / "meta.json").read_text())["tile_top_left"] == [0, 200]


def test_srif_similarity_is_undone(prep, photo, tmp_path):
    """The second image is the first scaled by 0.8 and turned by 20 degrees; gt_1.txt maps 1-based pixels."""
    folder = tmp_path / "Optical-SAR"
    folder.mkdir()
    scale, angle = 0.8, np.deg2rad(20)
    linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])  # (x, y)
    shape = (300, 320)
    translation = np.array([shape[1], shape[0]]) / 2 - linear @ (np.array([photo.shape[1], photo.shape[0]]) / 2)
    first_to_second = np.vstack([np.hstack([linear, translation[:, None]]), [0, 0, 1]])  # 0-based (x, y)
    inverse = np.linalg.inv(first_to_second)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    x, y, _ = inverse @ np.stack([cols.ravel(), rows.ravel(), np.ones(rows.size)])
    second = ndimage.map_coordinates(photo, [y, x], order=3, cval=0.0).reshape(shape)
    Image.fromarray(photo.astype(np.uint8)).save(folder / "pair1_1.jpg", quality=95)
    Image.fromarray(np.clip(second, 0, 255).astype(np.uint8)).save(folder / "pair1_2.jpg", quality=95)
    one = np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 1]])
    np.savetxt(folder / "gt_1.txt", (one @ first_to_second @ np.linalg.inv(one))[:2])
    pair = next(prep.read_srif(tmp_path, "srif-optical-sar"))
    assert pair.reference.shape == pair.captured.shape
    assert min(pair.reference.shape) >= 150
    assert "first image's frame" in pair.meta["registration"]  # the second one's content is turned in its frame
    measured = prep.measure_offset(pair.reference, pair.captured)
    assert prep.verdict(measured, 0.5)[0], measured


def test_command_line_mistakes_exit_2(prep, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        prep.main(["--dataset", "levir-cd", "--source", str(tmp_path / "absent"), "--out", str(tmp_path)])
    assert stop.value.code == 2
    assert "--source: expected a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        prep.main(["--dataset", "whu-cd", "--source", str(tmp_path), "--out", str(tmp_path), "--tile", "64"])
    assert stop.value.code == 2
    assert "--tile: expected at least 150" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as stop:
        prep.main(["--dataset", "oscd", "--source", str(tmp_path / "empty"), "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert "no oscd pair found" in capsys.readouterr().err
