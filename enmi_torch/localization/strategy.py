"""How a search visits the candidate poses: :class:`SearchStrategy` (every candidate, coarse to fine, or two stages).

:func:`~enmi_torch.localize` and :class:`~enmi_torch.Localizer` take one as ``search=`` (or its method's name, for the
default options); :mod:`~enmi_torch.localization.surfaces` carries it out.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from enmi_torch.utils.checks import check_bins, check_non_negative_int, check_option, check_positive_int

SEARCHES = ("exhaustive", "two_stage")
# Keyword arguments of localize and Localizer that are fields of SearchStrategy.
MOVED_OPTIONS = ("coarse_factor", "coarse_peaks", "cheap_bins")


@dataclass(frozen=True)
class SearchStrategy:
    """How :func:`~enmi_torch.localize` visits the candidate poses, with the options of that way.

    Attributes:
        method: ``"exhaustive"`` (every shift and yaw scored; coarse to fine when ``coarse_factor > 1``) or
            ``"two_stage"`` (a score that :attr:`~enmi_torch.scores.Score.supports_two_stage`, such as ECR with the
            shrunk or binned response, and ``coarse_factor=1``): the score's rough surface
            (:meth:`~enmi_torch.scores.Score.rough_surface`: ``cheap_bins`` bins spanning the 2nd to 98th percentile
            of the map window's valid cells, their default model variance) over every shift and yaw, then the exact
            score (:meth:`~enmi_torch.scores.Score.placement_scores`) at the 3 x 3 x 3 (shift, shift, yaw)
            neighbourhoods of its best 4 peaks; while the exact best lies by a peak of the lower half of that cheap
            ranking, the number of peaks doubles (up to 64), then the exact best's own neighbourhood is completed for
            the sub-cell fit. Rescored candidates score as in the exhaustive surface (up to round-off; with ECR's
            estimated model variance, read at each yaw's cheap peak, when ``cheap_bins=4`` and ``min_overlap <= 0.5``,
            else it may be read elsewhere), the others are ``-inf`` in ``surface``. It misses the exhaustive argmax
            when the cheap score ranks that peak below the ones it rescored and the doubling has stopped.
        coarse_factor: ``1`` searches every shift. ``f > 1`` searches first on images averaged over ``f x f`` cells
            (variance divided by ``f^2``), keeps the ``coarse_peaks`` best separated coarse candidates and searches
            every shift within ``f`` cells of each at full resolution (at its yaw and the two next ones): for windows
            much larger than the captured image. Each of these surfaces reads ECR's estimated model variance in its
            own window.
        coarse_peaks: coarse candidates refined when ``coarse_factor > 1``.
        cheap_bins: bins of the first stage of the two-stage search, ``2 <= cheap_bins <= bins`` of the score.
        finalists: how many of the surface's best local maxima (over shifts and yaws) are rescored exactly, each with
            its own fit (:meth:`~enmi_torch.scores.Score.finalists`), when the score's surface holds a model fitted
            once (not :attr:`~enmi_torch.scores.Score.surface_is_exact`: ECR's default); the pose is the best of
            them (:class:`~enmi_torch.localization.Finalists`). ``0``: the surface's maximum as it is. The default
            was chosen by measurement (``docs/results/scores.md``).

    Example:
        >>> SearchStrategy("two_stage", cheap_bins=8)
        SearchStrategy(method='two_stage', coarse_factor=1, coarse_peaks=3, cheap_bins=8, finalists=8)
        >>> as_search_strategy("two_stage") == SearchStrategy("two_stage")
        True
    """

    method: str = "exhaustive"
    coarse_factor: int = 1
    coarse_peaks: int = 3
    cheap_bins: int = 4
    finalists: int = 8

    def __post_init__(self) -> None:
        check_option("search", self.method, SEARCHES)
        check_positive_int("coarse_factor", self.coarse_factor)
        check_positive_int("coarse_peaks", self.coarse_peaks)
        check_bins(self.cheap_bins, "cheap_bins")
        check_non_negative_int("finalists", self.finalists)
        if self.method == "two_stage" and self.coarse_factor != 1:
            raise ValueError(f"search='two_stage' needs coarse_factor=1, got coarse_factor={self.coarse_factor!r}")


def as_search_strategy(search: SearchStrategy | str) -> SearchStrategy:
    """A :class:`SearchStrategy` as it is, or a method's name (``"exhaustive"``, ``"two_stage"``) with its defaults."""
    if isinstance(search, SearchStrategy):
        return search
    return SearchStrategy(method=search)


def refuse_moved_search_options(function: Callable) -> Callable:
    """``function`` that refuses the keyword arguments now in :class:`SearchStrategy` by a ``TypeError`` naming it."""

    @functools.wraps(function)
    def checked(*args: Any, **kwargs: Any) -> Any:
        moved = [name for name in MOVED_OPTIONS if name in kwargs]
        if moved:
            fields = ", ".join(f"{name}={kwargs[name]!r}" for name in moved)
            raise TypeError(
                f"{function.__qualname__}() takes {', '.join(moved)} in search=SearchStrategy(...): pass "
                f"search=SearchStrategy(..., {fields}) (enmi_torch.localization.SearchStrategy)"
            )
        return function(*args, **kwargs)

    return checked
