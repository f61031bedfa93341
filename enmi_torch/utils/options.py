"""Options that only mean something together, and keywords that moved: each refused in one line that names them.

A family's options (a score's, a search's) are checked one by one where they are taken; which *combinations* mean
something is one small table per family, a tuple of :class:`OptionRule` rows, checked by :func:`check_option_rules`
in the family's constructor and in every function that takes the same options (the table is the one place that
decides). An option left at its default never trips a rule. A keyword that moved into an options object
(``SearchStrategy``, ``TrackerSettings``, a score) is refused by :func:`refuse_moved_keywords`, naming its new home.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

from torch import Tensor


class OptionRule(NamedTuple):
    """One row of a family's table: ``option`` takes effect only where the option ``needs`` is one of ``applies_with``.

    Attributes:
        option: the option that may be moot (away from its default it must take effect).
        needs: the option whose value decides.
        applies_with: the values of ``needs`` under which ``option`` takes effect, or a predicate on that value.
        meaning: what ``option`` is, for the refusal ("the shrunk response's delta^2").
        wanted: the remedy where ``applies_with`` is a predicate (``"coarse_factor > 1"``); a tuple spells its own.
    """

    option: str
    needs: str
    applies_with: tuple | Callable[[Any], bool]
    meaning: str
    wanted: str = ""

    def applies(self, value: Any) -> bool:
        """Whether ``option`` takes effect with ``needs`` set to ``value``."""
        if callable(self.applies_with):
            return bool(self.applies_with(value))
        return not isinstance(value, Tensor) and value in self.applies_with


def spell_keyword(name: str, value: Any) -> str:
    """An option as a keyword argument: ``response='linear'``."""
    return f"{name}={value!r}"


class OptionError(ValueError):
    """A refusal that names options: ``write(spell)`` is its text with each option written by ``spell(name, value)``.

    The message spells them as keyword arguments (:func:`spell_keyword`); :meth:`spelled` spells them another way, as
    a command's flags (``--score-option misfit=regional``, ``--model.localization_shift 4``).
    """

    def __init__(self, write: Callable[[Callable[[str, Any], str]], str]) -> None:
        self.write = write
        super().__init__(write(spell_keyword))

    def spelled(self, spell: Callable[[str, Any], str]) -> str:
        """The refusal with each option written by ``spell``."""
        return self.write(spell)


class OptionConflict(OptionError):
    """An option given where another makes it moot: the :class:`OptionRule`, the value given, the other's value."""

    def __init__(self, rule: OptionRule, value: Any, other: Any) -> None:
        self.rule, self.value, self.other = rule, value, other
        super().__init__(self._write)

    def _write(self, spell: Callable[[str, Any], str]) -> str:
        rule = self.rule
        if callable(rule.applies_with):
            remedy = rule.wanted
        else:
            remedy = " or ".join(spell(rule.needs, value) for value in rule.applies_with)
        return (
            f"{spell(rule.option, self.value)} has no effect with {spell(rule.needs, self.other)}: it is "
            f"{rule.meaning}; drop it or pass {remedy}"
        )


def _is_default(value: Any, default: Any) -> bool:
    """Whether an option's value is its default (a tensor or a bool only by identity: ``1 == True``)."""
    if value is default:
        return True
    if isinstance(value, (Tensor, bool)) or isinstance(default, (Tensor, bool)):
        return False
    return bool(value == default)


def check_option_rules(rules: Sequence[OptionRule], options: Mapping[str, Any], defaults: Mapping[str, Any]) -> None:
    """Raise :class:`OptionConflict` for the first row of ``rules`` that ``options`` break.

    ``defaults``: the defaults of the function or constructor that took ``options`` (:func:`signature_defaults`); an
    option at its default breaks no row. A row whose options are not both among ``options`` is skipped (a function
    that takes only some of the family's options).
    """
    for rule in rules:
        if rule.option not in options or rule.needs not in options:
            continue
        value = options[rule.option]
        if rule.option in defaults and _is_default(value, defaults[rule.option]):
            continue
        if not rule.applies(options[rule.needs]):
            raise OptionConflict(rule, value, options[rule.needs])


@functools.cache
def signature_defaults(function: Callable) -> dict[str, Any]:
    """The defaults of ``function``'s parameters, by name (the values an option left out takes)."""
    parameters = inspect.signature(function).parameters.values()
    return {parameter.name: parameter.default for parameter in parameters if parameter.default is not parameter.empty}


class MovedKeywords(NamedTuple):
    """Keywords a function took before that now live in one of its arguments (an options object).

    Attributes:
        names: the keywords that moved.
        parameter: the argument that takes them now (``"search"``).
        home: the class they are fields or options of (``"SearchStrategy"``); ``home_of``, if given, picks it from
            the keywords given (a score's family from ``metric``).
        where: where to import it from, for the message.
        home_of: ``(given keywords) -> (class name, keywords that are not its options)``, or ``None``.
    """

    names: tuple[str, ...]
    parameter: str
    home: str
    where: str
    home_of: Callable[[dict[str, Any]], tuple[str, tuple[str, ...]]] | None = None

    def refusal(self, owner: str, given: dict[str, Any]) -> str | None:
        """The refusal of the keywords of ``given`` that moved, for the function ``owner``; ``None`` for none."""
        moved = {name: given[name] for name in self.names if name in given}
        if not moved:
            return None
        home, dropped = (self.home, ()) if self.home_of is None else self.home_of(moved)
        fields = ", ".join(f"{name}={value!r}" for name, value in moved.items() if name not in dropped)
        return (
            f"{owner}() takes {', '.join(moved)} in {self.parameter}={home}(...): pass "
            f"{self.parameter}={home}({', '.join(part for part in ('...', fields) if part)}) ({self.where})"
        )


def refuse_moved_keywords(*moves: MovedKeywords) -> Callable[[Callable], Callable]:
    """A decorator: the function refuses the keywords of ``moves`` by one ``TypeError`` naming where each went.

    Example:
        >>> moved = MovedKeywords(("cheap_bins",), "search", "SearchStrategy", "enmi_torch.localization")
        >>> @refuse_moved_keywords(moved)
        ... def find(*, search=None):
        ...     return search
        >>> find(cheap_bins=8)
        Traceback (most recent call last):
        ...
        TypeError: find() takes cheap_bins in search=SearchStrategy(...): pass search=SearchStrategy(...
    """

    def decorate(function: Callable) -> Callable:
        @functools.wraps(function)
        def checked(*args: Any, **kwargs: Any) -> Any:
            owner = function.__qualname__.removesuffix(".__init__")  # a class is called by its name
            refusals = [move.refusal(owner, kwargs) for move in moves]
            refusals = [refusal for refusal in refusals if refusal is not None]
            if refusals:
                raise TypeError("; ".join(refusals))
            return function(*args, **kwargs)

        return checked

    return decorate


def options_checked(check: Callable[[dict[str, Any], dict[str, Any]], Any]) -> Callable[[Callable], Callable]:
    """A decorator: ``check(arguments, defaults)`` runs on each call's arguments (defaults filled in) before the call.

    ``check`` is a family's option check (the single options, then its table of :class:`OptionRule` rows), so that
    a function taking a family's options refuses what the family's constructor refuses, with the same words.
    """

    def decorate(function: Callable) -> Callable:
        signature, defaults = inspect.signature(function), signature_defaults(function)

        @functools.wraps(function)
        def checked(*args: Any, **kwargs: Any) -> Any:
            try:
                bound = signature.bind(*args, **kwargs)
            except TypeError:
                return function(*args, **kwargs)  # Python's own message for a wrong call
            check({**defaults, **bound.arguments}, defaults)
            return function(*args, **kwargs)

        return checked

    return decorate
