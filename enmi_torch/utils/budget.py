"""The memory budget: a call estimates what it will allocate and refuses, before allocating, what exceeds the budget.

Some sizes follow from arguments, not from the inputs: a joint histogram holds ``bins^2`` cells per sample whatever
the image size (``bins=100000`` is 37 GiB for one 16 x 16 image), and a search of radius ``shifts`` correlates
bin planes as large as its window (``shifts=10000``: 20,000 x 20,000 cells per plane). Such calls estimate the
bytes of their largest tensors (joint histograms, bin-weight planes, FFT spectra, surfaces, search windows, arrays
read from files) from the shapes alone and raise :class:`MemoryBudgetError` when the estimate exceeds the budget, at
once, instead of failing in the allocator minutes later or swapping the machine. The estimate counts the largest
tensors, not every temporary; treat it as an order of magnitude.

The budget holds on every device. It is 4 GiB unless ``ENMI_TORCH_MEMORY_BUDGET`` (bytes, e.g. ``16e9``, or
``none``) says otherwise at import; change it with :func:`set_memory_budget` or, for a block of code,
:func:`memory_budget`. ``None`` turns the check off.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from typing import Any

DEFAULT_MEMORY_BUDGET = 4 << 30
_ENVIRONMENT = "ENMI_TORCH_MEMORY_BUDGET"
_RAISE_IT = (
    "or raise the budget with enmi_torch.utils.budget.set_memory_budget(bytes), "
    "`with enmi_torch.utils.budget.memory_budget(bytes):` or "
    f"{_ENVIRONMENT}=bytes (None or 'none' turns the check off)"
)


class MemoryBudgetError(ValueError):
    """A call would allocate more than the memory budget (see :func:`set_memory_budget`); nothing was allocated."""


def _check_budget(name: str, budget: Any) -> int | None:
    if budget is None:
        return None
    if isinstance(budget, bool) or not isinstance(budget, (int, float)) or not math.isfinite(budget) or budget <= 0:
        raise ValueError(f"{name} must be a number of bytes > 0 or None, got {budget!r}")
    return int(budget)


def _budget_from_environment() -> int | None:
    text = os.environ.get(_ENVIRONMENT)
    if text is None:
        return DEFAULT_MEMORY_BUDGET
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{_ENVIRONMENT} must be a number of bytes > 0 or 'none', got {text!r}") from None
    return _check_budget(_ENVIRONMENT, value)


_BUDGET = _budget_from_environment()


def get_memory_budget() -> int | None:
    """The memory budget in bytes (``None``: no check).

    Example:
        >>> from enmi_torch.utils.budget import get_memory_budget, memory_budget
        >>> with memory_budget(2**30):
        ...     get_memory_budget()
        1073741824
    """
    return _BUDGET


def set_memory_budget(budget: int | float | None) -> int | None:
    """Set the memory budget of every later call, in bytes (``None`` turns the check off); returns the previous one.

    Example:
        >>> from enmi_torch.utils.budget import get_memory_budget, set_memory_budget
        >>> previous = set_memory_budget(16 * 2**30)
        >>> get_memory_budget() == 16 * 2**30
        True
        >>> _ = set_memory_budget(previous)
    """
    global _BUDGET
    previous = _BUDGET
    _BUDGET = _check_budget("budget", budget)
    return previous


@contextlib.contextmanager
def memory_budget(budget: int | float | None) -> Iterator[None]:
    """Use ``budget`` bytes (``None``: no check) as the memory budget within a ``with`` block.

    Example:
        >>> from enmi_torch.functional import joint_histogram
        >>> from enmi_torch.utils.budget import MemoryBudgetError, memory_budget
        >>> image = torch.rand(1, 1, 4, 4)
        >>> try:
        ...     with memory_budget(1000):
        ...         joint_histogram(image, image, bins=100, value_range=(0, 1))
        ... except MemoryBudgetError as error:
        ...     print(str(error)[:60])
        bins=100 needs about 39.1 KiB for the joint histograms (1, 1
    """
    previous = set_memory_budget(budget)
    try:
        yield
    finally:
        set_memory_budget(previous)


def format_bytes(count: int | float) -> str:
    """``count`` bytes in binary units, e.g. ``"37.3 GiB"``."""
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if count < 1024 or unit == "TiB":
            return f"{count:.0f} {unit}" if unit == "bytes" else f"{count:.1f} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def within_budget(needed: int) -> bool:
    """Whether ``needed`` bytes fit the memory budget."""
    return _BUDGET is None or needed <= _BUDGET


def budget_error(needed: int, cause: str, what: str, remedy: str) -> MemoryBudgetError:
    """The error for ``needed`` bytes over the budget; ``cause`` names the arguments as passed (``"bins=100000"``).

    The message reads ``"{cause} needs about N GiB for {what}, over the memory budget of M GiB: {remedy}, or raise
    the budget ..."``. Build it only once :func:`within_budget` said no: the check itself stays a comparison.
    """
    return MemoryBudgetError(
        f"{cause} needs about {format_bytes(needed)} for {what}, over the memory budget of {format_bytes(_BUDGET)}: "
        f"{remedy}, {_RAISE_IT}"
    )


def joint_histogram_bytes(
    candidates: int,
    batch: int,
    pixels: int,
    bins: int,
    itemsize: int,
    *,
    captured_planes: bool,
    reference_planes: bool,
    histogram_copies: int = 1,
) -> int:
    """Bytes of ``(C, B, bins, bins)`` joint histograms and of the dense ``(B, N, bins)`` bin weights behind them.

    ``captured_planes``: the captured weights are held whole (Parzen kernels, or a soft reference); the likelihood
    kernels stream them in chunks of a few MiB. ``reference_planes``: ``(C, B, N, bins)`` weights are held too (a
    soft reference, or Parzen captured weights repeated for several candidates). ``histogram_copies``: tensors of
    the histograms' size held at once (4 while NMI's entropies are taken).
    """
    cells = histogram_copies * candidates * batch * bins * bins
    weights = batch * pixels * bins * (int(captured_planes) + candidates * int(reference_planes))
    return (cells + weights) * itemsize


def surface_bytes(
    batch: int,
    local_shape: tuple[int, int],
    window_shape: tuple[int, int],
    local_planes: int,
    window_planes: int,
    weight_bins: int,
    itemsize: int,
) -> int:
    """Bytes of an FFT score surface of ``batch`` local images in a window (:mod:`enmi_torch.placement`).

    The window's ``window_planes`` planes are held real and as spectra (about four reals per window cell each), one
    local image's ``local_planes`` spectra at a time (two), a block of counts per window plane at every placement, and
    the ``(B, h, w, weight_bins)`` bin weights of the local images (three: weights, masked, one-hot indices).
    """
    window = window_shape[0] * window_shape[1]
    placements = (window_shape[0] - local_shape[0] + 1) * (window_shape[1] - local_shape[1] + 1)
    pixels = local_shape[0] * local_shape[1]
    elements = (
        (4 * window_planes + 2 * local_planes) * window
        + 2 * window_planes * placements
        + 3 * batch * pixels * weight_bins
        + 2 * batch * placements
    )
    return elements * itemsize + 8 * window


def information_planes(bins: int, pixels: int) -> int:
    """Planes of one side of an ENMI/NMI surface: at most one per bin that its pixels can occupy, and a mask."""
    return min(bins, pixels) + 1


def search_bytes(
    batch: int,
    local_shape: tuple[int, int],
    radius: tuple[int, int],
    yaws: int,
    bins: int | None,
    itemsize: int,
    coarse_factor: int,
) -> int:
    """Bytes of a :func:`~enmi_torch.localize` search: windows, surfaces and the ``(B, Y, Sy, Sx)`` result.

    ``bins=None`` for NCC (three planes a side, no bin weights). With ``coarse_factor > 1`` the surfaces are taken
    on images pooled by the factor (the full-resolution refinements are small).
    """
    height, width = local_shape
    rows, cols = height + 2 * radius[0], width + 2 * radius[1]
    if coarse_factor > 1:
        height, width = max(1, height // coarse_factor), max(1, width // coarse_factor)
        rows, cols = rows // coarse_factor + height + 1, cols // coarse_factor + width + 1
    if bins is None:
        local_planes = window_planes = 3
        weight_bins = 0
    else:
        local_planes = information_planes(bins, height * width)
        window_planes = information_planes(bins, rows * cols)
        weight_bins = bins
    surface = surface_bytes(yaws, (height, width), (rows, cols), local_planes, window_planes, weight_bins, itemsize)
    results = batch * yaws * (2 * radius[0] + 1) * (2 * radius[1] + 1) * (2 * itemsize + 1)
    return surface + results + (itemsize + 1) * rows * cols


def check_histogram_memory(
    captured: Any,
    bins: int,
    candidates: int | None,
    *,
    captured_planes: bool,
    reference_planes: bool,
    scored: bool,
) -> None:
    """Refuse joint histograms of ``captured`` ``(B, N)`` (against ``candidates`` references, or one) over the budget.

    ``captured_planes`` and ``reference_planes`` as in :func:`joint_histogram_bytes`; ``scored``: NMI is taken.
    """
    batch, pixels = captured.shape
    count = 1 if candidates is None else candidates
    needed = joint_histogram_bytes(
        count,
        batch,
        pixels,
        bins,
        captured.element_size(),
        captured_planes=captured_planes,
        reference_planes=reference_planes,
        histogram_copies=4 if scored else 1,
    )
    if within_budget(needed):
        return
    shape = (batch, bins, bins) if candidates is None else (candidates, batch, bins, bins)
    parts = [f"the joint histograms {shape} in {str(captured.dtype).removeprefix('torch.')}"]
    parts += ["their entropies"] * scored + [f"the bin weights of {pixels} pixels"] * captured_planes
    what = parts[0] if len(parts) == 1 else f"{', '.join(parts[:-1])} and {parts[-1]}"
    raise budget_error(needed, f"bins={bins}", what, "lower bins, or pass fewer samples or candidates per call")


def check_surface_memory(local: Any, window: Any, bins: int | None) -> None:
    """Refuse an FFT surface of ``local`` ``(B, h, w)`` in ``window`` ``(Bw, Hw, Ww)`` over the budget; NCC: no bins."""
    batch, height, width = local.shape
    rows, cols = window.shape[1:]
    if bins is None:
        planes = (3, 3, 0)
    else:
        planes = (information_planes(bins, height * width), information_planes(bins, rows * cols), bins)
    needed = surface_bytes(batch, (height, width), (rows, cols), *planes, local.element_size())
    if within_budget(needed):
        return
    raise budget_error(
        needed,
        f"a {rows} x {cols} window" + ("" if bins is None else f" with bins={bins}"),
        f"the FFT spectra of its planes and the surfaces of {batch} local image(s) of {height} x {width}",
        "pass a smaller window" + ("" if bins is None else " or lower bins"),
    )


def check_search_memory(
    local: Any, shifts: Any, radius: tuple[int, int], yaws: int, bins: int | None, coarse_factor: int
) -> None:
    """Refuse a :func:`~enmi_torch.localize` search over the budget, before any window is cut."""
    batch, _, height, width = local.shape
    itemsize = max(4, local.element_size())  # float64 stays, lower precisions compute in float32
    needed = search_bytes(batch, (height, width), radius, yaws, bins, itemsize, coarse_factor)
    if within_budget(needed):
        return
    surfaces = (batch, yaws, 2 * radius[0] + 1, 2 * radius[1] + 1)
    raise budget_error(
        needed,
        f"shifts={shifts!r}" + ("" if coarse_factor == 1 else f" with coarse_factor={coarse_factor}"),
        f"the {height + 2 * radius[0]} x {width + 2 * radius[1]} search window, the FFT spectra of its planes"
        + ("" if bins is None else f" (bins={bins})")
        + f" and the surfaces {surfaces}",
        "lower shifts, search coarse to fine (a larger coarse_factor)" + ("" if bins is None else " or lower bins"),
    )


def check_cells_memory(cause: str, cells: int, bytes_per_cell: int, what: str, remedy: str) -> None:
    """Refuse ``cells`` cells of ``bytes_per_cell`` bytes each (maps, grids, kernels) over the budget.

    ``cause`` names the arguments as passed (``"shape=(100000, 100000)"``), ``what`` the tensors counted.
    """
    needed = cells * bytes_per_cell
    if not within_budget(needed):
        raise budget_error(needed, cause, what, remedy)
