"""Declared keys: one row per config key or command-line option, with its type, unit, bounds and
meaning.

A :class:`Key` is the single source of a value's parser (:meth:`Key.parse`), of its row in the
docs' tables (:func:`markdown_table`) and, for command-line options, of its argparse type
(``vtube_fleet.cli._args``). Bounds are :class:`Bound` objects: a value outside them is refused
with a message naming the bound and where it comes from, e.g. ``must be <= 50 (the position
stream rate the vehicles send: LOCAL_POSITION_NED at 50 Hz), got 1000000.0``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from vtube_fleet.core.text import plain_number

__all__ = [
    "FINITE",
    "NON_NEGATIVE",
    "POSITIVE",
    "Bound",
    "Key",
    "markdown_table",
    "show_value",
]


def show_value(value: Any) -> str:
    """A config value as the user wrote it (TOML/JSON spelling: ``true``, ``"abc"``, ``-5``;
    ``nan`` / ``inf``; a TOML date as its text), for every config error message."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    try:
        text = json.dumps(value, default=str)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."  # an error is one readable line


@dataclass(frozen=True)
class Bound:
    """The admissible interval of a number: ``low`` < x (``low_inclusive``: <=), x <= ``high``
    (``high_inclusive=False``: <). ``why`` says where the upper bound comes from (a PX4
    default, the vehicles' stream rate, a documented ceiling). Every bounded number must be
    finite. ``interval``: refusals say ``within (low, high)`` instead of naming one side."""

    low: float | None = None
    high: float | None = None
    low_inclusive: bool = False
    high_inclusive: bool = True
    why: str = ""
    interval: bool = False

    def text(self) -> str:
        """The bound as the docs write it: ``> 0``, ``>= 0``, ``(0, 50]``, ``finite``."""
        lo, hi = self.low, self.high
        if lo is not None and hi is not None:
            return (f"{'[' if self.low_inclusive else '('}{plain_number(lo)}, "
                    f"{plain_number(hi)}{']' if self.high_inclusive else ')'}")
        if lo is not None:
            return (">= " if self.low_inclusive else "> ") + plain_number(lo)
        if hi is not None:
            return ("<= " if self.high_inclusive else "< ") + plain_number(hi)
        return "finite"

    def _interval_text(self) -> str:
        return f"within {self.text()}"

    def problem(self, x: float) -> str | None:
        """Why ``x`` is refused (without the ``got …`` part), or ``None`` if it is admissible."""
        if not math.isfinite(x):
            return "expected a finite number"
        if self.low is not None and not (x >= self.low if self.low_inclusive else x > self.low):
            if self.interval:
                return f"must be {self._interval_text()}"
            return f"must be {'>=' if self.low_inclusive else '>'} {plain_number(self.low)}"
        if self.high is not None and not (x <= self.high if self.high_inclusive
                                          else x < self.high):
            if self.interval:
                return f"must be {self._interval_text()}"
            why = f" ({self.why})" if self.why else ""
            return f"must be {'<=' if self.high_inclusive else '<'} {plain_number(self.high)}{why}"
        return None


#: Any finite number.
FINITE = Bound()
#: x > 0 (and finite): durations, rates, gains.
POSITIVE = Bound(low=0.0)
#: x >= 0 (and finite): margins, latencies, factors.
NON_NEGATIVE = Bound(low=0.0, low_inclusive=True)

KINDS = ("number", "integer", "choice", "flag", "text", "point", "other")


@dataclass(frozen=True)
class Key:
    """One declared key or option.

    ``kind``: ``number`` (int or float, within ``bound``), ``integer`` (within ``bound``),
    ``choice`` (one of ``choices``), ``flag`` (true/false), ``text``, ``point`` (``[x, y]``, two
    finite numbers) or ``other`` (a structured value its section parses itself; the row only
    documents it, ``type_label`` says what it is). ``default`` is the value when absent
    (``None``: none, e.g. measured or computed at run time; ``default_text`` says what then);
    ``required`` keys have no default. ``unit`` is the SI unit (``""`` for none). ``also``:
    words a number may be replaced with (``apex_distance = "auto"``). ``bound_note``: what is
    checked besides ``bound`` (a relation to another key, the domain check of another module),
    shown in the docs' bounds column.
    """

    name: str
    kind: str
    meaning: str
    unit: str = ""
    default: Any = None
    required: bool = False
    bound: Bound | None = None
    choices: tuple[str, ...] = ()
    default_text: str | None = None
    also: tuple[str, ...] = ()
    type_label: str | None = None
    bound_note: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"{self.name}: unknown kind {self.kind!r}")
        if self.kind in ("number", "integer") and self.bound is None:
            object.__setattr__(self, "bound", FINITE)

    def parse(self, value: Any) -> Any:
        """The checked value (floats for numbers); raises :class:`ValueError` with a message
        ``… , got VALUE`` naming the bound."""
        got = f"got {show_value(value)}"
        if self.also and isinstance(value, str) and value in self.also:
            return value
        if self.kind in ("number", "integer"):
            integer = self.kind == "integer"
            if isinstance(value, bool) or not isinstance(value, int if integer else int | float):
                what = "an integer" if integer else "a number"
                if self.also:
                    what += " or " + " or ".join(map(json.dumps, self.also))
                raise ValueError(f"expected {what}, {got}")
            x = int(value) if integer else float(value)
            assert self.bound is not None
            why = self.bound.problem(float(x))
            if why is not None:
                raise ValueError(f"{why}, {got}")
            return x
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise ValueError(f"expected one of {', '.join(map(json.dumps, self.choices))}, "
                                 f"{got}")
            return value
        if self.kind == "flag":
            if not isinstance(value, bool):
                raise ValueError(f"expected true or false, {got}")
            return value
        if self.kind == "point":
            if (not isinstance(value, list) or len(value) != 2
                    or not all(isinstance(v, int | float) and not isinstance(v, bool)
                               for v in value)):
                raise ValueError(f"expected a point [x, y] of two numbers, {got}")
            pt = [float(v) for v in value]
            if not all(math.isfinite(v) for v in pt):
                raise ValueError(f"expected finite numbers, {got}")
            return pt
        if self.kind == "other":
            raise TypeError(f"{self.name}: a structured value, parsed by its section")
        if not isinstance(value, str):
            raise ValueError(f"expected a string, {got}")
        return value

    def type_text(self) -> str:
        """The docs' ``type`` column: ``number``, ``integer``, ``"a" \\| "b"``, ``true/false``."""
        if self.type_label is not None:
            return self.type_label
        if self.kind == "point":
            return "`[x, y]`"
        if self.also:
            return " \\| ".join([self.kind, *(f'`"{w}"`' for w in self.also)])
        if self.kind == "choice":
            return " \\| ".join(f'`"{c}"`' for c in self.choices)
        if self.kind == "flag":
            return "true/false"
        return self.kind

    def default_cell(self) -> str:
        if self.required:
            return "required"
        if self.default is None:
            return self.default_text or "none"
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        if isinstance(self.default, str):
            return f'`"{self.default}"`'
        return plain_number(float(self.default))

    def bound_cell(self) -> str:
        note = self.bound_note
        if self.kind not in ("number", "integer") or self.bound is None:
            return note
        b = self.bound
        text = b.text() + (f" ({b.why})" if b.why else "")
        return f"{text}; {note}" if note else text


def markdown_table(keys: Iterable[Key]) -> str:
    """The docs' table of ``keys``: key, type, unit, default, bounds, meaning (one row each)."""
    rows = ["| key | type | unit | default | bounds | meaning |",
            "|---|---|---|---|---|---|"]
    for k in keys:
        rows.append(f"| `{k.name}` | {k.type_text()} | {k.unit or ''} | {k.default_cell()} | "
                    f"{k.bound_cell()} | {k.meaning} |")
    return "\n".join(rows) + "\n"
