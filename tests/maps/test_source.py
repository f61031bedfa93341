"""MapSource windows: a crop at a known world position is localized back there on north-up, flipped and rotated
GeoTIFFs; a window holds what rasterio reads there; the window's size follows its radius in world units or cells."""

import math

import numpy as np
import pytest
import torch
from _geotiffs import CELL, TRANSFORMS, WORLD_YAW, Window, rasterio, texture, write_raster, xy

from enmi_torch import localize
from enmi_torch.maps import MapSource
from enmi_torch.registration import warp_reference

# The captured image's centre pixel lies on map cell x = 170 (column), y = 64 (row): a swapped axis lands elsewhere.
TRUTH = (170, 64)
SIZE = (32, 40)  # (h, w): not square either


def _crop(prior_map: np.ndarray, yaw: float, dtype: torch.dtype) -> torch.Tensor:
    """The captured image of pose (170, 64, yaw) in cells, with a little noise."""
    reference = torch.from_numpy(prior_map)[None, None].to(dtype)
    pose = torch.tensor([[*TRUTH, yaw]], dtype=dtype)
    captured = warp_reference(reference, pose, SIZE)[0]
    return captured + 4 * torch.randn(captured.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)


@pytest.mark.parametrize("name", list(TRANSFORMS))
@pytest.mark.parametrize("yaw", [0.0, 8.0])
def test_a_crop_at_a_known_world_position_is_localized_back_to_it(tmp_path, name, yaw, dtype):
    prior_map = texture()
    affine = TRANSFORMS[name]
    path = write_raster(tmp_path / f"{name}.tif", prior_map.astype(np.float32), affine)
    truth = xy(affine, TRUTH[1], TRUTH[0], offset="center")  # rasterio's centre of row 64, column 170
    prior = (truth[0] + 2.0, truth[1] - 1.5)  # metres east and north of the truth: a few cells on any map
    captured = _crop(prior_map, yaw, dtype)
    with MapSource.open(path) as source:
        window = source.window(around=prior, radius=(15.0, 15.0), dtype=dtype)
    assert window.image.dtype == dtype and window.crs == "EPSG:32633"
    found = localize(
        captured,
        window.image,
        16.0,
        shifts=9,
        around=window.center,
        yaws=[0.0, 4.0, 8.0, 12.0],
        reference_mask=window.valid_mask,
    )
    pose = found.pose[0].tolist()  # (x, y, yaw) in the window's cells
    world = window.to_world(pose).tolist()
    assert math.dist(world[:2], truth) < 0.2 * CELL, (world, truth)
    assert world[2] == pytest.approx(WORLD_YAW[name](yaw), abs=0.5)
    assert window.to_map_cells(pose)[:2].tolist() == pytest.approx(TRUTH, abs=0.2)


def test_a_window_holds_the_cells_and_the_transform_rasterio_reads_there_on_and_off_the_map(tmp_path):
    values = texture().astype(np.float32)
    affine = TRANSFORMS["rotated"]
    path = write_raster(tmp_path / "map.tif", values, affine)
    padded = np.pad(values, 20)  # cells off the map: 0 and invalid
    inside = np.pad(np.ones(values.shape, dtype=bool), 20)
    with MapSource.open(path) as source, rasterio.open(path) as dataset:
        assert source.shape == (200, 260) and source.transform.affine == pytest.approx(tuple(affine)[:6])
        for around, radius in (((100, 50), (7, 4)), ((3, 198), (6, 5)), ((258, 1), (3, 9))):
            window = source.window(around, radius, units="cells")
            x0, y0 = around[0] - radius[0], around[1] - radius[1]
            assert window.offset == (x0, y0) and window.center == radius
            rows, cols = slice(y0 + 20, y0 + 20 + 2 * radius[1] + 1), slice(x0 + 20, x0 + 20 + 2 * radius[0] + 1)
            np.testing.assert_array_equal(window.image[0, 0].numpy(), padded[rows, cols])
            np.testing.assert_array_equal(window.valid_mask[0, 0].numpy(), inside[rows, cols])
            box = Window(x0, y0, 2 * radius[0] + 1, 2 * radius[1] + 1)
            assert window.transform.affine == pytest.approx(tuple(dataset.window_transform(box))[:6])
        window = source.window((100, 50), (7, 4), units="cells")
        np.testing.assert_array_equal(window.image[0, 0].numpy(), dataset.read(1, window=Window(93, 46, 15, 9)))


def test_a_world_radius_covers_its_box_in_cells_and_a_cell_radius_is_whole_cells(tmp_path):
    path = write_raster(tmp_path / "map.tif", texture().astype(np.float32), TRANSFORMS["north_up"])
    with MapSource.open(path) as source:
        centre = source.to_world((100, 60)).tolist()
        window = source.window(around=centre, radius=(5.0, 2.0))  # 10 and 4 cells of 0.5 m
        assert window.image.shape == (1, 1, 9, 21) and window.offset == (90, 56)
        off_centre = source.window(around=(centre[0] + 0.2, centre[1]), radius=(5.0, 2.0))  # 0.4 cell east
        assert off_centre.image.shape == (1, 1, 9, 23) and off_centre.center == (11, 4)  # rounded out, both sides
        assert source.window((100.4, 59.6), (10, 4), units="cells").offset == (90, 56)  # the nearest cell
    rotated = write_raster(tmp_path / "rotated.tif", texture().astype(np.float32), TRANSFORMS["rotated"])
    with MapSource.open(rotated) as source:
        window = source.window(around=source.to_world((100, 60)).tolist(), radius=(5.0, 2.0))
        # The world box turned 30 degrees into cells: 10 cos 30 + 4 sin 30 = 10.66 columns, 5 + 3.46 rows.
        assert window.image.shape == (1, 1, 2 * 9 + 1, 2 * 11 + 1)


def test_a_window_off_the_map_and_bad_arguments_are_refused_by_name(tmp_path):
    source = MapSource.from_array(torch.rand(20, 30))
    with pytest.raises(ValueError, match=r"lies off the 20 x 30 map .* columns 40\.\.50"):
        source.window((45, 10), 5, units="cells")
    with pytest.raises(ValueError, match="world coordinates need a georeferenced map"):
        source.window((5.0, 5.0), 2.0)
    with pytest.raises(ValueError, match="units='cells'"):
        source.to_world((1.0, 2.0))
    cases = [
        ({"around": (1, 2), "radius": -1, "units": "cells"}, ValueError, r"radius must be an int >= 0 \(cells\)"),
        ({"around": (1, 2), "radius": 1.5, "units": "cells"}, ValueError, "radius must be an int >= 0"),
        ({"around": (1,), "radius": 1, "units": "cells"}, ValueError, r"around must be \(x, y\)"),
        ({"around": (1, math.nan), "radius": 1, "units": "cells"}, ValueError, "around must be"),
        ({"around": (1, 2), "radius": 1, "units": "pixels"}, ValueError, r"units must be one of \['world', 'cells'\]"),
        ({"around": (1, 2), "radius": 1, "units": "cells", "dtype": torch.int64}, TypeError, "dtype must be a float"),
    ]
    for arguments, error, message in cases:
        with pytest.raises(error, match=message):
            source.window(**arguments)
    geo = MapSource.from_array(torch.rand(20, 30), transform=(1.0, 0.0, 0.0, 0.0, -1.0, 20.0))
    with pytest.raises(ValueError, match=r"radius must be a finite number >= 0 \(world units\)"):
        geo.window((5.0, 5.0), math.inf)


def test_an_array_source_cuts_the_windows_a_slice_gives_and_keeps_its_mask_and_transform():
    image = torch.arange(30 * 20, dtype=torch.float64).reshape(20, 30)
    image[3, 4] = math.nan
    valid = torch.ones(20, 30, dtype=torch.bool)
    valid[5, 6] = False
    source = MapSource.from_array(
        image[None, None], transform=TRANSFORMS["flipped"], crs="EPSG:32633", valid_mask=valid
    )
    window = source.window((6, 4), (3, 2), units="cells", dtype=torch.float64)
    expected = image[2:7, 3:10].clone()
    mask = torch.isfinite(expected) & valid[2:7, 3:10]
    assert torch.equal(window.valid_mask[0, 0], mask) and not mask[1, 1] and not mask[3, 3]
    assert torch.equal(window.image[0, 0], torch.where(mask, expected, 0.0))
    assert window.to_world((3.0, 2.0)).tolist() == pytest.approx(source.to_world((6.0, 4.0)).tolist(), abs=1e-9)
    assert repr(source) == "MapSource(image, 20 x 30 cells, crs='EPSG:32633')"
    with pytest.raises(ValueError, match=r"valid_mask must be a bool map of shape \(20, 30\)"):
        MapSource.from_array(image, valid_mask=valid[:10])
    with pytest.raises(ValueError, match=r"image must be a \(H, W\) or \(1, 1, H, W\) map"):
        MapSource.from_array(image[None])
    with pytest.raises(TypeError, match="crs must be a string"):
        MapSource.from_array(image, crs=32633)
