"""What a score is: the :class:`Score` base class, :func:`as_score` (the string shorthand) and :func:`direct_surface`.

A score object owns its options (checked once, at construction), its value on aligned pairs (``score(...)``), its
surface over every placement (``score.surface(...)``) and its loss (``score.loss(...)``); each family's file
(:mod:`~enmi_torch.scores.ecr`, :mod:`~enmi_torch.scores.enmi`, :mod:`~enmi_torch.scores.nmi`,
:mod:`~enmi_torch.scores.ncc`, :mod:`~enmi_torch.scores.mixture`) holds the functions that do the work and the class
that calls them. Everything that takes a score (``localize``, ``Localizer``, ``Tracker``, ``ScoreLoss``, the
command line) takes the object, or its name for the default options.
"""

from __future__ import annotations

import inspect
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor

from enmi_torch.placement.direct import PairScore, direct_placements
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.utils.checks import check_option

REDUCTIONS = ("none", "mean", "sum")
# The optional capabilities a family may declare (Score.traits), with the methods each one means.
TRAITS = {
    "two_stage": "rough_score, rough_surface and placement_scores",
    "least_squares": "response_basis and least_squares_fit",
}
TRAIT_NOTES = {
    "two_stage": "ECR with response='shrunk' or 'binned'",
    "least_squares": "a weighted least-squares fit, smooth in the pose; a histogram score has none",
}
# Each family registers itself here under its name (see Score.__init_subclass__), for as_score.
_FAMILIES: dict[str, type[Score]] = {}


def reduce_loss(loss: Tensor, reduction: str) -> Tensor:
    """``loss`` ``(B,)`` reduced by ``"mean"``, ``"sum"`` or ``"none"`` (checked against :data:`REDUCTIONS`)."""
    check_option("reduction", reduction, REDUCTIONS)
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    return loss


class ResponseBasis(NamedTuple):
    """The response of the map's values that a least-squares score fits the captured values by.

    Attributes:
        knots: ``K >= 2`` for a piecewise-linear response with a knot on the centre of each of ``K`` equal bins over
            ``value_range``; 0 for the affine response ``a + b m``.
        value_range: ``(low, high)`` of the knots' bins; ``None`` for the affine response.
    """

    knots: int = 0
    value_range: tuple[float, float] | None = None

    @property
    def size(self) -> int:
        """The number of the response's coefficients: the knots, or 2 (``a`` and ``b``)."""
        return self.knots or 2


class LeastSquaresFit(NamedTuple):
    """A least-squares score's terms at one alignment: how it weighs each pixel and pulls its response.

    Attributes:
        weights: ``(B, N)`` per-pixel weights, 0 where a pixel does not count.
        line_penalty: ``(B,)`` the pull ``1 / delta^2`` of a piecewise-linear response's knots toward a line, or
            ``None`` for a response fitted freely.
    """

    weights: Tensor
    line_penalty: Tensor | None = None


class Score:
    """A score of a captured image against a reference: its options, value, surface and loss in one object.

    Subclasses (the families) take keyword-only options, check them and pass them to ``Score.__init__``; they define
    ``_value``, ``_surface`` and ``_loss`` by calling their family's functions. A score is a plain Python object:
    compared by options, hashable, picklable (so that it can be sent to worker processes).

    Attributes:
        name: the family's name, as :func:`as_score` takes it (``"ecr"``, ``"enmi"``, ``"nmi"``, ``"ncc"``,
            ``"mixture"``).
        uses_variance: whether the score weighs the captured pixels by a noise variance (required then, refused
            otherwise).
        empty_score: the score of a placement where no valid pixel overlaps (that of unrelated images).
        higher_is_better: ``True`` for every family: a larger score is a better match (its loss falls). Beside
            it, :attr:`is_differentiable` says whether the score carries a gradient (a loss of one that does not is
            refused).
    """

    name: ClassVar[str]
    uses_variance: ClassVar[bool]
    # The traits some instance of the family may have (for require's message); Score.traits says which one has.
    trait_holders: ClassVar[frozenset[str]] = frozenset()
    empty_score: ClassVar[float] = 0.0
    higher_is_better: ClassVar[bool] = True
    # Whether the captured values are binned (they must then not all fall in one bin while varying).
    _bins_captured: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" in cls.__dict__:
            _FAMILIES[cls.name] = cls

    def __init__(self, **options: Any) -> None:
        self._options = options

    @property
    def options(self) -> dict[str, Any]:
        """The options as given and checked (a copy): ``type(score)(**score.options) == score``."""
        return dict(self._options)

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The names of the family's options, in the constructor's order."""
        parameters = inspect.signature(cls.__init__).parameters.values()
        return tuple(parameter.name for parameter in parameters if parameter.kind is inspect.Parameter.KEYWORD_ONLY)

    def __getattr__(self, name: str) -> Any:
        options = self.__dict__.get("_options", {})
        if name in options:
            return options[name]
        raise AttributeError(f"{type(self).__name__} has no attribute or option {name!r}")

    def replace(self, **changes: Any) -> Score:
        """A copy with some options changed, checked again: ``ECR().replace(bins=8) == ECR(bins=8)``."""
        unknown = sorted(set(changes) - set(self.option_names()))
        if unknown:
            raise TypeError(
                f"{type(self).__name__} has no option(s) {unknown}; its options: {list(self.option_names())}"
            )
        return type(self)(**{**self._options, **changes})

    def __repr__(self) -> str:
        options = ", ".join(f"{name}={_short_repr(value)}" for name, value in self._options.items())
        return f"{type(self).__name__}({options})"

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash((type(self).__name__, self._key()))

    def _key(self) -> tuple:
        """The options as a tuple of plain values (tensors by dtype, shape and values)."""
        return tuple(
            (name, (str(value.dtype), tuple(value.shape), tuple(value.flatten().tolist())))
            if isinstance(value, Tensor)
            else (name, value)
            for name, value in self._options.items()
        )

    @property
    def is_differentiable(self) -> bool:
        """Whether the score carries a gradient to the captured image, so that its loss can train."""
        return True

    def check_differentiable(self) -> None:
        """Raise ``ValueError`` when the score carries no gradient, naming the option that gives one."""
        if not self.is_differentiable:
            raise ValueError(f"{self!r} has no gradient, so it has no loss")

    def check_variance(self, variance: Any) -> None:
        """Raise ``ValueError`` unless a variance is given exactly when this score uses one."""
        if self.uses_variance and variance is None:
            raise ValueError(f"variance must be given for score {self.name!r}, got None")
        if not self.uses_variance and variance is not None:
            raise ValueError(
                f"variance is not used by score {self.name!r}; pass variance=None, got {type(variance).__name__}"
            )

    def __call__(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float | None = None, *, valid_mask=None
    ) -> Tensor:
        """The score of aligned pairs, ``(B,)`` (``(C, B)`` for ``C`` candidate references per captured image).

        Args:
            captured: ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
            reference: the same shape, or ``(C, *captured.shape)``.
            variance: the captured pixels' noise variance (a number or a per-pixel map) for the scores that use one
                (:attr:`uses_variance`), else ``None``.
            valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        """
        self.check_variance(variance)
        return self._value(captured, reference, variance, valid_mask)

    def surface(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Surface:
        """The score at every placement of ``captured`` ``(B, 1, h, w)`` inside ``reference`` ``(1 or B, 1, Hw, Ww)``.

        Returns:
            :class:`~enmi_torch.placement.Surface` ``(B, Hw - h + 1, Ww - w + 1)``: ``score[b, u, v]`` equals this
            score of ``captured[b]`` and ``reference[b, :, u:u + h, v:v + w]`` over the pixels valid in both
            (:func:`direct_surface` computes it that way), without gradient.
        """
        self.check_variance(variance)
        return self._surface(captured, reference, variance, captured_mask, reference_mask)

    def loss(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        valid_mask: Tensor | None = None,
        reduction: str = "mean",
    ) -> Tensor:
        """The family's loss (``2 - NMI``, ``2 - ENMI``, ``1 - NCC``, ``-ECR``, ``-M``) reduced over the batch.

        Raises:
            ValueError: for a score without gradient (:attr:`is_differentiable` false), naming the option to change.
        """
        check_option("reduction", reduction, REDUCTIONS)
        self.check_differentiable()
        self.check_variance(variance)
        return self._loss(captured, reference, variance, valid_mask, reduction)

    def per_sample(self, batch: int) -> list[Score]:
        """The score for each sample of a batch: options given per sample (ENMI's ``(B, bins)`` prior) cut to one."""
        return [self] * batch

    @property
    def traits(self) -> frozenset[str]:
        """The optional capabilities this score implements, of :data:`TRAITS` (none by default).

        ``"two_stage"``: :meth:`rough_score`, :meth:`rough_surface` and :meth:`placement_scores`, for the two-stage
        search; ``"least_squares"``: :meth:`response_basis` and :meth:`least_squares_fit`, for
        :func:`~enmi_torch.register`. A family that has a trait for some options only says so per instance.
        """
        return frozenset()

    def require(self, trait: str, use: str) -> None:
        """Raise ``ValueError`` naming ``use``, the trait and the scores that have it, unless this score has it."""
        check_option("trait", trait, tuple(TRAITS))
        if trait not in self.traits:
            holders = [name for name, family in sorted(_FAMILIES.items()) if trait in family.trait_holders]
            raise ValueError(
                f"{use} needs a score with the {trait!r} trait ({TRAITS[trait]}), got score={self!r}; scores that "
                f"have it: {', '.join(holders)} ({TRAIT_NOTES[trait]})"
            )

    @property
    def surface_is_exact(self) -> bool:
        """Whether :meth:`surface` equals this score of each aligned pair (then a search has no finalist to rescore).

        ``True`` for scores whose surface sums the same terms as their value; ``False`` where the surface holds a
        model fitted once (ECR's estimated model variance and response, its censored readings): a search rescores
        its finalists by :meth:`finalists`.
        """
        return True

    @property
    def estimates_noise_model(self) -> bool:
        """Whether this score estimates a noise model from each pair (ECR's ``tau^2`` or ``delta^2``).

        :meth:`held_fit` holds it; ``False`` by default (NMI, ENMI, NCC, the mixture, ECR with both fixed).
        """
        return False

    def held_fit(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float | None = None, *, valid_mask=None
    ) -> Score:
        """This score with what it estimates from each pair estimated on one aligned pair and held fixed.

        A score that fits a model to each pair (ECR's ``tau^2`` and ``delta^2``: :attr:`estimates_noise_model`)
        scores every later pair with the model of this one: :class:`~enmi_torch.Tracker` holds it across frames
        (``TrackerSettings.noise_model``). The default, for a score that estimates nothing from the pair: the score
        itself. Arguments as :meth:`__call__`'s, one pair.
        """
        self.check_variance(variance)
        return self

    def finalists(
        self,
        captured: Tensor,
        window: Tensor,
        placements: Tensor,
        variance: Tensor | None = None,
        *,
        captured_mask: Tensor | None = None,
        window_mask: Tensor | None = None,
    ) -> Tensor:
        """This score's exact value at a few placements of captured images in a map window, ``(P,)``.

        The search's finalist stage (:class:`~enmi_torch.localization.SearchStrategy`'s ``finalists``): the
        surface ranks every placement; its best local maxima are scored here, each with its own fit. The default
        crops the window under each placement and scores the aligned pair (``score(captured, crop, variance)``,
        the pixels valid in both): always right, and a new family gets it for free; a family overrides it only to
        be faster.

        Args:
            captured: ``(Y, 1, h, w)`` captured images (a search's rotations of one image, one per yaw).
            window: ``(1, 1, Hw, Ww)`` the map window of the surface.
            placements: ``(P, 3)`` int64 ``(index into captured, row, col)``: ``captured[k]`` with its top-left pixel
                on window cell ``(row, col)``, as ``surface[k, row, col]``.
            variance: ``(Y, 1, h, w)`` for a score that uses one, else ``None``.
            captured_mask: ``(Y, 1, h, w)`` bool, or ``None`` (all valid).
            window_mask: ``(1, 1, Hw, Ww)`` bool, or ``None`` (all valid).

        Returns:
            ``(P,)`` scores, ``empty_score`` where no valid pixel of the placement lands on a valid cell.

        Example:
            >>> from enmi_torch import NMI
            >>> window = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
            >>> score = NMI(bins=64, kernel="hard")
            >>> score.finalists(window[..., 2:6, 1:5], window, torch.tensor([[0, 2, 1], [0, 0, 0]])).tolist()
            [2.0, 2.0]
        """
        height, width = captured.shape[2:]
        index, rows, cols = placements.unbind(1)
        rows_at = rows[:, None, None] + torch.arange(height, device=window.device)[:, None]
        cols_at = cols[:, None, None] + torch.arange(width, device=window.device)
        crops = window[0, 0][rows_at, cols_at][:, None]
        valid = torch.ones_like(crops, dtype=torch.bool)
        if window_mask is not None:
            valid = window_mask[0, 0][rows_at, cols_at][:, None]
        if captured_mask is not None:
            valid = valid & captured_mask[index]
        scores = torch.full((placements.shape[0],), self.empty_score, dtype=window.dtype, device=window.device)
        kept = valid.flatten(1).any(1)
        if bool(kept.any()):
            chosen = variance[index[kept]] if variance is not None else None
            scores[kept] = self(captured[index[kept]], crops[kept], chosen, valid_mask=valid[kept]).to(scores.dtype)
        return scores

    def _pair_scorer(self, inputs: SurfaceInputs) -> PairScore:
        """:func:`direct_surface`'s score of one aligned pair: the score itself, with each sample's options."""
        samples = self.per_sample(inputs.captured.shape[0])

        def pair_score(sample: int, captured: Tensor, section: Tensor, variance: Tensor | None, valid: Tensor):
            return samples[sample](captured, section, variance, valid_mask=valid)[0]

        return pair_score

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        raise NotImplementedError

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        raise NotImplementedError

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        raise NotImplementedError


def _short_repr(value: Any) -> str:
    """A tensor option as ``tensor(shape, dtype)`` (its values would flood the repr), anything else as ``repr``."""
    if isinstance(value, Tensor):
        return f"tensor({tuple(value.shape)}, {value.dtype})"
    return repr(value)


def as_score(score: Score | str) -> Score:
    """A :class:`Score` as it is, or a family's name as that family with its default options.

    Example:
        >>> as_score("ncc"), as_score("ecr").options["response"]
        (NCC(), 'shrunk')
        >>> as_score("mi")
        Traceback (most recent call last):
        ...
        ValueError: score must be a Score or one of ['ecr', 'enmi', 'mixture', 'ncc', 'nmi'], got 'mi'
    """
    if isinstance(score, Score):
        return score
    if isinstance(score, str) and score in _FAMILIES:
        return _FAMILIES[score]()
    raise ValueError(f"score must be a Score or one of {sorted(_FAMILIES)}, got {score!r}")


def score_names() -> list[str]:
    """The names :func:`as_score` takes, sorted."""
    return sorted(_FAMILIES)


def direct_surface(
    score: Score | str,
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | None = None,
    *,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """The reference for the FFT surfaces: a loop over placements, ``score(...)`` on each aligned pair.

    Slow (one call per placement and sample); use it on small windows to check ``score.surface(...)``, which takes
    the same arguments.

    Args:
        score: a :class:`Score` or its name (:func:`as_score`).
        captured: ``(B, 1, h, w)``.
        reference: ``(1 or B, 1, Hw, Ww)``.
        variance: the captured pixels' noise variance, for the scores that use one.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference.

    Returns:
        :class:`~enmi_torch.placement.Surface`: ``score[b, u, v]`` is the score of ``captured[b]`` and
        ``reference[b, :, u:u + h, v:v + w]`` over the pixels valid in both (``score.empty_score`` without any).

    Example:
        >>> from enmi_torch import NMI
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
        >>> direct_surface(NMI(bins=64, kernel="hard"), reference[..., 2:6, 1:5], reference).score[0, 2, 1]
        tensor(2.)
    """
    score = as_score(score)
    score.check_variance(variance)
    value_range = score.options.get("value_range", (0.0, 1.0))  # the fill of masked pixels, never scored
    bins = score.bins if score._bins_captured else None
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    return direct_placements(inputs, score._pair_scorer(inputs), score.empty_score)
