"""Real maps: windows of a GeoTIFF, COG, ``.npy`` or PNG map around a prior pose, and world coordinates.

A prior map is usually a georeferenced raster (an orthophoto, a rasterized lidar intensity map), often far larger
than memory, with a coordinate reference system (UTM metres, say). :class:`MapSource` opens one and cuts
:class:`MapWindow` s around a point given in the map's CRS: only the window is read (rasterio's windowed reads, the
``geo`` extra: ``pip install "enmi_torch[geo]"``), and the window carries its :class:`GeoTransform`, so the search
works on a tensor in cells and never sees a file or a CRS; poses are converted at the edges (``to_world``,
``to_cells``).

Data flow, each module importing only the ones before it: :mod:`~enmi_torch.maps.transform` (cells to world, poses
and yaws) → :mod:`~enmi_torch.maps.bands` (which band) → :mod:`~enmi_torch.maps.arrays` (maps in memory) and
:mod:`~enmi_torch.maps.geotiff` (rasterio, by windows) → :mod:`~enmi_torch.maps.source` (:class:`MapSource`,
:class:`MapWindow`); :mod:`~enmi_torch.maps.write` writes a GeoTIFF or COG. ``import enmi_torch`` never imports
rasterio.

Convention:
    Poses in cells are the library's ``(x, y, yaw)``: ``x`` the map column, ``y`` the row (down), whole numbers at
    cell centres, yaw in degrees counter-clockwise as displayed. World poses are ``(X, Y, yaw)`` in the map's CRS with
    the yaw the heading of the captured image's top, clockwise from north (``+Y``): equal to the cell yaw on a
    north-up map; see :class:`GeoTransform` for flipped and rotated maps.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> from enmi_torch import localize
    >>> from enmi_torch.maps import MapSource, write_geotiff
    >>> photo = torch.rand(300, 400, generator=torch.Generator().manual_seed(0)) * 256  # a texture, 300 x 400 cells
    >>> corner = (0.5, 0.0, 500000.0, 0.0, -0.5, 5400000.0)  # 0.5 m cells, north up, top-left corner in UTM 33N
    >>> path = write_geotiff(Path(tempfile.mkdtemp()) / "map.tif", photo, corner, crs="EPSG:32633")
    >>> captured = photo[120:152, 200:248][None, None]  # its centre pixel (16, 24) lies on map cell (224, 136)
    >>> with MapSource.open(path) as source:
    ...     window = source.window(around=(500110.0, 5399931.0), radius=(20.0, 16.0))  # prior 2 m off; metres
    ...     print(source.to_world((224, 136)).tolist())  # the truth, in metres
    [500112.25, 5399931.75]
    >>> found = localize(captured, window.image, 64.0, shifts=10, around=window.center,
    ...                  reference_mask=window.valid_mask)  # the search sees a tensor in cells
    >>> window.to_world(found.pose[0]).round(decimals=2).tolist()  # window cells (x, y, yaw) to metres and heading
    [500112.25, 5399931.75, 0.0]
"""

from enmi_torch.maps.source import MapSource, MapWindow
from enmi_torch.maps.transform import GeoTransform
from enmi_torch.maps.write import write_geotiff

__all__ = ["GeoTransform", "MapSource", "MapWindow", "write_geotiff"]
