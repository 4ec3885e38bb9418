"""PNG figures of a run: the paper's Fig. 11 safety curves and snapshots of the swarm (Fig. 10).

The functions take plain arrays (times, metric series, positions), not a simulator result, so the
simulator, the fleet and ``review`` draw the same figures. They use matplotlib's object API with
the Agg canvas: no pyplot, no global backend switch, safe in threads and headless machines.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = ["pick_snapshot_frames", "plot_safety", "plot_snapshots"]


def _finite(x: Any) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    return np.where(np.isfinite(a), a, np.nan)


def _save(fig: Figure, path: str | os.PathLike[str], dpi: int) -> None:
    FigureCanvasAgg(fig)
    fig.savefig(os.fspath(path), dpi=dpi)


def plot_safety(
    path: str | os.PathLike[str],
    t: np.ndarray,
    metrics: Mapping[str, np.ndarray] | Any,
    *,
    r_s: float,
    v_min: float,
    v_max: float,
    obstacle_radii: Sequence[float] = (),
    title: str | None = None,
    center: Mapping[str, np.ndarray] | Any | None = None,
    dpi: int = 110,
) -> None:
    """Fig. 11 of the paper as one PNG with five panels against time ``t`` (K,):

    (a) minimum pair distance with the 2 r_s line, (b) minimum obstacle-centre distance with the
    r_o + r_s line(s), (c)/(d) minimum distance to the main tube's left/right leg with the r_s
    line, (e) minimum and maximum speed with the v_min / v_max lines.

    ``metrics`` is a :class:`~vtube_fleet.core.metrics.StepMetrics` or a mapping with its key names
    (``min_pair_distance_m`` ...). ``center`` optionally adds the same curves for unicycle robot
    centres (dashed) next to the control points.
    """

    def get(src: Any, key: str) -> np.ndarray:
        return _finite(src[key] if isinstance(src, Mapping) else getattr(src, key))

    t = np.asarray(t, dtype=float)
    fig = Figure(figsize=(8.0, 11.0), layout="constrained")
    axes = fig.subplots(5, 1, sharex=True)
    limit_style = {"color": "tab:red", "ls": "--", "lw": 1.0}
    curve_style = {"lw": 0.8}

    lim = SafetyLimits(r_s, 0.0, math.inf)
    panels = [
        ("min_pair_distance_m", "(a) min distance\nbetween robots [m]", [(lim.pair_m, "2 r_s")]),
        (
            "min_obstacle_center_distance_m",
            "(b) min distance robot–\nobstacle centre [m]",
            [(lim.obstacle_center_m(r), f"r_o + r_s = {lim.obstacle_center_m(r):g}")
             for r in sorted(set(obstacle_radii))],
        ),
        ("min_left_leg_distance_m", "(c) min distance to\nleft boundary [m]",
         [(lim.leg_m, "r_s")]),
        ("min_right_leg_distance_m", "(d) min distance to\nright boundary [m]",
         [(lim.leg_m, "r_s")]),
    ]
    for ax, (key, label, limits) in zip(axes[:4], panels, strict=True):
        y = get(metrics, key)
        ax.plot(t, y, color="tab:blue", label="control point" if center is not None else None,
                **curve_style)
        if center is not None:
            ax.plot(t, get(center, key), color="tab:green", ls=":", label="robot centre",
                    **curve_style)
        for value, name in limits:
            ax.axhline(value, label=name, **limit_style)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if np.all(np.isnan(y)):
            ax.text(0.5, 0.5, "nothing within range", transform=ax.transAxes,
                    ha="center", va="center", color="0.4")
        ax.legend(loc="upper right", fontsize=8)

    ax = axes[4]
    ax.plot(t, get(metrics, "min_speed_m_s"), color="tab:blue", label="min speed", **curve_style)
    ax.plot(t, get(metrics, "max_speed_m_s"), color="tab:orange", label="max speed",
            **curve_style)
    ax.axhline(v_min, label=f"v_min = {v_min:g}", **limit_style)
    ax.axhline(v_max, label=f"v_max = {v_max:g}", color="tab:purple", ls="--", lw=1.0)
    ax.set_ylabel("(e) speed [m/s]")
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, ncols=2)
    if title:
        fig.suptitle(title)
    _save(fig, path, dpi)


def pick_snapshot_frames(t: np.ndarray, pos: np.ndarray, count: int = 4) -> list[int]:
    """``count`` frame indices spread over the part of the run where robots are in the tube:
    the first frame, then up to 85 % of the way to the last frame with a robot left."""
    t = np.asarray(t, dtype=float)
    present = ~np.isnan(np.asarray(pos)[..., 0])
    alive = np.flatnonzero(present.any(axis=1))
    if alive.size == 0 or t.size == 0:
        return [0]
    last = int(alive[-1])
    picks = np.round(np.linspace(0.0, 0.85 * last, max(count, 1))).astype(int)
    return sorted({int(i) for i in picks})


def plot_snapshots(
    path: str | os.PathLike[str],
    tube: Trapezoid,
    frames: Iterable[tuple[float, np.ndarray]],
    *,
    r_s: float,
    obstacles: Sequence[Obstacle] = (),
    sub_tubes: Sequence[Trapezoid] = (),
    triangles: Sequence[Any] = (),
    headings: Sequence[np.ndarray | None] | None = None,
    title: str | None = None,
    dpi: int = 110,
) -> None:
    """Snapshots of the swarm, one panel per ``(t, positions (M, 2))`` frame (NaN = absent).

    Each panel shows the main tube, the sub-tube outlines of the partition, the circumscribed
    triangles I_k (``triangles`` items with ``p_oth``, ``p_otu``, ``p_otd``), the obstacles O_k
    with their extended areas O'_k (dashed, radius r_o + r_s), and every robot with its safety
    disc S_i (red circle of radius r_s, as in the paper's Fig. 10). ``headings`` (one (M,) array
    per frame) draw unicycle headings.
    """
    frames = list(frames)
    n = max(len(frames), 1)
    poly = tube.polygon()
    xmin, ymin = poly.min(axis=0)
    xmax, ymax = poly.max(axis=0)
    span_x, span_y = xmax - xmin, ymax - ymin
    ncols = 1 if n == 1 or span_x >= 3.0 * span_y else 2
    nrows = int(np.ceil(n / ncols))
    panel_w = 9.0 if ncols == 1 else 7.0
    panel_h = max(2.5, panel_w * span_y / max(span_x, 1e-9) + 0.6)
    fig = Figure(figsize=(panel_w * ncols, panel_h * nrows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    pad = 0.04 * max(span_x, span_y)

    for idx, ax in enumerate(axes):
        if idx >= len(frames):
            ax.set_visible(False)
            continue
        t_s, pos = frames[idx]
        pos = np.asarray(pos, dtype=float)
        ax.add_patch(Polygon(poly, closed=True, fill=False, ec="black", lw=1.4))
        for sub in sub_tubes:
            ax.add_patch(Polygon(sub.polygon(), closed=True, fill=False, ec="tab:blue", lw=0.6,
                                 ls="--", alpha=0.7))
        for tri in triangles:
            pts = np.stack([tri.p_oth, tri.p_otu, tri.p_otd])
            ax.add_patch(Polygon(pts, closed=True, fc="tab:orange", ec="tab:orange", alpha=0.18,
                                 lw=0.8))
        for o in obstacles:
            ax.add_patch(Circle(o.center, o.radius, fc="0.35", ec="black", lw=0.6))
            ax.add_patch(Circle(o.center, o.radius + r_s, fill=False, ec="0.35", ls=":", lw=0.7))
        here = ~np.isnan(pos[:, 0])
        p = pos[here]
        if p.size:
            d = np.full(p.shape[0], 2 * r_s)
            ax.add_collection(EllipseCollection(d, d, np.zeros_like(d), units="xy", offsets=p,
                                                offset_transform=ax.transData, facecolors="none",
                                                edgecolors="tab:red", linewidths=0.6))
            ax.plot(p[:, 0], p[:, 1], ".", color="black", ms=1.5)
            if headings is not None and headings[idx] is not None:
                h = np.asarray(headings[idx], dtype=float)[here]
                ax.quiver(p[:, 0], p[:, 1], np.cos(h), np.sin(h), angles="xy", scale_units="xy",
                          scale=1.0 / (1.5 * r_s), width=0.004, color="black")
        ax.set_xlim(xmin - pad, xmax + pad)
        ax.set_ylim(ymin - pad, ymax + pad)
        ax.set_aspect("equal")
        ax.set_title(f"t = {t_s:.2f} s, {int(here.sum())} robots in the tube", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.2)
    if title:
        fig.suptitle(title)
    _save(fig, path, dpi)

