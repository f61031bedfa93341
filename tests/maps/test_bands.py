"""Which band a map reads: one band as it is, red, green and blue as their luma, anything else by number only."""

import pytest

from enmi_torch.maps.bands import LUMA_WEIGHTS, choose_bands


@pytest.mark.parametrize(
    ("band", "colours", "expected"),
    [
        (None, ["gray"], ((1,), (1.0,))),
        (None, ["undefined"], ((1,), (1.0,))),
        (None, ["red", "green", "blue"], ((1, 2, 3), LUMA_WEIGHTS)),
        (None, ["red", "green", "blue", "alpha"], ((1, 2, 3), LUMA_WEIGHTS)),
        (3, ["red", "green", "blue"], ((3,), (1.0,))),
        (2, ["gray", "undefined", "undefined", "undefined", "undefined"], ((2,), (1.0,))),
    ],
)
def test_the_bands_read_and_their_weights(band, colours, expected):
    assert choose_bands(band, colours, "map") == expected


def test_the_luma_is_itu_r_bt_601_as_pillow_takes_it():
    from PIL import Image

    pixels = {(255, 0, 0): 76, (0, 255, 0): 150, (0, 0, 255): 29, (10, 200, 90): 131}
    for colour, grey in pixels.items():
        assert Image.new("RGB", (1, 1), colour).convert("L").getpixel((0, 0)) == grey
        assert abs(sum(weight * value for weight, value in zip(LUMA_WEIGHTS, colour, strict=True)) - grey) <= 0.5


@pytest.mark.parametrize(
    ("band", "colours", "message"),
    [
        (None, ["gray", "alpha"], r"has 2 bands \(gray, alpha\): choose one with band=1 to 2"),
        (None, ["blue", "green", "red"], "choose one with band=1 to 3"),
        (None, ["red", "green", "blue", "nir", "swir"], "has 5 bands"),
        (0, ["gray"], "band must be a band number from 1 to 1 of map, got 0"),
        (2, ["gray"], "from 1 to 1"),
        (True, ["gray", "gray"], "got True"),
        ("1", ["gray"], "got '1'"),
    ],
)
def test_an_ambiguous_or_missing_band_is_refused_naming_the_choice(band, colours, message):
    with pytest.raises(ValueError, match=message):
        choose_bands(band, colours, "map")
