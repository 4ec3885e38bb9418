"""How the core writes numbers into its error messages (one format for every message)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.tube import Obstacle

__all__ = ["compact_number", "obstacle_label", "plain_number", "point_text"]


def compact_number(x: float, nd: int = 3) -> str:
    """At most ``nd`` decimals, at least one: 4.0, 0.9, 1.654; ``inf`` / ``nan`` as such."""
    if not math.isfinite(x):
        return str(x)
    s = f"{x:.{nd}f}".rstrip("0")
    s = s + "0" if s.endswith(".") else s
    return "0.0" if s == "-0.0" else s


def plain_number(x: float) -> str:
    """A bound or default as written in a message or a docs table: 50, 0.5, 1.5 (no trailing
    zeros, unlike :func:`compact_number`'s 50.0); beyond 1e6 in :func:`compact_number`."""
    if float(x).is_integer():
        return str(int(x))
    return f"{x:g}" if abs(x) < 1e6 else compact_number(x)


def point_text(p: np.ndarray) -> str:
    """A 2-D point as ``(x, y)`` in :func:`compact_number` format."""
    return f"({compact_number(float(p[0]))}, {compact_number(float(p[1]))})"


def obstacle_label(i: int, ob: Obstacle) -> str:
    """``obstacle #k at (x, y) r_o=r``: how every message names obstacle ``i`` (0-based)."""
    return f"obstacle #{i + 1} at {point_text(ob.center)} r_o={compact_number(float(ob.radius))}"
