"""Maps read whole: ``.npy`` arrays (the budget-checked reader), grey PNGs with their 16 bits, colour images as luma
with alpha as validity, in memory the same windows a slice gives."""

import numpy as np
import pytest
import torch
from PIL import Image

from enmi_torch.maps import MapSource
from enmi_torch.utils.budget import MemoryBudgetError, memory_budget


def _window_of(path, band=None):
    with MapSource.open(path, band=band) as source:
        rows, cols = source.shape
        return source.window((cols // 2, rows // 2), (cols // 2, rows // 2), units="cells", dtype=torch.float64)


def test_a_npy_map_is_read_through_the_budget_checked_reader(tmp_path):
    values = np.random.default_rng(0).normal(size=(7, 11))
    np.save(tmp_path / "map.npy", values)
    window = _window_of(tmp_path / "map.npy")
    np.testing.assert_array_equal(window.image[0, 0, :7, :11].numpy(), values)
    with MapSource.open(tmp_path / "map.npy") as source:
        assert source.transform is None and source.crs is None and source.shape == (7, 11)
    with memory_budget(100), pytest.raises(MemoryBudgetError, match=r"--map '.*map\.npy' needs about 616 bytes"):
        MapSource.open(tmp_path / "map.npy", source="--map")
    with pytest.raises(ValueError, match="band is for multi-band images and GeoTIFFs"):
        MapSource.open(tmp_path / "map.npy", band=1)
    with pytest.raises(FileNotFoundError, match=r"--map '.*none\.npy': no such file"):
        MapSource.open(tmp_path / "none.npy", source="--map")


def test_a_grey_png_keeps_16_bits_and_a_colour_one_reads_as_its_luma_with_alpha_as_validity(tmp_path):
    deep = (np.arange(6 * 9, dtype=np.uint16).reshape(6, 9) * 1000).astype(np.uint16)
    Image.fromarray(deep).save(tmp_path / "deep.png")
    np.testing.assert_array_equal(_window_of(tmp_path / "deep.png").image[0, 0, :6, :9].numpy(), deep)
    rgba = np.random.default_rng(1).integers(0, 256, (6, 9, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    rgba[2, 3, 3] = 0
    Image.fromarray(rgba, "RGBA").save(tmp_path / "colour.png")
    window = _window_of(tmp_path / "colour.png")
    grey = np.asarray(Image.fromarray(rgba[..., :3]).convert("L"), dtype=np.float64)
    valid = window.valid_mask[0, 0, :6, :9].numpy()
    assert valid.sum() == 6 * 9 - 1 and not valid[2, 3]
    assert np.abs(window.image[0, 0, :6, :9].numpy() - grey)[valid].max() <= 0.5 + 1e-9  # Pillow rounds
    blue = _window_of(tmp_path / "colour.png", band=3).image[0, 0, :6, :9].numpy()  # alpha still marks validity
    np.testing.assert_array_equal(blue, np.where(valid, rgba[..., 2], 0))
    Image.fromarray(rgba[..., 0]).save(tmp_path / "grey.jpg", quality=100)
    jpeg = _window_of(tmp_path / "grey.jpg").image[0, 0, :6, :9].numpy()
    np.testing.assert_array_equal(jpeg, np.asarray(Image.open(tmp_path / "grey.jpg"), dtype=np.float64))
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(ValueError, match=r"--map '.*broken\.png' is not a readable image"):
        MapSource.open(tmp_path / "broken.png", source="--map")
