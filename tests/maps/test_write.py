"""write_geotiff: what rasterio reads back (values, transform, CRS, nodata, colours), and a COG with overviews."""

import numpy as np
import pytest
import torch
from _geotiffs import TRANSFORMS, rasterio

from enmi_torch.maps import GeoTransform, MapSource, write_geotiff


def test_what_is_written_is_what_rasterio_reads_back(tmp_path):
    values = torch.rand(30, 50, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    path = write_geotiff(tmp_path / "map.tif", values, TRANSFORMS["rotated"], crs="EPSG:25832", nodata=-1.0)
    with rasterio.open(path) as dataset:
        np.testing.assert_array_equal(dataset.read(1), values.numpy())
        assert dataset.dtypes == ("float64",) and dataset.nodata == -1.0 and dataset.crs.to_epsg() == 25832
        assert tuple(dataset.transform)[:6] == pytest.approx(tuple(TRANSFORMS["rotated"])[:6])
        assert dataset.profile["tiled"] and dataset.profile["compress"] == "deflate"
    rgb = np.random.default_rng(0).integers(0, 256, (3, 20, 20), dtype=np.uint8)
    geo = GeoTransform(2.0, 0.0, 100.0, 0.0, -2.0, 200.0)
    with rasterio.open(write_geotiff(tmp_path / "rgb.tif", rgb, geo)) as dataset:
        assert [colour.name for colour in dataset.colorinterp] == ["red", "green", "blue"] and dataset.crs is None
        np.testing.assert_array_equal(dataset.read(), rgb)
        assert tuple(dataset.transform)[:6] == geo.affine


def test_a_cog_is_tiled_with_overviews_and_reads_as_the_plain_file(tmp_path):
    values = np.random.default_rng(0).integers(0, 1000, (1300, 1100)).astype(np.uint16)
    plain = write_geotiff(tmp_path / "plain.tif", values, TRANSFORMS["north_up"], crs="EPSG:32633")
    cog = write_geotiff(tmp_path / "cog.tif", values, TRANSFORMS["north_up"], crs="EPSG:32633", cog=True)
    with rasterio.open(cog) as dataset:
        assert dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and dataset.overviews(1) == [2, 4]
        assert dataset.block_shapes == [(512, 512)]
    with MapSource.open(plain) as first, MapSource.open(cog) as second:
        assert torch.equal(
            first.window((600, 700), 40, units="cells").image, second.window((600, 700), 40, units="cells").image
        )


def test_bad_images_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"image must be \(H, W\) or \(C, H, W\), got shape \(1, 1, 2, 2\)"):
        write_geotiff(tmp_path / "map.tif", np.zeros((1, 1, 2, 2)), TRANSFORMS["north_up"])
    with pytest.raises(ValueError, match="must be invertible"):
        write_geotiff(tmp_path / "map.tif", np.zeros((2, 2)), (1.0, 0.0, 0.0, 0.0, 0.0, 0.0))
