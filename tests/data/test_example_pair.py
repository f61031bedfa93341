"""The bundled example pair: intact files, the transform of the ENVI header, two co-registered dates, its change map.

The raw source (``/work/data/landsat``: the ENVI files and the pair that
``data_tools/experiments/yardstick/prepare_scene_change.py`` prepared from them independently) is compared where this
machine has it.
"""

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from skimage.registration import phase_cross_correlation

from enmi_torch.data import ExamplePair, example_pair
from enmi_torch.data import example as example_module
from enmi_torch.data.example import FILES, SIDECAR, data_folder

RAW = Path("/work/data/landsat")


def test_the_files_are_the_ones_the_sidecar_names_and_hashes():
    folder = data_folder()
    info = json.loads((folder / SIDECAR).read_text())
    assert info["files"] == FILES
    for role, name in FILES.items():
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == info["sha256"][role], name
        assert (folder / name).stat().st_size < 250_000  # small enough to commit and ship
    assert {"source", "licence", "citation", "grey", "crs", "transform", "dates", "scenes"} <= set(info)
    assert "public domain" in info["licence"] and "Wu" in info["citation"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_pair_as_tensors(dtype):
    pair = example_pair(dtype)
    assert isinstance(pair, ExamplePair)
    for image in (pair.earlier, pair.later):
        assert image.shape == (1, 1, 512, 512) and image.dtype == dtype
        assert float(image.min()) == 0.0 and float(image.max()) == 255.0 and torch.equal(image, image.round())
    assert pair.change.dtype == torch.bool and pair.change.shape == (1, 1, 512, 512)
    assert pair.crs == "EPSG:32650" and pair.info["dates"] == {"earlier": "2000-05-03", "later": "2002-07-12"}
    first, second = example_pair(dtype), example_pair(dtype)
    first.earlier.add_(1)  # new tensors on every call
    assert torch.equal(second.earlier, pair.earlier)


def test_the_transform_is_the_envi_headers_map_info():
    # map info = {UTM, 1, 1, 660585, 3551295, 30, 30, 50, North}: pixel (1, 1)'s top-left corner, 30 m cells.
    transform = example_pair().transform
    cells = torch.tensor([[0.0, 0.0], [10.0, 3.0], [511.0, 200.0]], dtype=torch.float64)  # x (column), y (row)
    expected = torch.stack([660585 + 30 * (cells[:, 0] + 0.5), 3551295 - 30 * (cells[:, 1] + 0.5)], -1)
    torch.testing.assert_close(transform.to_world(cells), expected, rtol=0, atol=1e-6)


def test_the_two_dates_are_co_registered_and_a_shift_would_show():
    pair = example_pair(torch.float64)
    earlier, later = pair.earlier[0, 0].numpy(), pair.later[0, 0].numpy()
    for top in (0, 256):
        for left in (0, 256):
            window = np.s_[top : top + 256, left : left + 256]
            shift = phase_cross_correlation(earlier[window], later[window], upsample_factor=20, normalization=None)[0]
            assert np.abs(shift).max() <= 0.1, (top, left, shift)
    moved = phase_cross_correlation(earlier, np.roll(later, 1, axis=1), upsample_factor=20, normalization=None)[0]
    assert moved.tolist() == [0.0, -1.0]  # the control: a one-cell shift along the columns is seen as such


def test_the_change_map_marks_where_the_dates_differ_beyond_one_tone_map():
    pair = example_pair(torch.float64)
    earlier, later = pair.earlier.flatten().numpy(), pair.later.flatten().numpy()
    changed = pair.change.flatten().numpy()
    assert 0.002 < changed.mean() < 0.01
    slope, offset = np.polyfit(earlier, later, 1)
    residual = np.abs(later - (slope * earlier + offset))
    assert residual[changed].mean() > 3 * residual[~changed].mean()


def test_one_grey_level_map_for_both_dates():
    # The 2000 image's 0.5 and 99.5 percentiles go to 0 and 255 over the whole 800 x 800 subset, not over the crop:
    # a few cells of the crop reach each end; the 2002 image, darker in July, goes through the same map.
    pair = example_pair(torch.float64)
    assert 0 < float((pair.earlier == 0).double().mean()) < 0.02
    assert 0 < float((pair.earlier == 255).double().mean()) < 0.02
    assert float(pair.later.mean()) < float(pair.earlier.mean()) - 10


@pytest.mark.skipif(not (RAW / "pair").is_dir(), reason="the raw Landsat files are not on this machine")
def test_the_crop_is_the_pair_prepared_independently_from_the_raw_files():
    pair = example_pair()
    for role, folder in (("earlier", "A"), ("later", "B"), ("change", "label")):
        prepared = np.asarray(Image.open(RAW / "pair" / folder / "nanjing.png"))[:512, :512]
        values = getattr(pair, role)[0, 0].numpy()
        assert np.array_equal(
            values > 0 if role == "change" else values, prepared > 0 if role == "change" else prepared
        )


def test_damaged_package_data_are_named(tmp_path, monkeypatch):
    folder = tmp_path / "nanjing"
    shutil.copytree(data_folder(), folder)
    monkeypatch.setattr(example_module, "data_folder", lambda: folder)
    assert example_pair().earlier.shape == (1, 1, 512, 512)  # the copy reads
    Image.fromarray(np.zeros((100, 512), np.uint8)).save(folder / FILES["later"])
    with pytest.raises(ValueError, match=r"nanjing_2002\.png holds uint8 \(100, 512\), expected uint8 \(512, 512\)"):
        example_pair()
    info = json.loads((folder / SIDECAR).read_text())
    del info["transform"]
    (folder / SIDECAR).write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"lacks \['transform'\]: reinstall enmi_torch"):
        example_pair()
    (folder / SIDECAR).unlink()
    with pytest.raises(ValueError, match="cannot be read"):
        example_pair()


def test_dtype_is_checked():
    with pytest.raises(ValueError, match=r"dtype must be torch\.float32 or torch\.float64, got torch\.int64"):
        example_pair(torch.int64)
