"""make_geotiff_map: a GeoTIFF of a photograph with the transform asked for, and a crop that enmi-localize finds where
the command says it lies."""

import re

import numpy as np
import pytest
from _geotiffs import rasterio
from skimage import data

from data_tools.make_geotiff_map import main
from enmi_torch.cli.localize import _command


@pytest.mark.parametrize(("photo", "rotation"), [("skimage:camera", 0.0), ("skimage:astronaut", 30.0)])
def test_the_crop_is_localized_where_the_command_says_it_lies(tmp_path, capsys, photo, rotation):
    arguments = [photo, str(tmp_path / "maps" / "map.tif"), "--origin", "500000", "5400000", "--pixel-size", "0.5"]
    arguments += ["--rotation", str(rotation), "--crop-world", "500120", "5399890", "--crop", str(tmp_path / "l.npy")]
    main(arguments)
    printed = capsys.readouterr().out
    truth = [float(value) for value in re.search(r"lies on world \(([-\d.]+), ([-\d.]+)\)", printed).groups()]
    image = getattr(data, photo.partition(":")[2])()
    with rasterio.open(tmp_path / "maps" / "map.tif") as dataset:
        assert dataset.count == (1 if image.ndim == 2 else 3) and dataset.crs.to_string() == "EPSG:32633"
        angle = np.radians(rotation)
        expected = (
            0.5 * np.cos(angle),
            0.5 * np.sin(angle),
            500000,
            0.5 * np.sin(angle),
            -0.5 * np.cos(angle),
            5400000,
        )
        assert tuple(dataset.transform)[:6] == pytest.approx(expected)
        assert np.array_equal(dataset.read(1), image if image.ndim == 2 else image[..., 0])
    assert abs(truth[0] - 500120) <= 0.5 and abs(truth[1] - 5399890) <= 0.5  # the cell centre nearest
    assert np.load(tmp_path / "l.npy").shape == (64, 80)
    prior = [str(truth[0] + 3.0), str(truth[1] - 2.0)]
    report = _command(
        [
            "--map",
            str(tmp_path / "maps" / "map.tif"),
            "--local",
            str(tmp_path / "l.npy"),
            "--variance",
            "100",
            "--prior-world",
            *prior,
            "--shifts",
            "12",
        ]
    )
    capsys.readouterr()
    assert abs(report["world_x"] - truth[0]) < 0.1 and abs(report["world_y"] - truth[1]) < 0.1, (report, truth)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["skimage:nothing"], "scikit-image has no bundled image 'nothing'"),
        (["skimage:camera", "--pixel-size", "0"], "--pixel-size must be a finite number > 0"),
        (["skimage:camera", "--crop", "c.npy"], "--crop FILE and --crop-world X Y go together"),
        (["skimage:camera", "--crop-world", "500001", "5399999", "--crop", "c.npy"], "partly off the map"),
    ],
)
def test_mistakes_end_in_one_line(tmp_path, capsys, arguments, message):
    base = [str(tmp_path / "map.tif"), "--origin", "500000", "5400000"]
    base += [] if "--pixel-size" in arguments else ["--pixel-size", "0.5"]
    with pytest.raises(SystemExit) as exit_info:
        main([arguments[0], *base, *arguments[1:]])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and message in error, error
