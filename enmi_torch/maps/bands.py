"""Which band of a multi-band map is read: one band by number, or the luma of a colour image.

The search compares one channel. A map of one band is read as it is; a colour map (red, green and blue bands, with
or without alpha) is read as its luma ``0.299 R + 0.587 G + 0.114 B`` (ITU-R BT.601, Pillow's ``convert("L")``,
so a colour PNG and its grey conversion read alike); any other count of bands needs ``band=`` (numbered from 1,
as GDAL and rasterio number them). Alpha is never a value: it marks cells invalid where it is 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

LUMA_WEIGHTS = (0.299, 0.587, 0.114)


def choose_bands(band: Any, colours: Sequence[str], source: str) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """The bands to read (numbered from 1) and the weights that sum them into the map's one channel.

    Args:
        band: ``None`` (one band, or the luma of red, green and blue) or a band number ``1 <= band <= count``.
        colours: each band's colour interpretation in lower case (``"gray"``, ``"red"``, ``"alpha"``,
            ``"undefined"`` ...), one per band.
        source: the map as named in messages (``"--map 'city.tif'"``).

    Example:
        >>> choose_bands(None, ["red", "green", "blue", "alpha"], "map")
        ((1, 2, 3), (0.299, 0.587, 0.114))
        >>> choose_bands(2, ["undefined", "undefined"], "map")
        ((2,), (1.0,))
    """
    count = len(colours)
    if band is not None:
        if isinstance(band, bool) or not isinstance(band, int) or not 1 <= band <= count:
            raise ValueError(f"band must be a band number from 1 to {count} of {source}, got {band!r}")
        return (band,), (1.0,)
    if count == 1:
        return (1,), (1.0,)
    if count in (3, 4) and list(colours[:3]) == ["red", "green", "blue"]:
        return (1, 2, 3), LUMA_WEIGHTS
    raise ValueError(
        f"{source} has {count} bands ({', '.join(colours)}): choose one with band=1 to {count} (on the command line "
        "--band); only one band or red, green and blue (read as their luma) are read without it"
    )
