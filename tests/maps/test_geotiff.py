"""GeoTIFF maps through rasterio: nodata and masks, bands, windowed reads of a map larger than the memory budget, a
COG read as the plain GeoTIFF is, and rasterio imported only when a GeoTIFF is opened."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from _geotiffs import TRANSFORMS, DatasetReader, Window, rasterio, texture, write_raster
from PIL import Image

from enmi_torch import localize
from enmi_torch.maps import MapSource
from enmi_torch.utils.budget import DEFAULT_MEMORY_BUDGET, MemoryBudgetError, memory_budget

ROOT = Path(__file__).resolve().parents[2]


def test_nodata_nan_and_an_internal_mask_are_invalid_cells_and_read_as_zero(tmp_path):
    values = texture(40, 50).astype(np.float32)
    values[5:9, 10:20] = -9999.0
    values[30, 7] = np.nan
    path = write_raster(tmp_path / "map.tif", values, TRANSFORMS["north_up"], nodata=-9999.0)
    with MapSource.open(path) as source:
        window = source.window((25, 20), (25, 20), units="cells")
    expected = np.ones(values.shape, dtype=bool)
    expected[5:9, 10:20] = False
    expected[30, 7] = False
    mask = window.valid_mask[0, 0, :40, :50].numpy()
    np.testing.assert_array_equal(mask, expected)
    np.testing.assert_array_equal(window.image[0, 0, :40, :50].numpy(), np.where(expected, values, 0))
    assert not window.valid_mask[0, 0, 40:].any() and not window.valid_mask[0, 0, :, 50:].any()  # off the map
    integers = np.full((30, 30), 7, dtype=np.uint16)
    integers[:, :4] = 0
    masked = write_raster(tmp_path / "uint16.tif", integers, TRANSFORMS["flipped"], nodata=0)
    with MapSource.open(masked) as source:
        window = source.window((15, 15), 15, units="cells")
    assert window.valid_mask[0, 0, :30, :30].sum() == 30 * 26 and window.image[0, 0, 0, 5] == 7.0


def test_a_colour_map_is_read_as_its_luma_with_alpha_as_validity_and_other_bands_need_band(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (3, 24, 36), dtype=np.uint8)
    alpha = np.full((1, 24, 36), 255, dtype=np.uint8)
    alpha[0, :, :6] = 0
    path = write_raster(
        tmp_path / "rgba.tif", np.concatenate([rgb, alpha]), TRANSFORMS["north_up"], photometric="RGB", alpha="YES"
    )
    grey = np.asarray(Image.fromarray(np.moveaxis(rgb, 0, -1)).convert("L"), dtype=np.float64)  # Pillow's luma
    with MapSource.open(path) as source:
        window = source.window((18, 12), (18, 12), units="cells", dtype=torch.float64)
        assert np.abs(window.image[0, 0, :24, 6:36].numpy() - grey[:, 6:]).max() <= 0.5 + 1e-9  # Pillow rounds
        assert window.valid_mask[0, 0, :24].sum(0).tolist() == [0] * 6 + [24] * 30 + [0]
    with MapSource.open(path, band=2) as source:  # one band by number, alpha still marks validity
        window = source.window((18, 12), (18, 12), units="cells")
        np.testing.assert_array_equal(window.image[0, 0, :24, 6:36].numpy(), rgb[1, :, 6:])
    two = write_raster(tmp_path / "two.tif", rgb[:2], TRANSFORMS["north_up"])
    with pytest.raises(ValueError, match=r"has 2 bands \(gray, undefined\): choose one with band=1 to 2"):
        MapSource.open(two, source="--map")
    with pytest.raises(ValueError, match="band must be a band number from 1 to 2"):
        MapSource.open(two, band=3)
    with MapSource.open(two, band=2) as source:
        np.testing.assert_array_equal(
            source.window((18, 12), (18, 12), units="cells").image[0, 0, :24, :36].numpy(), rgb[1]
        )


def test_scale_and_offset_are_applied_and_a_plain_tiff_is_not_georeferenced(tmp_path):
    packed = np.arange(12, dtype=np.int16).reshape(3, 4)
    path = write_raster(tmp_path / "packed.tif", packed, TRANSFORMS["north_up"])
    with rasterio.open(path, "r+") as dataset:
        dataset.scales, dataset.offsets = (0.5,), (10.0,)
    with MapSource.open(path) as source:
        window = source.window((2, 1), (2, 1), units="cells", dtype=torch.float64)
    np.testing.assert_array_equal(window.image[0, 0, :, :4].numpy(), packed * 0.5 + 10.0)
    plain = tmp_path / "plain.tif"
    Image.fromarray(packed.astype(np.uint8)).save(plain)
    with MapSource.open(plain) as source:
        assert source.transform is None and source.crs is None
        assert source.window((1, 1), 1, units="cells").image[0, 0].tolist() == [[0, 1, 2], [4, 5, 6], [8, 9, 10]]
        with pytest.raises(ValueError, match="world coordinates need a georeferenced map"):
            source.to_cells((0.0, 0.0))


def test_missing_and_foreign_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"--map '.*nothing\.tif': no such file"):
        MapSource.open(tmp_path / "nothing.tif", source="--map")
    (tmp_path / "text.tif").write_text("not a raster")
    with pytest.raises(ValueError, match=r"--map '.*text\.tif' cannot be read as a raster"):
        MapSource.open(tmp_path / "text.tif", source="--map")


def _record_reads(monkeypatch) -> list[tuple[str, int, int]]:
    """Every read of a raster's cells or masks, as (kind, rows, columns): the library's reads are windowed."""
    reads = []
    for name in ("read", "read_masks"):
        original = getattr(DatasetReader, name)

        def recorded(self, *args, _original=original, _name=name, **kwargs):
            window = kwargs.get("window")
            assert window is not None, f"{_name} without a window reads the whole map"
            reads.append((_name, int(window.height), int(window.width)))
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(DatasetReader, name, recorded)
    return reads


def test_a_map_larger_than_the_memory_budget_is_read_by_windows_and_never_whole(tmp_path, monkeypatch):
    side = 40_000  # 1.6e9 cells: 6.4 GB as float32, more than the default budget of 4 GiB
    assert side * side * 4 > DEFAULT_MEMORY_BUDGET
    patch = texture(512, 512).astype(np.float32) + 1.0  # 0 is nodata: the unwritten tiles read as nodata
    path = tmp_path / "big.tif"
    profile = {"driver": "GTiff", "width": side, "height": side, "count": 1, "dtype": "float32", "nodata": 0.0}
    profile |= {"crs": "EPSG:32633", "transform": TRANSFORMS["north_up"], "tiled": True, "compress": "deflate"}
    with rasterio.open(path, "w", sparse_ok=True, **profile) as dataset:  # tiles never written take no disk
        dataset.write(patch, 1, window=Window(20_000, 30_000, 512, 512))
    assert path.stat().st_size < 2 << 20  # under 2 MiB on disk
    reads = _record_reads(monkeypatch)
    with memory_budget(DEFAULT_MEMORY_BUDGET), MapSource.open(path) as source:
        assert source.shape == (side, side)
        world = source.to_world((20_310, 30_210)).tolist()
        window = source.window(around=world, radius=(30.0, 20.0))  # 60 x 40 cells of 0.5 m each way
        assert window.image.shape == (1, 1, 81, 121) and window.offset == (20_250, 30_170)
        np.testing.assert_array_equal(window.image[0, 0].numpy(), patch[170:251, 250:371])
        assert reads and all(rows <= 81 and cols <= 121 for _, rows, cols in reads)
        edge = source.window((20_000, 30_000), 8, units="cells")  # the patch's corner: the rest is nodata
        assert edge.valid_mask[0, 0].sum() == 9 * 9 and bool(edge.valid_mask[0, 0, 8:, 8:].all())
        count = len(reads)
        with pytest.raises(MemoryBudgetError, match=r"radius=12000\.0 needs about .* for the 48001 x 48001 window"):
            source.window(around=world, radius=12_000.0)  # the whole map and more: refused before reading
        with pytest.raises(MemoryBudgetError):
            source.window((side // 2, side // 2), side // 2, units="cells")
        assert len(reads) == count
    captured = torch.from_numpy(patch[200:232, 300:340])[None, None]  # centre pixel on cell (20_320, 30_216)
    found = localize(captured, window.image, 16.0, shifts=12, around=window.center)
    assert window.to_map_cells(found.pose[0].tolist()).tolist() == pytest.approx([20_320.0, 30_216.0, 0.0], abs=0.05)


def test_a_cog_with_overviews_reads_and_localizes_as_the_plain_geotiff(tmp_path):
    values = texture().astype(np.float32)
    plain = write_raster(tmp_path / "plain.tif", values, TRANSFORMS["rotated"])
    cog = write_raster(tmp_path / "cog.tif", values, TRANSFORMS["rotated"], driver="COG")
    with rasterio.open(cog) as dataset:
        assert dataset.overviews(1) and dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
    captured = torch.from_numpy(values[50:82, 150:190])[None, None]
    results = []
    for path in (plain, cog):
        with MapSource.open(path) as source:
            window = source.window(source.to_world((168, 68)).tolist(), radius=(16.0, 14.0))
        found = localize(captured, window.image, 16.0, shifts=8, around=window.center)
        results.append((window, found))
    (plain_window, plain_found), (cog_window, cog_found) = results
    assert torch.equal(plain_window.image, cog_window.image) and plain_window.transform == cog_window.transform
    assert torch.equal(plain_found.pose, cog_found.pose)
    cell = plain_found.pose[0, :2].tolist()
    assert plain_window.to_map_cells(cell).tolist() == pytest.approx([170.0, 66.0], abs=0.05)


def _run(script: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_the_core_and_the_maps_package_never_import_rasterio_until_a_geotiff_is_opened(tmp_path):
    path = write_raster(tmp_path / "map.tif", texture(20, 30).astype(np.float32), TRANSFORMS["north_up"])
    script = (
        "import sys, numpy as np, torch\n"
        "import enmi_torch, enmi_torch.maps, enmi_torch.cli.localize\n"
        "from enmi_torch.maps import MapSource\n"
        "enmi_torch.localize, enmi_torch.ECR\n"
        f"np.save({str(tmp_path / 'map.npy')!r}, np.ones((8, 9)))\n"
        f"MapSource.open({str(tmp_path / 'map.npy')!r}).window((4, 4), 2, units='cells')\n"
        "MapSource.from_array(torch.ones(5, 5), transform=(1, 0, 0, 0, -1, 5)).window((2.5, 2.5), 1.0)\n"
        "print('rasterio' in sys.modules)\n"
        f"MapSource.open({str(path)!r})\n"
        "print('rasterio' in sys.modules)\n"
    )
    completed = _run(script)
    assert completed.stdout.split() == ["False", "True"], completed.stderr


def test_without_rasterio_a_geotiff_is_refused_in_one_line_naming_the_extra(tmp_path):
    path = write_raster(tmp_path / "map.tif", texture(20, 30).astype(np.float32), TRANSFORMS["north_up"])
    script = (
        "import sys\n"
        "sys.modules['rasterio'] = None\n"
        "from enmi_torch.maps import MapSource\n"
        "try:\n"
        f"    MapSource.open({str(path)!r}, source='--map')\n"
        "except ModuleNotFoundError as error:\n"
        "    print(error.name, '|', error)\n"
    )
    completed = _run(script)
    assert completed.stdout.strip() == (
        f"rasterio | --map '{path}': reading a GeoTIFF needs rasterio: pip install \"enmi_torch[geo]\""
    ), completed.stderr
