"""How a search visits the candidate poses: :class:`SearchStrategy` (every candidate, coarse to fine, or two stages).

:func:`~enmi_torch.localize` and :class:`~enmi_torch.Localizer` take one as ``search=`` (or its method's name, for the
default options); :mod:`~enmi_torch.localization.surfaces` carries it out.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from enmi_torch.scores import as_score, score_names
from enmi_torch.utils.checks import check_bins, check_non_negative_int, check_option, check_positive_int
from enmi_torch.utils.options import (
    MovedKeywords,
    OptionRule,
    check_option_rules,
    refuse_moved_keywords,
    signature_defaults,
)

SEARCHES = ("exhaustive", "two_stage")
# Keyword arguments of localize and Localizer that are fields of SearchStrategy.
MOVED_OPTIONS = ("coarse_factor", "coarse_peaks", "cheap_bins")
# Which fields take effect under which values of the others (one more row for a new field that depends on another).
SEARCH_RULES = (
    OptionRule("cheap_bins", "method", ("two_stage",), "the bins of the two-stage search's first stage"),
    OptionRule(
        "coarse_peaks",
        "coarse_factor",
        lambda factor: factor > 1,
        "the number of coarse candidates a coarse-to-fine search refines",
        "coarse_factor > 1 (a coarse-to-fine search)",
    ),
)


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
        coarse_peaks: coarse candidates refined when ``coarse_factor > 1`` (refused with ``coarse_factor=1``).
        cheap_bins: bins of the first stage of the two-stage search, ``2 <= cheap_bins <= bins`` of the score
            (refused with the exhaustive search). Which fields need which is :data:`SEARCH_RULES`.
        finalists: how many of the surface's best local maxima (over shifts and yaws) are rescored exactly, each with
            its own fit (:meth:`~enmi_torch.scores.Score.finalists`), when the score's surface holds a model fitted
            once (not :attr:`~enmi_torch.scores.Score.surface_is_exact`: ECR's default); the pose is the best of
            them (:class:`~enmi_torch.localization.Finalists`). ``0``: the surface's maximum as it is. The default
            was chosen by measurement (``docs/results/scores.md``). Another count with a score whose surface is exact
            is refused by the search (it has no finalist stage).

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
        options = {field.name: getattr(self, field.name) for field in fields(self)}
        check_option_rules(SEARCH_RULES, options, signature_defaults(SearchStrategy))


def as_search_strategy(search: SearchStrategy | str) -> SearchStrategy:
    """A :class:`SearchStrategy` as it is, or a method's name (``"exhaustive"``, ``"two_stage"``) with its defaults."""
    if isinstance(search, SearchStrategy):
        return search
    return SearchStrategy(method=search)


def _score_family(given: dict[str, Any]) -> tuple[str, tuple[str, ...]]:
    """The family a former ``metric=`` names (ECR without one); ``metric`` is not one of its options."""
    metric = given.get("metric")
    family = type(as_score(metric)).__name__ if isinstance(metric, str) and metric in score_names() else "ECR"
    return family, ("metric",)


# Keywords that localize, Localizer, Tracker and track_step took before 0.2, and where they live now.
MOVED_TO_SEARCH = MovedKeywords(MOVED_OPTIONS, "search", "SearchStrategy", "enmi_torch.localization.SearchStrategy")
MOVED_TO_SCORE = MovedKeywords(
    ("metric", "bins", "value_range", "kernel", "log_prior", "model_variance", "response", "reliability", "em_steps"),
    "score",
    "ECR",
    "a score of enmi_torch: ECR, ENMI, NMI, NCC or Mixture",
    _score_family,
)
# localize and Localizer refuse them by a TypeError naming their new home.
refuse_moved_search_options = refuse_moved_keywords(MOVED_TO_SEARCH, MOVED_TO_SCORE)
