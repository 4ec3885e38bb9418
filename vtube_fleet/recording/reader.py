"""Reading a recording back: :func:`load_recording` → :class:`RecordingData`.

Uses ``rerun.chunk.RrdReader``.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.recording.api import RecordingError
from vtube_fleet.recording.layout import (
    E_COMMANDS,
    E_EVENTS,
    E_EXITS,
    E_META,
    E_SUB_TUBES,
    E_SUMMARY,
    E_TRIANGLES,
    E_VEHICLES,
    EXIT_ARCHETYPE,
    META_FORMAT,
    METRICS_PREFIX,
    SAFETY_ARCHETYPE,
    SAFETY_PREFIX,
    STATE_ARCHETYPE,
    TIMELINE_TICK,
    TIMELINE_TIME,
)

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.route import Corridor
    from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = [
    "STAGE_EVENT",
    "RecordingData",
    "load_recording",
]

#: How a run announces its stages in the recording's events (``stage: connecting``).
STAGE_EVENT = "stage: "
#: A stage as a place in the run ("failed at connect").
_STAGE_NAMES = {"connecting": "connect"}

# ----------------------------------------------------------------------------------------------
# reading back
# ----------------------------------------------------------------------------------------------
@dataclass
class RecordingData:
    """A recording read back by :func:`load_recording`.

    ``t_s`` / ``tick`` (T,) are the recorded ticks in order; ``ids`` (M,) every vehicle id seen
    (the scenario's ids first, in their order); ``pos`` / ``vel`` (T, M, 2) with NaN where a
    vehicle was absent; ``cmd`` likewise or ``None``; ``phases`` (T, M) object array or ``None``;
    ``safety`` summary stream suffix → (pos, vel) (T, M, 2) the run's metrics were computed from
    when it said so (see :meth:`Recorder.log_tick`; otherwise review uses ``pos``/``vel``),
    ``safety_ticks`` suffix → (T,) bool: the ticks where the run gave that stream;
    ``metrics`` key → (T,) array at the recorded ticks (NaN where not logged) and
    ``metric_series`` key → (t_s, tick, value) as logged (the simulator logs every step's
    metrics, reduced per recorded frame); ``exits`` vehicle id → exit time;
    ``events`` (t_s, entity path, level, text); ``entity_rows`` entity path → temporal row count
    (static rows counted under ``static_rows``); ``meta`` / ``summary`` the two JSON documents.
    ``scene`` is False for a run that ended before it logged its scene (failed at connect or in
    the preflight, killed before arming): ``meta`` then holds only its ``kind`` (from the
    summary), there is nothing flown to review, :meth:`no_flight` says why.
    """

    path: Path
    meta: dict[str, Any]
    summary: dict[str, Any] | None
    t_s: np.ndarray
    tick: np.ndarray
    ids: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    cmd: np.ndarray | None
    phases: np.ndarray | None
    safety: dict[str, tuple[np.ndarray, np.ndarray]]
    safety_ticks: dict[str, np.ndarray]
    metrics: dict[str, np.ndarray]
    metric_series: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    exits: dict[int, float]
    events: list[tuple[float, str, str, str]]
    entity_rows: dict[str, int]
    static_rows: dict[str, int]
    application_id: str = ""
    recording_id: str = ""
    partitions: list[tuple[float, list[np.ndarray], list[np.ndarray]]] = field(
        default_factory=list)
    scene: bool = True

    @property
    def kind(self) -> str:
        return str(self.meta.get("kind", "?"))

    @property
    def last_stage(self) -> str | None:
        """The last stage the run announced (its ``stage: …`` events), if any."""
        stages = [text[len(STAGE_EVENT):] for _, ent, _, text in self.events
                  if ent == E_EVENTS and text.startswith(STAGE_EVENT)]
        return stages[-1] if stages else None

    def no_flight(self) -> str | None:
        """Why a recording without a scene holds no flight, e.g. ``failed at connect (1 of 1
        vehicles did not connect within …)``: the run's outcome, the stage it ended in and its
        reason; None for a recording with a scene."""
        if self.scene:
            return None
        s = self.summary or {}
        stage = self.last_stage
        where = f" at {_STAGE_NAMES.get(stage, stage)}" if stage else ""
        if not s:
            return f"the recording ends{where or ' before the first stage'} without a summary " \
                   "(the run was killed?)"
        reason = s.get("reason")
        return f"{s.get('outcome') or 'ended'}{where}" + (f" ({reason})" if reason else "")

    def tube(self) -> Trapezoid:
        from vtube_fleet.core.tube import Trapezoid

        t = self.meta["tube"]
        return Trapezoid(np.array(t["p_h0"]), np.array(t["p_h1"]), np.array(t["p_r0"]),
                         np.array(t["p_r1"]))

    def corridor(self) -> Corridor:
        """The recorded route (``meta["route"]``: every segment and junction) with its
        obstacles; a single tube's recording gives a one-segment corridor."""
        from vtube_fleet.core.route import Corridor, Junction, RouteGeometry
        from vtube_fleet.core.tube import Trapezoid

        route = self.meta.get("route")
        if not route:
            return Corridor.single(self.tube(), self.obstacles())
        segs = tuple(Trapezoid(np.array(t["p_h0"]), np.array(t["p_h1"]), np.array(t["p_r0"]),
                               np.array(t["p_r1"]), name=f"S{i + 1}")
                     for i, t in enumerate(route["segments"]))
        juncs = tuple(Junction(i, int(j["waypoint"]), np.array(j["center"], dtype=float),
                               math.radians(float(j["theta_deg"])),
                               tuple(float(x) for x in j["prolong_m"]))
                      for i, j in enumerate(route["junctions"]))
        return Corridor(RouteGeometry(segs, juncs), self.obstacles())

    def obstacles(self) -> tuple[Obstacle, ...]:
        from vtube_fleet.core.tube import Obstacle

        return tuple(Obstacle(center=np.array(o["center"], dtype=float), radius=float(o["radius"]),
                              apex_distance=o.get("apex_distance"))
                     for o in self.meta.get("obstacles", []))


def _list_column(rb: Any, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A list<…> column → (flat values, per-row lengths) or None if absent."""
    import pyarrow as pa

    if name not in rb.schema.names:
        return None
    arr = rb.column(name)
    if isinstance(arr, pa.ChunkedArray):
        arr = arr.combine_chunks()
    lengths = arr.value_lengths().fill_null(0).to_numpy(zero_copy_only=False)
    flat = arr.flatten()
    if pa.types.is_fixed_size_list(flat.type):
        size = flat.type.list_size
        values = flat.flatten().to_numpy(zero_copy_only=False).reshape(-1, size)
    elif pa.types.is_string(flat.type) or pa.types.is_large_string(flat.type):
        values = np.array(flat.to_pylist(), dtype=object)
    else:
        values = flat.to_numpy(zero_copy_only=False)
    return values, lengths.astype(np.int64)


def _components(rb: Any, archetype: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The ``archetype:*`` list columns of a record batch, by component name."""
    out = {}
    for n in rb.schema.names:
        if n.startswith(archetype + ":") and (c := _list_column(rb, n)) is not None:
            out[n.split(":", 1)[1]] = c
    return out


def _index_columns(rb: Any) -> tuple[np.ndarray, np.ndarray]:
    names = rb.schema.names
    n = rb.num_rows
    if TIMELINE_TIME in names:
        t = rb.column(TIMELINE_TIME).cast("int64").to_numpy(zero_copy_only=False) / 1e9
    else:
        t = np.full(n, np.nan)
    if TIMELINE_TICK in names:
        k = rb.column(TIMELINE_TICK).to_numpy(zero_copy_only=False).astype(np.int64)
    else:
        k = np.full(n, -1, dtype=np.int64)
    return t, k


def load_recording(path: str | os.PathLike[str]) -> RecordingData:
    """Read a recording written by :class:`RerunRecorder` (with ``rerun.chunk.RrdReader``).

    Raises :class:`RecordingError` when the file is missing, is not an .rrd, or carries no
    ``meta/scenario`` document of ours.
    """
    from rerun.chunk import RrdReader

    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file")
    if p.is_dir():
        raise RecordingError(f"{p}: is a directory, expected an .rrd file")
    try:
        with warnings.catch_warnings():
            # a file still being written, or cut short, has no footer: readable all the same
            warnings.filterwarnings("ignore", message=".*no footer.*")
            reader = RrdReader(p)
        stores = reader.recordings()
        if not stores:
            raise RecordingError(f"{p}: contains no recording")
        chunks = reader.stream(store=stores[0]).to_chunks()
    except RecordingError:
        raise
    except Exception as exc:  # noqa: BLE001 - rerun raises several types for bad files
        raise RecordingError(f"{p}: not a readable rerun recording ({exc})") from None

    meta_text: str | None = None
    summary_text: str | None = None
    entity_rows: dict[str, int] = {}
    static_rows: dict[str, int] = {}
    veh: list[tuple[np.ndarray, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = []
    cmd_parts: list[tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = []
    safety_parts: dict[str, list[tuple[np.ndarray, dict[str, Any]]]] = {}
    metric_parts: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    exits: dict[int, float] = {}
    events: list[tuple[float, str, str, str]] = []
    parts_sub: dict[int, tuple[float, list[np.ndarray]]] = {}
    parts_tri: dict[int, tuple[float, list[np.ndarray]]] = {}

    def text_of(rb: Any, name: str) -> list[str]:
        col = _list_column(rb, name)
        if col is None:
            return []
        vals, lens = col
        offs = np.concatenate([[0], np.cumsum(lens)])
        return [str(vals[offs[i]]) if lens[i] else "" for i in range(len(lens))]

    def strips_of(rb: Any) -> list[list[np.ndarray]]:
        import pyarrow as pa

        name = "LineStrips2D:strips"
        if name not in rb.schema.names:
            return []
        out = []
        arr = rb.column(name)
        if isinstance(arr, pa.ChunkedArray):
            arr = arr.combine_chunks()
        for row in arr.to_pylist():
            out.append([np.array(s, dtype=float).reshape(-1, 2) for s in (row or [])])
        return out

    for ch in chunks:
        ent = str(ch.entity_path).lstrip("/")
        if ent.startswith("__"):
            continue
        rb = ch.to_record_batch()
        if ch.is_static:
            static_rows[ent] = static_rows.get(ent, 0) + ch.num_rows
            if ent == E_META:
                texts = text_of(rb, "TextDocument:text")
                meta_text = texts[-1] if texts else meta_text
            elif ent == E_SUMMARY:
                texts = text_of(rb, "TextDocument:text")
                summary_text = texts[-1] if texts else summary_text
            continue
        entity_rows[ent] = entity_rows.get(ent, 0) + ch.num_rows
        t, k = _index_columns(rb)
        if ent == E_VEHICLES:
            comps = _components(rb, STATE_ARCHETYPE)
            veh.append((t, k, comps))
        elif ent == E_COMMANDS:
            comps = _components(rb, STATE_ARCHETYPE)
            cmd_parts.append((k, comps))
        elif ent.startswith(SAFETY_PREFIX):
            comps = _components(rb, SAFETY_ARCHETYPE)
            if "suffix" in comps:
                sfx = str(comps["suffix"][0][0]) if len(comps["suffix"][0]) else ""
                safety_parts.setdefault(sfx, []).append((k, comps))
        elif ent.startswith(METRICS_PREFIX):
            col = _list_column(rb, "Scalars:scalars")
            if col is not None:
                vals, lens = col
                offs = np.concatenate([[0], np.cumsum(lens)])
                v = np.array([vals[offs[i]] if lens[i] else np.nan for i in range(len(lens))],
                             dtype=float)
                metric_parts.setdefault(ent[len(METRICS_PREFIX):], []).append((t, k, v))
        elif ent == E_EXITS:
            col = _list_column(rb, f"{EXIT_ARCHETYPE}:vehicle_id")
            if col is not None:
                vals, lens = col
                offs = np.concatenate([[0], np.cumsum(lens)])
                for i in range(len(lens)):
                    for vid in vals[offs[i]:offs[i + 1]]:
                        exits.setdefault(int(vid), float(t[i]))
            for i, txt in enumerate(text_of(rb, "TextLog:text")):
                if txt:  # a fleet's exit is told by its phase change: no text of its own
                    events.append((float(t[i]), ent, "INFO", txt))
        elif ent.startswith(E_EVENTS):
            texts = text_of(rb, "TextLog:text")
            levels = text_of(rb, "TextLog:level") or ["INFO"] * len(texts)
            for i, txt in enumerate(texts):
                events.append((float(t[i]), ent, levels[i] or "INFO", txt))
        elif ent in (E_SUB_TUBES, E_TRIANGLES):
            target = parts_sub if ent == E_SUB_TUBES else parts_tri
            for i, strips in enumerate(strips_of(rb)):
                target[int(k[i])] = (float(t[i]), strips)

    summary = _json_object(summary_text)
    scene = meta_text is not None
    if meta_text is None:
        # a run that ended before its scene (failed at connect, refused in the preflight):
        # ours when it left its summary (an outcome) or announced a stage, with no flight in it
        staged = any(ent == E_EVENTS and text.startswith(STAGE_EVENT)
                     for _, ent, _, text in events)
        if not (staged or (summary is not None and "outcome" in summary)):
            raise RecordingError(f"{p}: not a vtube_fleet recording (no {E_META} document)")
        meta = {"kind": str((summary or {}).get("kind", "?"))}
    else:
        try:
            meta = json.loads(meta_text)
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{p}: {E_META} is not valid JSON ({exc})") from None
        if meta.get("format") != META_FORMAT:
            raise RecordingError(f"{p}: {E_META} has format {meta.get('format')!r}, "
                                 f"expected {META_FORMAT!r}")

    # ---- vehicles: one row per tick ----
    all_k = np.concatenate([k for _, k, _ in veh]) if veh else np.zeros(0, np.int64)
    all_t = np.concatenate([t for t, _, _ in veh]) if veh else np.zeros(0)
    ticks, first = np.unique(all_k, return_index=True)
    t_s = all_t[first]
    seen_ids: list[int] = [int(i) for i in meta.get("ids", [])]
    known = set(seen_ids)
    for _, _, comps in veh + [(None, None, c) for parts in safety_parts.values()
                              for _, c in parts]:
        if "vehicle_id" in comps:
            for i in np.unique(comps["vehicle_id"][0]).tolist():
                if int(i) not in known:
                    known.add(int(i))
                    seen_ids.append(int(i))
    ids = np.array(seen_ids, dtype=np.int64)
    col_of = {int(i): c for c, i in enumerate(seen_ids)}
    T, M = len(ticks), len(ids)

    def scatter(parts: list[tuple[np.ndarray, dict[str, Any]]], names: tuple[str, ...],
                fill: Any = np.nan, dtype: Any = float) -> list[np.ndarray]:
        """Per-row flat components → (T, M) arrays, one per name."""
        out = [np.full((T, M), fill, dtype=dtype) for _ in names]
        for k, comps in parts:
            if "vehicle_id" not in comps or not all(n in comps for n in names):
                continue
            vids, lens = comps["vehicle_id"]
            r = np.searchsorted(ticks, k)
            ok = (r < T) & (ticks[np.minimum(r, max(T - 1, 0))] == k) if T else r < 0
            row = np.repeat(np.where(ok, r, -1), lens)
            colidx = np.array([col_of[int(i)] for i in vids.tolist()], dtype=np.int64)
            keep = row >= 0
            for arr, n in zip(out, names, strict=True):
                arr[row[keep], colidx[keep]] = comps[n][0][keep]
        return out

    def xy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack([a, b], axis=-1)

    vparts = [(k, comps) for _, k, comps in veh]
    x, y, vx, vy = scatter(vparts, ("x_m", "y_m", "vx_m_s", "vy_m_s"))
    pos, vel = xy(x, y), xy(vx, vy)
    phases = None
    if veh and all("phase" in comps for _, _, comps in veh):
        (phases,) = scatter(vparts, ("phase",), fill=None, dtype=object)
    cmd = None
    if cmd_parts:
        cx, cy = scatter(cmd_parts, ("cmd_x_m_s", "cmd_y_m_s"))
        cmd = xy(cx, cy)
    safety: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    safety_ticks: dict[str, np.ndarray] = {}
    for sfx, parts in safety_parts.items():
        sx, sy, svx, svy = scatter(parts, ("x_m", "y_m", "vx_m_s", "vy_m_s"))
        safety[sfx] = (xy(sx, sy), xy(svx, svy))
        logged = np.zeros(T, dtype=bool)
        if T:
            kk = np.concatenate([k for k, _ in parts])
            r = np.searchsorted(ticks, kk)
            ok = (r < T) & (ticks[np.minimum(r, T - 1)] == kk)
            logged[r[ok]] = True
        safety_ticks[sfx] = logged
    metrics: dict[str, np.ndarray] = {}
    metric_series: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for key, parts in metric_parts.items():
        st = np.concatenate([q[0] for q in parts])
        sk = np.concatenate([q[1] for q in parts])
        sv = np.concatenate([q[2] for q in parts])
        order = np.argsort(sk, kind="stable")
        metric_series[key] = (st[order], sk[order], sv[order])
        arr = np.full(T, np.nan)
        for _, k, v in parts:
            r = np.searchsorted(ticks, k)
            ok = (r < T) & (ticks[np.minimum(r, T - 1)] == k) if T else np.zeros(len(k), bool)
            arr[r[ok]] = v[ok]
        metrics[key] = arr
    events.sort(key=lambda e: e[0])
    partitions = []
    for kk in sorted(set(parts_sub) | set(parts_tri)):
        ts = parts_sub.get(kk, parts_tri.get(kk))[0]  # type: ignore[index]
        partitions.append((ts, parts_sub.get(kk, (ts, []))[1], parts_tri.get(kk, (ts, []))[1]))
    return RecordingData(
        path=p, meta=meta, summary=summary, t_s=t_s, tick=ticks, ids=ids, pos=pos, vel=vel,
        cmd=cmd, phases=phases, safety=safety, safety_ticks=safety_ticks, metrics=metrics,
        metric_series=metric_series,
        exits=exits, events=events,
        entity_rows=entity_rows, static_rows=static_rows,
        application_id=str(stores[0].application_id), recording_id=str(stores[0].recording_id),
        partitions=partitions, scene=scene,
    )


def _json_object(text: str | None) -> dict[str, Any] | None:
    """A JSON document that is an object, else None."""
    if not text:
        return None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError:
        return None
    return doc if isinstance(doc, dict) else None
