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
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = [
    "fit_y",
    "pick_snapshot_frames",
    "plot_safety",
    "plot_snapshots",
    "plot_trajectories",
    "safety_figure",
    "trajectory_figure",
]


def _outlines(tube: Trapezoid | Sequence[Trapezoid]) -> list[np.ndarray]:
    """The polygons to draw: one tube's, or every segment's of a route."""
    if isinstance(tube, Trapezoid):
        return [tube.polygon()]
    return [t.polygon() for t in tube]


def _finite(x: Any) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    return np.where(np.isfinite(a), a, np.nan)


def _save(fig: Figure, path: str | os.PathLike[str], dpi: int) -> None:
    FigureCanvasAgg(fig)
    fig.savefig(os.fspath(path), dpi=dpi)


#: :func:`fit_y` draws a positive panel on a log scale when its largest value is more than this
#: many times its median (an end-of-run jump, e.g. the last robots far apart, would otherwise
#: flatten the story near the limits to a line)
LOG_SCALE_RATIO = 5.0


def fit_y(ax: Any, curves: Iterable[Any], limits: Iterable[float] = (), pad: float = 0.06
          ) -> tuple[float, float]:
    """Set the y-limits of ``ax`` to contain every finite value of ``curves`` and every limit,
    with a margin of ``pad`` of the span: a curve is never clipped (matplotlib's autoscaling
    is not relied on). When every value is positive and the largest is more than
    :data:`LOG_SCALE_RATIO` times the curves' median, the axis is logarithmic (ticks 1-2-5),
    so both the part near the limits and the jump stay readable. Returns the limits set."""
    vals = [np.asarray(c, dtype=float).ravel() for c in curves]
    cv = np.concatenate(vals) if vals else np.zeros(0)
    cv = cv[np.isfinite(cv)]
    vals.append(np.asarray(list(limits), dtype=float))
    allv = np.concatenate(vals)
    allv = allv[np.isfinite(allv)]
    if allv.size == 0:
        return ax.get_ylim()
    lo, hi = float(allv.min()), float(allv.max())
    if lo > 0.0 and cv.size and hi > LOG_SCALE_RATIO * float(np.median(cv)):
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        f = (hi / lo) ** pad
        lo, hi = lo / f, hi * f
        ax.set_ylim(lo, hi)
        return lo, hi
    span = hi - lo if hi > lo else max(abs(hi), 1.0)
    lo, hi = lo - pad * span, hi + pad * span
    ax.set_ylim(lo, hi)
    return lo, hi


def plot_safety(path: str | os.PathLike[str], t: np.ndarray,
                metrics: Mapping[str, np.ndarray] | Any, *, dpi: int = 110, **kw: Any) -> None:
    """:func:`safety_figure` saved as a PNG."""
    _save(safety_figure(t, metrics, **kw), path, dpi)


def safety_figure(
    t: np.ndarray,
    metrics: Mapping[str, np.ndarray] | Any,
    *,
    r_s: float,
    v_min: float,
    v_max: float,
    obstacle_radii: Sequence[float] = (),
    title: str | None = None,
    center: Mapping[str, np.ndarray] | Any | None = None,
    pair_search_m: float | None = None,
) -> Figure:
    """Fig. 11 of the paper as one figure with five panels against time ``t`` (K,):

    (a) minimum pair distance with the 2 r_s line, (b) minimum obstacle-centre distance with the
    r_o + r_s line(s), (c)/(d) minimum distance to the main tube's left/right leg with the r_s
    line, (e) minimum and maximum speed with the v_min / v_max lines.

    ``metrics`` is a :class:`~vtube_fleet.core.metrics.StepMetrics` or a mapping with its key names
    (``min_pair_distance_m`` ...). ``center`` optionally adds the same curves for unicycle robot
    centres (dashed) next to the control points. Every panel's y-range holds all of its
    curves and limits (:func:`fit_y`); the limits are dashed red lines, the legends placed
    where they cover the least. ``pair_search_m``: the radius within which the summary
    searched pairs, drawn dotted in (a) when the curve goes above it.
    """

    def get(src: Any, key: str) -> np.ndarray:
        return _finite(src[key] if isinstance(src, Mapping) else getattr(src, key))

    t = np.asarray(t, dtype=float)
    fig = Figure(figsize=(10.0, 11.0), layout="constrained")
    axes = fig.subplots(5, 1, sharex=True)
    limit_style = {"color": "tab:red", "ls": "--", "lw": 1.0}
    curve_style = {"lw": 0.8}

    lim = SafetyLimits(r_s, 0.0, math.inf)
    panels = [
        ("min_pair_distance_m", "(a) min distance\nbetween robots [m]",
         [(lim.pair_m, f"2 r_s = {lim.pair_m:g}")]),
        (
            "min_obstacle_center_distance_m",
            "(b) min distance robot–\nobstacle centre [m]",
            [(lim.obstacle_center_m(r), f"r_o + r_s = {lim.obstacle_center_m(r):g}")
             for r in sorted(set(obstacle_radii))],
        ),
        ("min_left_leg_distance_m", "(c) min distance to\nleft boundary [m]",
         [(lim.leg_m, f"r_s = {lim.leg_m:g}")]),
        ("min_right_leg_distance_m", "(d) min distance to\nright boundary [m]",
         [(lim.leg_m, f"r_s = {lim.leg_m:g}")]),
    ]
    for ax, (key, label, limits) in zip(axes[:4], panels, strict=True):
        y = get(metrics, key)
        curves = [y]
        ax.plot(t, y, color="tab:blue", label="control point" if center is not None else None,
                **curve_style)
        if center is not None:
            yc = get(center, key)
            curves.append(yc)
            ax.plot(t, yc, color="tab:green", ls=":", label="robot centre", **curve_style)
        for value, name in limits:
            ax.axhline(value, label=name, **limit_style)
        if (key == "min_pair_distance_m" and pair_search_m is not None
                and np.nanmax(np.r_[y, -np.inf]) > pair_search_m):
            ax.axhline(pair_search_m, color="0.5", ls=":", lw=0.8,
                       label=f"summary's pair search radius {pair_search_m:.3g}")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        fit_y(ax, curves, [v for v, _ in limits])
        if np.all(np.isnan(y)):
            ax.text(0.5, 0.5, "nothing within range", transform=ax.transAxes,
                    ha="center", va="center", color="0.4")
        if ax.get_legend_handles_labels()[0]:  # beside the panel: it never covers a curve
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)

    ax = axes[4]
    vlo, vhi = get(metrics, "min_speed_m_s"), get(metrics, "max_speed_m_s")
    ax.plot(t, vlo, color="tab:blue", label="min speed", **curve_style)
    ax.plot(t, vhi, color="tab:orange", label="max speed", **curve_style)
    ax.axhline(v_min, label=f"v_min = {v_min:g}", **limit_style)
    ax.axhline(v_max, label=f"v_max = {v_max:g}", **limit_style)
    ax.set_ylabel("(e) speed [m/s]")
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)
    fit_y(ax, [vlo, vhi], [v_min, v_max] if math.isfinite(v_max) else [v_min])
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


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
    tube: Trapezoid | Sequence[Trapezoid],
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

    Each panel shows the main tube (``tube``: or a route's segments, each outlined), the
    sub-tube outlines of the partition, the circumscribed
    triangles I_k (``triangles`` items with ``p_oth``, ``p_otu``, ``p_otd``), the obstacles O_k
    with their extended areas O'_k (dashed, radius r_o + r_s), and every robot with its safety
    disc S_i (red circle of radius r_s, as in the paper's Fig. 10). ``headings`` (one (M,) array
    per frame) draw unicycle headings.
    """
    frames = list(frames)
    n = max(len(frames), 1)
    outlines = _outlines(tube)
    poly = np.concatenate(outlines)
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
        for outline in outlines:
            ax.add_patch(Polygon(outline, closed=True, fill=False, ec="black", lw=1.4))
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


def trajectory_figure(
    tube: Trapezoid | Sequence[Trapezoid],
    t: np.ndarray,
    pos: np.ndarray,
    *,
    ids: Sequence[int] | None = None,
    r_s: float,
    obstacles: Sequence[Obstacle] = (),
    sub_tubes: Sequence[Trapezoid] = (),
    triangles: Sequence[Any] = (),
    title: str | None = None,
) -> Figure:
    """The whole flight in one panel: every vehicle's path (``pos`` (T, M, 2), NaN = absent;
    one colour per vehicle, a dot where it was first seen, a cross where it was last seen)
    over the main tube (or a route's segments), the partition (sub-tube outlines, triangles
    I_k) and the obstacles O_k
    with O'_k. The axes hold the tube and every recorded position: nothing leaves the frame
    (a vehicle flying on past the finishing line, landing elsewhere)."""
    pos = np.asarray(pos, dtype=float).reshape(len(t), -1, 2)
    outlines = _outlines(tube)
    poly = np.concatenate(outlines)
    pts = np.vstack([poly, pos.reshape(-1, 2)])
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = hi - lo
    pad = 0.04 * float(span.max()) + r_s
    aspect = float((span[1] + 2 * pad) / max(span[0] + 2 * pad, 1e-9))
    width = 10.0
    fig = Figure(figsize=(width, max(3.0, min(14.0, width * aspect + 1.2))), layout="constrained")
    ax = fig.subplots()
    for k, outline in enumerate(outlines):
        ax.add_patch(Polygon(outline, closed=True, fill=False, ec="black", lw=1.4,
                             label=None if k else ("tube T" if len(outlines) == 1
                                                   else "route segments")))
    for k, sub in enumerate(sub_tubes):
        ax.add_patch(Polygon(sub.polygon(), closed=True, fill=False, ec="tab:blue", lw=0.6,
                             ls="--", alpha=0.7, label="sub-tubes T_o,k" if k == 0 else None))
    for k, tri in enumerate(triangles):
        ax.add_patch(Polygon(np.stack([tri.p_oth, tri.p_otu, tri.p_otd]), closed=True,
                             fc="tab:orange", ec="tab:orange", alpha=0.18, lw=0.8,
                             label="triangles I_k" if k == 0 else None))
    for k, o in enumerate(obstacles):
        ax.add_patch(Circle(o.center, o.radius, fc="0.35", ec="black", lw=0.6,
                            label="obstacles O_k" if k == 0 else None))
        ax.add_patch(Circle(o.center, o.radius + r_s, fill=False, ec="0.35", ls=":", lw=0.7))
    m = pos.shape[1]
    cmap = _vehicle_colors(m)
    names = list(ids) if ids is not None else list(range(m))
    drawn = 0
    for j in range(m):
        p = pos[:, j]
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            continue
        drawn += 1
        c = cmap[j % len(cmap)]
        ax.plot(p[:, 0], p[:, 1], color=c, lw=0.9, alpha=0.9, gid=f"path {names[j]}")
        first, last = np.flatnonzero(ok)[[0, -1]]
        ax.plot(*p[first], "o", color=c, ms=3)
        ax.plot(*p[last], "x", color=c, ms=4)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (along the tube)")
    ax.set_ylabel("y [m] (left of the heading)")
    t = np.asarray(t, dtype=float)
    when = f", t = {t[0]:.1f}–{t[-1]:.1f} s" if t.size else ""
    ax.set_title(f"{drawn} paths (o first seen, x last seen){when}", fontsize=9)
    ax.grid(alpha=0.2)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    if title:
        fig.suptitle(title)
    return fig


def plot_trajectories(path: str | os.PathLike[str], tube: Trapezoid | Sequence[Trapezoid],
                      t: np.ndarray,
                      pos: np.ndarray, *, dpi: int = 110, **kw: Any) -> None:
    """:func:`trajectory_figure` saved as a PNG."""
    _save(trajectory_figure(tube, t, pos, **kw), path, dpi)


def _vehicle_colors(m: int) -> list[Any]:
    """Distinct colours for ``m`` paths (tab10 up to 10, tab20 up to 20, then a cycle through
    a perceptually even colormap)."""
    from matplotlib import colormaps

    if m <= 10:
        return list(colormaps["tab10"].colors)
    if m <= 20:
        return list(colormaps["tab20"].colors)
    return [colormaps["turbo"](x) for x in np.linspace(0.05, 0.95, m)]
