"""One scene key (``Key``): its type, default, unit, allowed range and meaning; and the
error a scene that breaks a key's rule raises (``SceneError``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from bayespsf.errors import BayespsfInputError


class SceneError(BayespsfInputError):
    """A scene key is unknown, unused by its kind, of the wrong type or out of range.

    Attributes
    ----------
    args : tuple of str
        ``(message,)``: what is wrong, naming the key (``section.key``) and its allowed range.
    """


@dataclass(frozen=True)
class Key:
    """One scene key: its type, default, unit, allowed values and meaning.

    Parameters
    ----------
    name : str
        The key's name within its table.
    kind : type or tuple of str
        ``float``, ``int``, ``bool``, ``str``, ``list``, or a tuple of the allowed strings.
    default : Any
        The value an omitted key takes.
    unit : str
        The value's unit in words (``"nm"``, ``"photons"``; ``""`` for none).
    doc : str
        What the key means (one sentence, in ``docs/scenes.md``'s tables).
    low, high : float or None, optional
        The allowed range of a number (None: unbounded).
    low_open, high_open : bool, optional
        Whether that end of the range is excluded.
    when : callable, optional
        ``when(table) -> bool``: the key applies only where this is true (None: always).
    when_doc : str, optional
        The rule in words.

    Examples
    --------
    >>> from bayespsf.scene import Key
    >>> Key("pixel_size", float, 100.0, "nm", "pixel side", 1.0, 1e5).allowed()
    '[1, 100000]'
    """

    name: str
    kind: type | tuple[str, ...]  # float, int, bool, str, list, or a tuple of allowed strings
    default: Any
    unit: str
    doc: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    when: Callable[[Mapping], bool] | None = None  # the key applies only when this is true
    when_doc: str = ""

    def allowed(self) -> str:
        """The allowed values in words: ``"one of 'a', 'b'"``, a type name, or a range.

        Returns
        -------
        str
            E.g. ``"[1, 100000]"``, ``"(0, inf]"``; brackets say whether an end is included.
        """
        if isinstance(self.kind, tuple):
            return "one of " + ", ".join(repr(c) for c in self.kind)
        if self.low is None and self.high is None:
            return self.kind.__name__
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        return ("(" if self.low_open else "[") + f"{lo}, {hi}" + (")" if self.high_open else "]")


def when_is(section_key: str, *values: str) -> Callable[[Mapping], bool]:
    """A ``Key.when`` rule: the key applies where the section's ``section_key`` is one of
    ``values``.

    Parameters
    ----------
    section_key : str
        Another key of the same table.
    *values : str
        The values of ``section_key`` for which the key applies.

    Returns
    -------
    callable
        ``rule(table) -> bool``.
    """
    return lambda section: section.get(section_key) in values


__all__ = ["Key", "SceneError", "when_is"]
