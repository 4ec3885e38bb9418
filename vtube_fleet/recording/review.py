"""Reviewing a recorded run.

Read the recording back, recompute its summary with the same metrics the run used, compare
with the run's own, draw the figures.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from vtube_fleet.recording.api import RecordingError
from vtube_fleet.recording.reader import RecordingData, load_recording

__all__ = [
    "ReviewResult",
    "best_known",
    "compare_summaries",
    "full_pair_curve",
    "recorded_every",
    "review",
    "step_metrics",
    "summary_from_recording",
    "write_review_plots",
]

#: Keys whose values come from positions/velocities/exits (recomputed by review).
_CHUNK_STEPS = 256


@dataclass
class ReviewResult:
    """What :func:`review` produced: ``summary`` holds the best figures the recording knows
    (:func:`best_known`), ``from_frames`` the recomputed keys from the recorded frames alone
    (:func:`summary_from_recording`; its ``steps`` are the frames judged), ``per_step_keys``
    the keys taken from the per-step series, ``run_keys`` the counts taken from the run's own
    summary because the per-step series confirm them; ``differences`` compares ``summary``
    with the run's own over ``recomputed_keys``."""

    data: RecordingData
    summary: dict[str, Any]
    recomputed_keys: tuple[str, ...]
    differences: list[tuple[str, Any, Any]]
    plots: list[Path] = field(default_factory=list)
    from_frames: dict[str, Any] = field(default_factory=dict)
    per_step_keys: tuple[str, ...] = ()
    run_keys: tuple[str, ...] = ()

    @property
    def no_flight(self) -> str | None:
        """Why there is no flight to review (a run that ended before its scene: e.g.
        ``failed at connect (…)``), else None (:meth:`RecordingData.no_flight`)."""
        return self.data.no_flight()

    @property
    def verdict(self) -> Any:
        """:func:`vtube_fleet.core.metrics.verdict` of the recomputed summary (every recorded
        stream but unicycle centres, which the simulator reports beside the control points)."""
        from vtube_fleet.core.metrics import verdict

        streams = ["", "_truth"] if "truth_violations" in self.summary else [""]
        return verdict(self.summary, streams)


def _monitor(data: RecordingData) -> Any:
    from vtube_fleet.core.metrics import SafetyMonitor

    meta = data.meta
    params = SimpleNamespace(r_s=meta["r_s"], r_a=meta["r_a"], v_min=meta["v_min"],
                             v_max=meta["v_max"])
    flown = None
    if meta.get("r_s_flown") is not None and meta.get("r_a_flown") is not None:
        flown = SimpleNamespace(r_s=meta["r_s_flown"], r_a=meta["r_a_flown"])
    if meta.get("route"):
        return SafetyMonitor.for_corridor(data.corridor(), params, flown)
    return SafetyMonitor.for_run(data.tube(), data.obstacles(), params, flown)


def route_segments(data: RecordingData) -> np.ndarray | None:
    """(T, M) the segment each vehicle flew at every recorded tick of a route's recording
    (None for a single tube): the route planned again from the recording's scene (obstacles
    at the apex distances flown, the controller's parameters with the flown radii) and its
    hand-overs replayed on the positions the run's metrics used (``core.route.Route.follow``).
    With a frame for every step this is the run's own assignment."""
    import dataclasses

    from vtube_fleet.core.params import ControllerParams
    from vtube_fleet.core.route import Route

    meta = data.meta
    if not meta.get("route"):
        return None
    cached = getattr(data, "_route_segments", None)
    if cached is not None:
        return cached
    corridor = data.corridor()
    h = meta.get("apex_distances_m") or []
    obs = tuple(dataclasses.replace(o, apex_distance=h[i]) if i < len(h) and h[i] is not None
                else o for i, o in enumerate(corridor.obstacles))
    params = ControllerParams(**meta["controller_params"])
    if meta.get("r_s_flown") is not None and meta.get("r_a_flown") is not None:
        params = dataclasses.replace(params, r_s=meta["r_s_flown"], r_a=meta["r_a_flown"])
    route = Route.plan(corridor.with_obstacles(obs), params,
                       lookahead=data.kind in ("fleet", "mqtt", "agent"))
    pos = data.safety[""][0] if "" in data.safety else data.pos
    seg = route.follow(pos)
    data._route_segments = seg  # type: ignore[attr-defined]
    return seg


def step_metrics(data: RecordingData, suffix: str = "") -> tuple[np.ndarray, Any]:
    """(t_s, :class:`~vtube_fleet.core.metrics.StepMetrics`) of one summary stream: the
    (positions, velocities) the run said its metrics used (``data.safety``, at the ticks where
    it gave them — e.g. the fleet only once in the tube; a fleet recording without them judged
    no tick, so none is recomputed), else the recorded vehicle positions and velocities at every
    recorded tick. A simulation is judged at the frames of the steps it judged, those with a
    per-step metrics row: not its final state (the last frame, after the last step, where the
    robots reaching the line exit and no command is evaluated)."""
    from vtube_fleet.core.metrics import StepMetrics

    pos, vel, rows = _judged(data, suffix)
    pos, vel, t = pos[rows], vel[rows], data.t_s[rows]
    mon = _monitor(data)
    seg = route_segments(data)  # a route: each vehicle's segment at every tick
    if seg is not None:
        seg = seg[rows]  # at the ticks judged
    parts = [mon.evaluate(pos, vel)] if not len(t) else []
    for s in range(0, len(t), _CHUNK_STEPS):
        sl = slice(s, s + _CHUNK_STEPS)
        parts.append(mon.evaluate(pos[sl], vel[sl], segment=None if seg is None else seg[sl]))
    return t, StepMetrics.concatenate(parts)


def _judged(data: RecordingData, suffix: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pos, vel) (T, M, 2) of a stream and the rows (recorded ticks) it is judged at
    (:func:`step_metrics`)."""
    if suffix in data.safety:
        pos, vel = data.safety[suffix]
        rows = np.flatnonzero(data.safety_ticks[suffix])
    elif suffix == "" and data.kind in ("fleet", "mqtt", "agent"):
        # the fleet (run, coordinator, agents) gives its metrics' inputs at every tick it
        # judged (in the tube); none given = no tick judged (e.g. interrupted in the take-off),
        # so none is recomputed either: review judges the same phases the run judged
        pos, vel, rows = data.pos, data.vel, np.zeros(0, dtype=np.int64)
    elif suffix == "":
        pos, vel, rows = data.pos, data.vel, np.arange(len(data.t_s))
    else:
        raise KeyError(suffix)
    if data.kind == "sim" and data.metric_series:
        logged = np.unique(np.concatenate([v[1] for v in data.metric_series.values()]))
        rows = rows[np.isin(data.tick[rows], logged)]
    return pos, vel, rows


def summary_from_recording(data: RecordingData, metrics: Any | None = None
                           ) -> tuple[dict[str, Any], tuple[str, ...]]:
    """The run summary recomputed from the recording → (summary, recomputed keys).

    Uses :class:`~vtube_fleet.core.metrics.SummaryAccumulator` on every summary stream the run
    recorded (``""``, ``"_center"`` …); exits come from the recorded exit events (exact times),
    indexed in the scenario's id order. Keys of the stored run summary that are not recomputed
    are copied over, in the stored summary's key order. ``metrics``: precomputed
    :func:`step_metrics` (t, metrics) of the ``""`` stream.
    """
    from vtube_fleet.core.metrics import SummaryAccumulator, truth_keys

    meta = data.meta
    ids = [int(i) for i in meta.get("ids", [])] or [int(i) for i in data.ids]
    index = {vid: k for k, vid in enumerate(ids)}
    acc = SummaryAccumulator(robots=int(meta.get("robots", len(ids))))
    acc.add(*(step_metrics(data) if metrics is None else metrics))
    for suffix in sorted(data.safety):
        if suffix:
            t, sm = step_metrics(data, suffix)
            acc.add(t, sm, suffix)
    by_time: dict[float, list[int]] = {}
    for vid, t in data.exits.items():
        if vid in index:
            by_time.setdefault(t, []).append(index[vid])
    for t, rows in sorted(by_time.items()):
        acc.add_exits(t, rows)
    fresh = truth_keys(acc.summary())
    recomputed = tuple(fresh)
    stored = data.summary or {}
    if stored:
        out = {k: fresh[k] if k in fresh else v for k, v in stored.items()}
        out.update({k: v for k, v in fresh.items() if k not in out})
    else:
        out = fresh
    return out, recomputed


def _stream_key(suffix: str) -> Any:
    """Summary key naming of a stream (``"_truth"`` keys are ``truth_…``, as the fleet's)."""
    if suffix == "_truth":
        return lambda key: f"truth_{key}"
    return lambda key: f"{key}{suffix}"


def best_known(data: RecordingData, frames: Mapping[str, Any], keys: tuple[str, ...]
               ) -> tuple[dict[str, Any], tuple[str, ...], tuple[str, ...]]:
    """The best figures the recording knows → (summary, per-step keys, run keys).

    ``frames``/``keys``: :func:`summary_from_recording`. Every extreme of
    :data:`~vtube_fleet.core.metrics.METRIC_KEYS` that the run also logged as a per-step
    series (the simulator: every step, reduced per recorded frame to its extreme; the fleet:
    every tick) becomes the extreme of that series (or of the frames, if more extreme). The
    counts are the frames' unless the frames are fewer than the run's steps (a decimated
    recording): then ``steps`` and each stream's ``violations``, ``violations_by_condition``
    and ``first_violation_s`` are the run's own summary's when the per-step series confirm
    them (a condition counted > 0 exactly where a series breaks its limit), else the frames'
    raised to what the series show (at least one step per condition broken, the first
    broken series value's time if earlier)."""
    from vtube_fleet.core.metrics import METRIC_KEYS

    out = dict(frames)
    stored = data.summary or {}
    mon = _monitor(data)
    per_step: list[str] = []
    run: list[str] = []
    fs, rs = frames.get("steps"), stored.get("steps")
    decimated = isinstance(fs, int) and isinstance(rs, int) and fs < rs
    for suffix in ["", *sorted(sfx for sfx in data.safety if sfx)]:
        name = _stream_key(suffix)
        broken: dict[str, bool] = {}
        first = math.inf
        for key in METRIC_KEYS:
            k = name(key)
            series = data.metric_series.get(k)
            if k not in keys or series is None:
                continue
            t, _, v = series
            fin = np.isfinite(v)
            if fin.any():
                ext = float(v[fin].min() if key.startswith("min_") else v[fin].max())
                cur = out.get(k)
                out[k] = ext if cur is None else (min(cur, ext) if key.startswith("min_")
                                                  else max(cur, ext))
                per_step.append(k)
            rule = mon.breaks(key, v)
            if rule is not None:
                cond, bad = rule
                broken[cond] = broken.get(cond, False) or bool(bad.any())
                if bad.any():
                    first = min(first, float(t[np.argmax(bad)]))
        vk, bk, fk = name("violations"), name("violations_by_condition"), name("first_violation_s")
        if not (decimated and broken and vk in keys and isinstance(out.get(bk), dict)):
            continue
        by_run = stored.get(bk)
        if isinstance(by_run, dict) and vk in stored and all(
                (int(by_run.get(c) or 0) > 0) == b for c, b in broken.items()):
            out[vk], out[bk], out[fk] = stored[vk], dict(by_run), stored.get(fk)
            run += [vk, bk, fk]
            continue
        by = dict(out[bk])
        for c, b in broken.items():
            if b and not by.get(c):
                by[c] = 1
        out[bk] = by
        out[vk] = max(int(out[vk] or 0), 1 if any(broken.values()) else 0)
        if math.isfinite(first) and (out.get(fk) is None or first < out[fk]):
            out[fk] = first
    if decimated:
        out["steps"] = rs
        run.append("steps")
    return out, tuple(per_step), tuple(run)


def _close(a: Any, b: Any, rel: float, abs_: float) -> bool:
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rel, abs_) for k in a)
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, int) and isinstance(b, int):
        return a == b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(float(a), float(b), rel_tol=rel, abs_tol=abs_)
    return a == b


def compare_summaries(
    recomputed: Mapping[str, Any], stored: Mapping[str, Any], keys: tuple[str, ...] | None = None,
    *, rel: float = 1e-9, abs_: float = 1e-9
) -> list[tuple[str, Any, Any]]:
    """Keys (of ``keys``, default all of ``recomputed``) whose values differ: counts and
    integers exactly, floats within ``rel``/``abs_`` → [(key, recomputed, stored)]."""
    out = []
    for k in keys if keys is not None else tuple(recomputed):
        if k not in stored:
            continue
        if not _close(recomputed.get(k), stored[k], rel, abs_):
            out.append((k, recomputed.get(k), stored[k]))
    return out


def _reconstruct_partition(data: RecordingData) -> tuple[list[Any], list[Any]]:
    """Sub-tubes (Trapezoid) and triangles (p_oth, p_otu, p_otd) of the first partition."""
    from vtube_fleet.core.tube import Trapezoid

    if not data.partitions:
        return [], []
    _, subs, tris = data.partitions[0]
    sub_tubes = []
    for k, s in enumerate(subs):
        if len(s) >= 4:  # closed strip p_h0, p_h1, p_r1, p_r0, p_h0
            try:
                sub_tubes.append(Trapezoid(s[0], s[1], s[3], s[2], name=f"T_o{k + 1}"))
            except Exception:  # noqa: BLE001 - drawing only: the outline as recorded (the
                # strips are float32: a rotated segment's bases are parallel only to ~1e-7)
                outline = np.asarray(s[:4], dtype=float)
                sub_tubes.append(SimpleNamespace(polygon=lambda o=outline: o))
    triangles = [SimpleNamespace(p_oth=t[0], p_otu=t[1], p_otd=t[2]) for t in tris if len(t) >= 3]
    return sub_tubes, triangles


def write_review_plots(data: RecordingData, out_dir: Path, metrics: Any | None = None,
                       *, stem: str | None = None) -> list[Path]:
    """The Fig. 11 safety curves, the swarm snapshots and the whole flight's paths as PNGs in
    ``out_dir``. The pair-distance curve is drawn for every step (:func:`full_pair_curve`),
    not only where two vehicles came within the summary's pair search radius."""
    from vtube_fleet.plots import (
        pick_snapshot_frames,
        plot_safety,
        plot_snapshots,
        plot_trajectories,
    )

    _require_dir(out_dir)
    stem = stem or data.path.stem
    meta = data.meta
    t, sm = step_metrics(data) if metrics is None else metrics
    title = f"{data.path.name} ({data.kind}, {int(meta.get('robots', len(data.ids)))} robots)"
    safety = out_dir / f"{stem}-safety.png"
    curves = dict(sm.as_dict())
    curves["min_pair_distance_m"] = full_pair_curve(data)
    plot_safety(safety, t, curves, r_s=meta["r_s"], v_min=meta["v_min"], v_max=meta["v_max"],
                obstacle_radii=[o["radius"] for o in meta.get("obstacles", [])], title=title,
                pair_search_m=float(_monitor(data).pair_radius))
    written = [safety]
    # snapshots of what the safety metrics counted (the fleet: vehicles in the tube)
    if "" in data.safety:
        rows = np.flatnonzero(data.safety_ticks[""])
        t_snap, p_snap = data.t_s[rows], data.safety[""][0][rows]
    else:
        t_snap, p_snap = data.t_s, data.pos
    if len(t_snap):
        sub_tubes, triangles = _reconstruct_partition(data)
        frames = pick_snapshot_frames(t_snap, p_snap, count=4)
        snaps = out_dir / f"{stem}-snapshots.png"
        plot_snapshots(snaps, data.corridor().segments,
                       [(float(t_snap[i]), p_snap[i]) for i in frames],
                       r_s=meta["r_s"], obstacles=data.obstacles(), sub_tubes=sub_tubes,
                       triangles=triangles, title=title)
        written.append(snaps)
    if len(data.t_s):  # every recorded position, also before and after the tube
        sub_tubes, triangles = _reconstruct_partition(data)
        paths = out_dir / f"{stem}-trajectories.png"
        plot_trajectories(paths, data.corridor().segments, data.t_s, data.pos,
                          ids=[int(i) for i in data.ids],
                          r_s=meta["r_s"], obstacles=data.obstacles(), sub_tubes=sub_tubes,
                          triangles=triangles, title=title)
        written.append(paths)
    return written


def full_pair_curve(data: RecordingData, suffix: str = "") -> np.ndarray:
    """The minimum pair distance of every step of :func:`step_metrics` ``(data, suffix)`` over
    ALL pairs (the same :class:`~vtube_fleet.core.metrics.SafetyMonitor`, its pair search
    radius widened to the whole flown extent): for the plot only. The summary searches pairs
    within r_s + r_a (every pair that can break 2 r_s is within it), so its per-step series is
    empty (NaN) wherever nobody came that close — a curve clipped at that radius."""
    import dataclasses

    pos, _, rows = _judged(data, suffix)
    pos = pos[rows]
    finite = pos[np.isfinite(pos).all(axis=-1)]
    if finite.shape[0] < 2:
        return np.full(pos.shape[0], np.nan)
    reach = float(np.hypot(*np.ptp(finite, axis=0))) + 1.0
    mon = dataclasses.replace(_monitor(data), pair_radius=reach)
    out = [mon.evaluate(pos[s:s + _CHUNK_STEPS]).min_pair_distance_m
           for s in range(0, pos.shape[0], _CHUNK_STEPS)]
    v = np.concatenate(out) if out else np.zeros(0)
    return np.where(np.isfinite(v), v, np.nan)


def _require_dir(out_dir: Path) -> None:
    """``out_dir`` exists as a writable folder (made if missing), else :class:`RecordingError`."""
    if out_dir.exists() and not out_dir.is_dir():
        raise RecordingError(f"--out {out_dir}: not a folder (the plots are written into it)")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"--out {out_dir}: cannot make the folder: "
                             f"{exc.strerror or exc}") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise RecordingError(f"--out {out_dir}: the folder is not writable")


def review(path: str | Path, *, out_dir: Path | None = None, plots: bool = True) -> ReviewResult:
    """Load a recording, recompute its summary (from the frames, then the best the recording
    knows: :func:`best_known`), compare with the run's own, draw the plots. A bad ``out_dir``
    is refused before the recording is read."""
    if plots and out_dir is not None:
        _require_dir(Path(out_dir))
    data = load_recording(path)
    if not data.scene:  # nothing flown (failed at connect, in the preflight …): nothing to judge
        return ReviewResult(data=data, summary=dict(data.summary or {}), recomputed_keys=(),
                            differences=[])
    for key in ("tube", "r_s", "r_a", "v_min", "v_max"):
        if key not in data.meta:
            raise RecordingError(f"{data.path}: scenario metadata lacks {key!r} "
                                 "(recorded without log_scene?)")
    sm = step_metrics(data)
    frames, keys = summary_from_recording(data, sm)
    summary, per_step, run = best_known(data, frames, keys)
    diffs = compare_summaries(summary, data.summary or {}, keys, rel=1e-9, abs_=1e-9)
    written: list[Path] = []
    if plots:
        written = write_review_plots(data, out_dir or data.path.parent, sm)
    return ReviewResult(data=data, summary=summary, recomputed_keys=keys, differences=diffs,
                        plots=written, from_frames={k: frames[k] for k in keys},
                        per_step_keys=per_step, run_keys=run)


def recorded_every(d: RecordingData) -> int:
    """Steps (ticks) per recorded tick, typically (the median spacing of the recorded ticks)."""
    if len(d.tick) < 2:
        return 1
    return max(1, int(np.median(np.diff(d.tick))))
