"""The rerun writer: :class:`RerunRecorder` and :func:`open_recorder`.

A sender thread, batched columns, decimation that keeps the extremes.
"""

from __future__ import annotations

import atexit
import datetime as _dt
import functools
import json
import logging
import math
import os
import queue
import socket
import threading
import time
import uuid
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar
from urllib.parse import urlparse

import numpy as np

from vtube_fleet.artifacts import json_safe
from vtube_fleet.recording.api import NullRecorder, Recorder, RecordingError
from vtube_fleet.recording.layout import (
    DEFAULT_COLOR,
    DEFAULT_CONNECT_URL,
    E_COMMANDS,
    E_EVENTS,
    E_EXITS,
    E_META,
    E_OBSTACLES,
    E_OBSTACLES_EXT,
    E_STATUS,
    E_SUB_TUBES,
    E_SUMMARY,
    E_TRIANGLES,
    E_TUBE,
    E_VEHICLE_EVENTS,
    E_VEHICLES,
    E_VELOCITY,
    EVENT_ARCHETYPE,
    EXIT_ARCHETYPE,
    LIMIT_PERIOD_S,
    LIMITS_PREFIX,
    LOG_LEVELS,
    META_FORMAT,
    META_VERSION,
    METRIC_NAMES,
    METRIC_VIEWS,
    METRICS_PREFIX,
    OTHER_COLOR,
    PHASE_COLORS,
    SAFETY_ARCHETYPE,
    STATE_ARCHETYPE,
    TIMELINE_TICK,
    TIMELINE_TIME,
    stream_entity,
)

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.config.mission import MissionConfig
    from vtube_fleet.config.scenario import Scenario
    from vtube_fleet.core.partition import Partition
    from vtube_fleet.core.tube import Obstacle

_M = TypeVar("_M", bound=Callable[..., Any])

__all__ = [
    "RerunRecorder",
    "default_blueprint",
    "normalize_connect_url",
    "open_recorder",
]

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _phase_str(p: Any) -> str:
    """``Phase.IN_TUBE`` → ``"in_tube"``; plain strings unchanged."""
    return str(getattr(p, "value", p))


def _pt(p: np.ndarray) -> list[float]:
    return [float(p[0]), float(p[1])]


def _circle(center: np.ndarray, radius: float, n: int = 48) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.asarray(center, dtype=float) + radius * np.stack([np.cos(a), np.sin(a)], axis=-1)


def _closed(poly: np.ndarray) -> np.ndarray:
    poly = np.asarray(poly, dtype=float)
    return np.vstack([poly, poly[:1]])


def _present_rows(ids: np.ndarray, pos: Any, vel: Any
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Copies of (ids, pos, vel) restricted to the rows with a finite position."""
    pos = np.asarray(pos, dtype=float)
    vel = np.asarray(vel, dtype=float)
    present = ~np.isnan(pos[:, 0])
    return ids[present], pos[present], vel[present]


def _merge(key: str, old: float, new: float) -> float:
    """Combine two values of one metric over consecutive ticks (decimation keeps extremes)."""
    if math.isnan(old):
        return new
    if math.isnan(new):
        return old
    if key.startswith("min_"):
        return min(old, new)
    if key.startswith("max_") or key in ("tick_duration_s", "link_latency_s"):
        return max(old, new)
    return new


def _offsets(lengths: np.ndarray) -> np.ndarray:
    """Per-row lengths → int32 offsets with the leading 0 (``rerun.ComponentColumn``)."""
    out = np.zeros(len(lengths) + 1, dtype=np.int32)
    np.cumsum(lengths, out=out[1:])
    return out


def _td_ns(t_s: np.ndarray) -> np.ndarray:
    """Seconds → numpy timedelta64[ns] (rerun ``duration`` time column)."""
    return np.round(np.asarray(t_s, dtype=float) * 1e9).astype(np.int64).astype("timedelta64[ns]")


def normalize_connect_url(addr: str | None) -> str:
    """``--rerun-connect`` value → a rerun gRPC URL.

    Accepts a full URL (``rerun+http://host:port/proxy``), ``host:port``, ``:port`` or a bare
    port number; ``None``/empty gives :data:`DEFAULT_CONNECT_URL`.
    """
    if addr is None or not str(addr).strip():
        return DEFAULT_CONNECT_URL
    a = str(addr).strip()
    if "://" in a:
        u = urlparse(a)
        if u.scheme not in ("rerun", "rerun+http", "rerun+https"):
            raise RecordingError(
                f"--rerun-connect {a}: scheme must be rerun://, rerun+http:// or rerun+https://"
            )
        return a if u.path.rstrip("/") == "/proxy" else a.rstrip("/") + "/proxy"
    host, sep, port = a.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", a
    host = host or "127.0.0.1"
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise RecordingError(f"--rerun-connect {a}: expected HOST:PORT, a port or a rerun URL")
    return f"rerun+http://{host}:{int(port)}/proxy"


def _check_writable(path: Path) -> None:
    """Raise :class:`RecordingError` unless ``path`` can be created as a file later (nothing
    is created now: a run that fails before recording leaves no folder behind)."""
    if path.is_dir():
        raise RecordingError(f"--rerun-save {path}: is a directory, expected a file")
    if path.exists():
        if not os.access(path, os.W_OK):
            raise RecordingError(f"--rerun-save {path}: cannot write: permission denied")
        return
    anc = path.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise RecordingError(f"--rerun-save {path}: {anc} is not a directory")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise RecordingError(f"--rerun-save {path}: cannot write in {anc}: permission denied")


def _viewer_reachable(url: str, timeout_s: float) -> bool:
    u = urlparse(url)
    port = u.port or (443 if u.scheme == "rerun+https" else 9876)
    try:
        with socket.create_connection((u.hostname or "127.0.0.1", port), timeout=timeout_s):
            return True
    except OSError:
        return False


def _never_raises(method: _M) -> _M:
    """A public :class:`Recorder` method: a recording problem is logged, never raised into the
    caller's loop (the one place recording errors are swallowed; callers do not guard)."""

    @functools.wraps(method)
    def wrapper(self: RerunRecorder, *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - recording must not kill the control loop
            self._report(exc)
            return None

    return wrapper  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class _Looks:
    """Display data of one (ids, phases) combination, converted to arrow once and reused."""

    labels: Any  # pyarrow StringArray "id phase"
    phases: Any | None  # pyarrow StringArray of phase names, or None
    phase_strs: list[str] | None
    colors: np.ndarray  # (M,) uint32 RGBA


@dataclass
class _Row:
    t_s: float
    tick: int
    ids: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    cmd: np.ndarray | None
    looks: _Looks
    metrics: dict[str, float]
    safety: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# the rerun recorder
# ----------------------------------------------------------------------------------------------
class RerunRecorder:
    """A :class:`Recorder` writing to an .rrd file and/or a live viewer, on its own
    :class:`rerun.RecordingStream`.

    ``decimate`` records every n-th :meth:`log_tick` call (among the calls at least
    ``min_period_s`` of mission time after the previous recorded one, when that is > 0; the
    simulator's command line uses 0.04 s). Recorded ticks are buffered (copies)
    and handed, ``batch_ticks`` at a time or after ``max_delay_s`` of wall time, to a sender
    thread that converts them to arrow and calls :meth:`~rerun.RecordingStream.send_columns`
    once per entity — so the caller's loop only pays for the copy (``background=False`` sends
    from the caller's thread instead). At most ``max_queued_batches`` jobs wait for the
    sender; beyond that ``on_backlog`` decides: ``"block"`` waits for the sender (nothing is
    lost; the default, and the simulator's choice), ``"drop"`` drops ticks with a warning
    rather than stalling the loop (the default for ``kind="fleet"``).
    ``arrow_scale_s`` is the length of a velocity arrow per m/s; the ``status`` table is
    refreshed every ``status_period_s`` of mission time. ``kind`` is ``"sim"`` or ``"fleet"``.
    ``detect_exits=False``: exits only from :meth:`log_exits` (an owner that decides exits
    itself, e.g. from states arriving between ticks, so that review sees exactly its exits).

    The recording is closed — buffer sent, sender joined, stream flushed, file closed — by
    :meth:`close` (idempotent), by the context manager, and at interpreter exit if the owner
    forgot. Recording errors are logged, never raised into the control loop.
    """

    def __init__(
        self,
        save_path: str | os.PathLike[str] | None,
        *,
        connect: str | None = None,
        app_id: str = "vtube_fleet",
        decimate: int = 1,
        min_period_s: float = 0.0,
        kind: str = "sim",
        batch_ticks: int = 16,
        max_delay_s: float = 0.25,
        background: bool = True,
        max_queued_batches: int = 256,
        on_backlog: str | None = None,
        arrow_scale_s: float = 0.5,
        status_period_s: float = 1.0,
        recording_id: str | None = None,
        connect_timeout_s: float = 0.5,
        flush_timeout_s: float = 10.0,
        detect_exits: bool = True,
    ) -> None:
        import pyarrow as pa
        import rerun as rr

        if save_path is None and connect is None:
            raise ValueError("RerunRecorder needs save_path and/or connect (else NullRecorder)")
        if not (isinstance(decimate, int) and decimate >= 1):
            raise RecordingError(f"recording decimation must be an integer >= 1, got {decimate!r}")
        if batch_ticks < 1:
            raise ValueError(f"batch_ticks must be >= 1, got {batch_ticks}")
        self._rr = rr
        self._pa = pa
        self.path = None if save_path is None else Path(save_path)
        self.decimate = decimate
        if not (math.isfinite(min_period_s) and min_period_s >= 0):
            raise RecordingError(f"recording min_period_s must be >= 0, got {min_period_s}")
        self.min_period_s = float(min_period_s)
        self.kind = kind
        self.app_id = app_id
        self.batch_ticks = int(batch_ticks)
        self.max_delay_s = float(max_delay_s)
        self.max_queued_batches = int(max_queued_batches)
        if on_backlog is None:
            on_backlog = "drop" if kind == "fleet" else "block"
        if on_backlog not in ("block", "drop"):
            raise ValueError(f"on_backlog must be 'block' or 'drop', got {on_backlog!r}")
        self.on_backlog = on_backlog
        self.arrow_scale_s = float(arrow_scale_s)
        self.status_period_s = float(status_period_s)
        self.flush_timeout_s = float(flush_timeout_s)
        self.recording_id = recording_id or str(uuid.uuid4())
        self.connect_url: str | None = None
        self.closed = False
        self.dropped_ticks = 0
        self.detect_exits = bool(detect_exits)

        self._lock = threading.RLock()
        self._calls = 0  # log_tick calls
        self._eligible = 0  # calls past the min_period_s gate
        self._next_record_t = -math.inf
        self._recorded = 0  # recorded ticks (sent or queued)
        self._rows: list[_Row] = []
        self._last_send = time.monotonic()
        self._pending: _Row | None = None  # last skipped call, recorded at close
        self._agg: dict[str, float] = {}  # metric extrema since the last recorded tick
        self._looks_key: tuple[bytes, tuple[Any, ...] | None] | None = None
        self._looks: _Looks | None = None
        self._prev_ids: np.ndarray | None = None
        self._prev_present: np.ndarray | None = None
        self._prev_phases: tuple[Any, ...] | None = None
        self._exited: set[int] = set()
        self._last_tick = 0
        self._next_status_t = -math.inf
        self._limits: dict[str, tuple[float, ...]] = {}
        self._next_limit_t = -math.inf
        self._metric_keys_seen: set[str] = set()
        self._send_errors = 0
        self._meta: dict[str, Any] = {}
        self._descriptors: dict[str, Any] = {}
        self._open_block: tuple[int, float, int, dict[str, float]] | None = None
        self._mbuf: list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]] = []
        self._mbuf_n = 0
        self._xbuf: list[tuple[float, int, list[int]]] = []

        if self.path is not None:
            _check_writable(self.path)
        if connect is not None:
            url = normalize_connect_url(connect)
            if _viewer_reachable(url, connect_timeout_s):
                self.connect_url = url
            else:
                where = f"; recording to {self.path} only" if self.path else "; nothing recorded"
                log.warning("no rerun viewer answers at %s%s (start one with `rerun`)", url, where)
        self._enabled = self.path is not None or self.connect_url is not None
        self._background = background
        self._opened = False  # the sinks are opened by the first log call: no empty files
        self._blueprint_sent = False
        self._rec: Any = None
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._qcond = threading.Condition(threading.Lock())
        self._queued = 0  # jobs waiting for the sender
        self._worker: threading.Thread | None = None
        self._atexit = _make_atexit(self)
        atexit.register(self._atexit)

    def _open(self) -> bool:
        """Open the sinks (file, live viewer) and the sender thread on first use; False when
        recording is disabled (no file and no viewer)."""
        if self._opened:
            return self._enabled
        self._opened = True
        if not self._enabled:
            return False
        rr = self._rr
        sinks: list[Any] = []
        if self.connect_url is not None:
            sinks.append(rr.GrpcSink(self.connect_url))
        if self.path is not None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise RecordingError(
                    f"--rerun-save {self.path}: cannot create the folder: {exc.strerror or exc}"
                ) from None
            sinks.append(rr.FileSink(self.path))
        self._rec = rr.RecordingStream(self.app_id, recording_id=self.recording_id)
        self._rec.set_log_time_enabled(False)
        self._rec.set_log_tick_enabled(False)
        self._rec.set_sinks(*sinks)
        self._send_static_defaults()
        if self._background:
            self._worker = threading.Thread(target=self._work, name="rerun-recorder",
                                            daemon=True)
            self._worker.start()
        return True

    def _send_blueprint(self, bounds: tuple[float, float, float, float] | None) -> None:
        self._rec.send_blueprint(default_blueprint(bounds, self.kind), make_active=True,
                                 make_default=True)
        self._blueprint_sent = True

    # ----- sender thread ----------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            self._guard(job)
            with self._qcond:
                self._queued -= 1
                self._qcond.notify_all()

    def _submit(self, job: Any, *, ticks: int = 0) -> bool:
        """Run ``job`` (a rerun call) on the sender thread, or here without one. ``ticks``:
        how many ticks of data the job carries (0: scene, events, exits, summary — never
        dropped). False when the job was dropped or recording is off."""
        if not self._open():
            return False
        if self._worker is None:
            self._guard(job)
            return True
        with self._qcond:
            full = self._queued >= self.max_queued_batches
            if full and self.on_backlog == "block":
                # never lose data: wait for the sender (the simulator's choice)
                self._qcond.wait_for(lambda: self._queued < self.max_queued_batches
                                     or self._worker is None or not self._worker.is_alive(),
                                     timeout=self.flush_timeout_s + 30.0)
                full = self._queued >= self.max_queued_batches
            drop = full and ticks > 0
            if not drop:
                self._queued += 1
                self._qcond.notify_all()
        if drop:
            self.dropped_ticks += ticks
            if self.dropped_ticks == ticks or self.dropped_ticks % 1000 < ticks:
                log.warning("rerun recording falls behind (%d jobs queued): %d ticks dropped "
                            "so far", self.max_queued_batches, self.dropped_ticks)
            return False
        self._queue.put(job)
        return True

    def _report(self, exc: Exception) -> None:
        """A recording problem: counted, the first three logged; never raised (Recorder)."""
        self._send_errors += 1
        if self._send_errors <= 3:
            log.warning("rerun recording: %s: %s", type(exc).__name__, exc)

    def _guard(self, fn: Any) -> None:
        """Run a rerun call (on the sender thread); a problem goes to :meth:`_report`."""
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - recording must not kill the control loop
            self._report(exc)

    # ----- scene ------------------------------------------------------------------------
    def _send_static_defaults(self) -> None:
        rr = self._rr
        for key, name in METRIC_NAMES.items():
            self._rec.log(METRICS_PREFIX + key, rr.SeriesLines(names=[name]), static=True)
        self._rec.log(E_VELOCITY, rr.Arrows2D.from_fields(colors=[0x66BB6AFF]), static=True)
        self._rec.log(E_COMMANDS, rr.Arrows2D.from_fields(colors=[0xBDBDBD90]), static=True)

    @_never_raises
    def log_scene(
        self, scenario: Scenario, partition: Partition | None = None, *,
        mission: MissionConfig | None = None, meta: Mapping[str, Any] | None = None,
    ) -> None:
        rr = self._rr
        tube = scenario.tube
        obstacles = tuple(scenario.obstacles)
        robots = scenario.robots
        params = scenario.controller
        r_s = float(params.r_s)
        doc = self._scene_meta(scenario, mission, meta)
        with self._lock:
            if self.closed or not self._open():
                return
            self._meta = doc
            poly = tube.polygon()
            pad = 0.05 * float(np.ptp(poly, axis=0).max())
            lo, hi = poly.min(axis=0) - pad, poly.max(axis=0) + pad
            self._send_blueprint((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
            # the tube frame has y to the left of the heading: show it y-up
            self._rec.log("world", rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
            self._rec.log(E_META, rr.TextDocument(json.dumps(doc, indent=1),
                                                  media_type=rr.MediaType.TEXT), static=True)
            self._rec.log(E_TUBE, rr.LineStrips2D([_closed(tube.polygon())], colors=[0xE0E0E0FF],
                                                  radii=rr.Radius.ui_points(2.0), draw_order=25.0),
                          static=True)
            # display defaults of the partition outlines (their strips are temporal)
            self._rec.log(E_SUB_TUBES, rr.LineStrips2D.from_fields(
                radii=[rr.Radius.ui_points(0.8)], draw_order=22.0), static=True)
            self._rec.log(E_TRIANGLES, rr.LineStrips2D.from_fields(
                radii=[rr.Radius.ui_points(1.0)], draw_order=23.0), static=True)
            if obstacles:
                centers = np.array([o.center for o in obstacles], dtype=float)
                radii = np.array([o.radius for o in obstacles], dtype=float)
                self._rec.log(E_OBSTACLES, rr.Points2D(centers, radii=radii, colors=[0x616161FF],
                                                       labels=[f"O{i + 1}" for i in
                                                               range(len(obstacles))]),
                              static=True)
                self._rec.log(E_OBSTACLES_EXT, rr.LineStrips2D(
                    [_circle(c, r + r_s) for c, r in zip(centers, radii, strict=True)],
                    colors=[0x616161FF], radii=rr.Radius.ui_points(0.7)), static=True)
            self._rec.log(E_VEHICLES, rr.Points2D.from_fields(radii=[r_s]), static=True)
            self._set_limits(r_s, obstacles, float(robots.v_min), float(robots.v_max))
            if partition is not None:
                self._log_partition_now(partition, t_s=0.0, tick=0)

    def _scene_meta(self, scenario: Scenario, mission_cfg: MissionConfig | None,
                    meta: Mapping[str, Any] | None) -> dict[str, Any]:
        tube = scenario.tube
        robots = scenario.robots
        params = scenario.controller
        sim = scenario.sim
        doc: dict[str, Any] = {
            "format": META_FORMAT,
            "version": META_VERSION,
            "kind": self.kind,
            "app_id": self.app_id,
            "recording_id": self.recording_id,
            "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "source": str(scenario.source),
            "decimate": self.decimate,
            "min_period_s": self.min_period_s,
            "arrow_scale_s": self.arrow_scale_s,
            "tube": {k: _pt(getattr(tube, k)) for k in ("p_h0", "p_h1", "p_r0", "p_r1")},
            "obstacles": [
                {"center": _pt(o.center), "radius": float(o.radius),
                 "apex_distance": None if o.apex_distance is None else float(o.apex_distance)}
                for o in scenario.obstacles
            ],
            "r_s": float(params.r_s),
            "r_a": float(params.r_a),
            "v_min": float(params.v_min),
            "v_max": float(params.v_max),
            "eps_0": float(params.eps_0),
            "robots": int(robots.count),
            "ids": list(range(int(robots.count))),
            "model": str(robots.model),
            "nid_distance": robots.nid_distance,
            "controller": json_safe(params),
            "sim": json_safe(sim) if sim is not None else None,
            "dt_s": float(sim.dt) if sim is not None else None,
        }
        if mission_cfg is not None:
            doc["mission"] = json_safe(mission_cfg)
        if meta:
            doc.update(json_safe(dict(meta)))
        return doc

    def _set_limits(self, r_s: float, obstacles: Sequence[Obstacle], v_min: float,
                    v_max: float) -> None:
        from vtube_fleet.core.metrics import SafetyLimits

        lim = SafetyLimits(r_s, v_min, v_max)
        self._limits = {
            "min_pair_distance_m": (lim.pair_m,),
            "min_left_leg_distance_m": (lim.leg_m,),
            "min_right_leg_distance_m": (lim.leg_m,),
            "min_speed_m_s": (lim.v_min,),
            "max_speed_m_s": (lim.v_max,),
        }
        if obstacles:
            self._limits["min_obstacle_center_distance_m"] = tuple(
                sorted({lim.obstacle_center_m(o.radius) for o in obstacles}))
        for key, values in self._limits.items():
            names = [f"limit {v:g}" for v in values]
            self._rec.log(LIMITS_PREFIX + key, self._rr.SeriesLines(
                colors=[0xE53935FF] * len(values), names=names, widths=[1.0] * len(values)),
                static=True)

    @_never_raises
    def log_partition(self, partition: Any, t_s: float) -> None:
        with self._lock:
            if not self.closed and self._enabled:
                tick = self._last_tick
                self._submit(lambda: self._log_partition_now(partition, t_s=float(t_s),
                                                             tick=tick))

    def _log_partition_now(self, partition: Any, *, t_s: float, tick: int) -> None:
        rr = self._rr
        idx = self._index([t_s], [tick])
        subs = list(getattr(partition, "sub_tubes", ()))
        tris = list(getattr(partition, "triangles", ()))
        strips = [_closed(s.polygon()) for s in subs]
        self._rec.send_columns(E_SUB_TUBES, idx, rr.LineStrips2D.columns(
            strips=strips, labels=[getattr(s, "name", f"T_o{i + 1}") for i, s in enumerate(subs)],
            colors=np.full(len(subs), 0x42A5F580, dtype=np.uint32)).partition([len(subs)]))
        tri_strips = [_closed(np.stack([t.p_oth, t.p_otu, t.p_otd])) for t in tris]
        self._rec.send_columns(E_TRIANGLES, idx, rr.LineStrips2D.columns(
            strips=tri_strips, colors=np.full(len(tris), 0xFB8C00FF, dtype=np.uint32)).partition(
                [len(tris)]))

    # ----- ticks ------------------------------------------------------------------------
    @_never_raises
    def log_tick(
        self,
        *,
        t_s: float,
        tick: int,
        ids: np.ndarray,
        pos: np.ndarray,
        vel: np.ndarray,
        phases: Sequence[Any] | None = None,
        cmd: np.ndarray | None = None,
        metrics: Mapping[str, float] | None = None,
        safety: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        with self._lock:
            if self.closed:
                return
            t_s, tick = float(t_s), int(tick)
            ids = np.asarray(ids)
            pos = np.asarray(pos, dtype=float)
            self._detect_changes(t_s, tick, ids, pos, phases)
            if metrics:
                self._aggregate(metrics)
            self._last_tick = tick
            record = False
            if t_s >= self._next_record_t:  # the time gate (min_period_s), then the count
                record = self._eligible % self.decimate == 0
                self._eligible += 1
                self._next_record_t = t_s + self.min_period_s - 1e-9
            self._calls += 1
            row = self._make_row(t_s, tick, ids, pos, vel, phases, cmd)
            if safety:
                row.safety = {sfx: _present_rows(ids, sp, sv) for sfx, (sp, sv) in safety.items()}
            if record:
                self._pending = None
                self._push(row)
            else:
                self._pending = row

    def _make_row(self, t_s: float, tick: int, ids: np.ndarray, pos: np.ndarray,
                  vel: Any, phases: Sequence[Any] | None, cmd: Any) -> _Row:
        """Copies of the present rows (the caller may reuse its arrays)."""
        vel = np.asarray(vel, dtype=float)
        present = ~np.isnan(pos[:, 0])
        if present.all():
            r_ids, r_pos, r_vel = ids.copy(), pos.copy(), vel.copy()
            r_cmd = None if cmd is None else np.array(cmd, dtype=float)
            r_ph = phases
        else:
            r_ids, r_pos, r_vel = ids[present], pos[present], vel[present]
            r_cmd = None if cmd is None else np.asarray(cmd, dtype=float)[present]
            r_ph = None if phases is None else [p for p, k in zip(phases, present, strict=True)
                                                if k]
        return _Row(t_s, tick, r_ids, r_pos, r_vel, r_cmd, self._looks_for(r_ids, r_ph), {})

    def _looks_for(self, ids: np.ndarray, phases: Sequence[Any] | None) -> _Looks:
        key = (ids.tobytes(), None if phases is None else tuple(phases))
        if key != self._looks_key or self._looks is None:
            pa = self._pa
            if phases is None:
                labels = [str(i) for i in ids.tolist()]
                looks = _Looks(pa.array(labels, type=pa.string()), None, None,
                               np.full(len(labels), DEFAULT_COLOR, dtype=np.uint32))
            else:
                ph = [_phase_str(p) for p in phases]
                labels = [f"{i} {p}" for i, p in zip(ids.tolist(), ph, strict=True)]
                looks = _Looks(pa.array(labels, type=pa.string()), pa.array(ph, type=pa.string()),
                               ph, np.array([PHASE_COLORS.get(p, OTHER_COLOR) for p in ph],
                                            dtype=np.uint32))
            self._looks_key, self._looks = key, looks
        return self._looks

    def _aggregate(self, metrics: Mapping[str, float]) -> None:
        agg = self._agg
        for k, v in metrics.items():
            old = agg.get(k)
            agg[k] = float(v) if old is None else _merge(k, old, float(v))

    def _push(self, row: _Row) -> None:
        row.metrics, self._agg = self._agg, {}
        self._rows.append(row)
        self._recorded += 1
        if row.t_s >= self._next_status_t:
            self._next_status_t = row.t_s + self.status_period_s
            self._submit(lambda: self._send_status(row))
        self._maybe_send()

    def _maybe_send(self) -> None:
        if (len(self._rows) >= self.batch_ticks or self._mbuf_n >= 16 * self.batch_ticks
                or time.monotonic() - self._last_send >= self.max_delay_s):
            self._send_rows()

    def _send_rows(self) -> None:
        """Hand the buffered ticks, metric series and exits to the sender as one job."""
        rows, self._rows = self._rows, []
        mbuf, self._mbuf, self._mbuf_n = self._mbuf, [], 0
        xbuf, self._xbuf = self._xbuf, []
        self._last_send = time.monotonic()
        if not (rows or mbuf or xbuf):
            return

        def job() -> None:
            if rows:
                self._send_rows_now(rows)
            if mbuf:
                self._send_metric_chunks(mbuf)
            if xbuf:
                self._send_exits(xbuf)

        if not self._submit(job, ticks=len(rows) + sum(len(m[0]) for m in mbuf)) and xbuf:
            self._submit(lambda: self._send_exits(xbuf))  # exits are never dropped

    def _detect_changes(self, t_s: float, tick: int, ids: np.ndarray, pos: np.ndarray,
                        phases: Sequence[Any] | None) -> None:
        """Phase changes (→ ``events/vehicles``) and exits (→ ``events/exits``), every call."""
        gone: list[int] = []
        if phases is not None:
            ph = tuple(phases)
            if ph != self._prev_phases or not np.array_equal(ids, self._prev_ids):
                prev = {}
                if self._prev_phases is not None and self._prev_ids is not None:
                    prev = dict(zip(self._prev_ids.tolist(), self._prev_phases, strict=True))
                changed_ids, texts = [], []
                for i, p in zip(ids.tolist(), ph, strict=True):
                    q = prev.get(i)
                    if q != p:
                        ps = _phase_str(p)
                        changed_ids.append(i)
                        texts.append(f"vehicle {i}: {_phase_str(q)} → {ps}" if q is not None
                                     else f"vehicle {i}: {ps}")
                        if ps == "exited":
                            gone.append(i)
                if texts:
                    self._submit(lambda: self._send_vehicle_events(t_s, tick, changed_ids, texts,
                                                                   ["INFO"] * len(texts)))
                self._prev_phases = ph
                self._prev_ids = ids.copy()
        else:
            present = ~np.isnan(pos[:, 0])
            pids, pprev = self._prev_ids, self._prev_present
            if pids is not None and pprev is not None:
                if np.array_equal(ids, pids):
                    left = pprev & ~present
                    if left.any():
                        gone = [int(i) for i in ids[left]]
                else:
                    now = set(ids[present].tolist())
                    gone = [int(i) for i in pids[pprev].tolist() if int(i) not in now]
            if pids is None or not np.array_equal(ids, pids):
                self._prev_ids = ids.copy()
            self._prev_present = present
        gone = [i for i in gone if i not in self._exited] if self.detect_exits else []
        if gone:
            self._exited.update(gone)
            self._xbuf.append((t_s, tick, gone))

    # ----- sending (sender thread) ------------------------------------------------------
    def _index(self, t_s: Sequence[float] | np.ndarray, ticks: Sequence[int] | np.ndarray
               ) -> list[Any]:
        rr = self._rr
        return [rr.TimeColumn(TIMELINE_TIME, duration=_td_ns(np.asarray(t_s, dtype=float))),
                rr.TimeColumn(TIMELINE_TICK, sequence=np.asarray(ticks, dtype=np.int64))]

    def _custom(self, archetype: str, name: str, values: Any, offsets: np.ndarray) -> Any:
        """A column of our own component ``archetype:name``; ``offsets`` (int32, leading 0)
        split the values into rows (see :func:`_offsets`)."""
        from rerun.any_value import AnyBatchValue

        key = f"{archetype}:{name}"
        desc = self._descriptors.get(key)
        if desc is None:
            desc = self._descriptors[key] = self._rr.ComponentDescriptor(key, archetype=archetype)
        arr = values if isinstance(values, self._pa.Array) else self._pa.array(values)
        return self._rr.ComponentColumn(desc, AnyBatchValue(desc, arr), offsets=offsets)

    def _send_exits(self, exits: list[tuple[float, int, list[int]]]) -> None:
        rr = self._rr
        texts = [("vehicle " if len(g) == 1 else "vehicles ") + ", ".join(map(str, g)) + " exited"
                 for _, _, g in exits]
        ids = np.array([i for _, _, g in exits for i in g], dtype=np.int64)
        self._rec.send_columns(
            E_EXITS, self._index([e[0] for e in exits], [e[1] for e in exits]), [
                *rr.TextLog.columns(text=texts, level=["INFO"] * len(exits)),
                self._custom(EXIT_ARCHETYPE, "vehicle_id", ids,
                             _offsets(np.array([len(g) for _, _, g in exits], np.int32)))])

    def _send_vehicle_events(self, t_s: float, tick: int, vids: list[int], texts: list[str],
                             levels: list[str]) -> None:
        n = len(texts)
        rr = self._rr
        self._rec.send_columns(E_VEHICLE_EVENTS, self._index([t_s] * n, [tick] * n), [
            *rr.TextLog.columns(text=texts, level=levels),
            self._custom(EVENT_ARCHETYPE, "vehicle_id", np.asarray(vids, np.int64),
                         _offsets(np.ones(n, np.int32)))])

    def _send_rows_now(self, rows: list[_Row]) -> None:
        rr, pa = self._rr, self._pa
        comps = rr.components
        t = np.array([r.t_s for r in rows])
        ticks = np.array([r.tick for r in rows], dtype=np.int64)
        idx = self._index(t, ticks)
        lengths = np.array([len(r.ids) for r in rows], dtype=np.int32)
        offsets = _offsets(lengths)
        pos = np.concatenate([r.pos for r in rows]).reshape(-1, 2)
        vel = np.concatenate([r.vel for r in rows]).reshape(-1, 2)
        ids = np.concatenate([r.ids for r in rows]).astype(np.int64)
        labels = pa.concat_arrays([r.looks.labels for r in rows])
        colors = np.concatenate([r.looks.colors for r in rows])

        def col(desc: Any, batch: Any, offs: np.ndarray = offsets) -> Any:
            return rr.ComponentColumn(desc, batch, offsets=offs)

        from rerun.any_value import AnyBatchValue

        lab_desc = rr.Points2D.descriptor_labels()
        pos32 = pos.astype(np.float32)
        cols = [
            col(rr.Points2D.descriptor_positions(), comps.Position2DBatch(pos32)),
            col(lab_desc, AnyBatchValue(lab_desc, labels)),
            col(rr.Points2D.descriptor_colors(), comps.ColorBatch(colors)),
            self._custom(STATE_ARCHETYPE, "vehicle_id", ids, offsets),
            self._custom(STATE_ARCHETYPE, "x_m", pos[:, 0], offsets),
            self._custom(STATE_ARCHETYPE, "y_m", pos[:, 1], offsets),
            self._custom(STATE_ARCHETYPE, "vx_m_s", vel[:, 0], offsets),
            self._custom(STATE_ARCHETYPE, "vy_m_s", vel[:, 1], offsets),
        ]
        if all(r.looks.phases is not None for r in rows):
            cols.append(self._custom(STATE_ARCHETYPE, "phase", pa.concat_arrays(
                [r.looks.phases for r in rows]), offsets))
        self._rec.send_columns(E_VEHICLES, idx, cols)
        self._rec.send_columns(E_VELOCITY, idx, [
            col(rr.Arrows2D.descriptor_origins(), comps.Position2DBatch(pos32)),
            col(rr.Arrows2D.descriptor_vectors(),
                comps.Vector2DBatch((vel * self.arrow_scale_s).astype(np.float32))),
        ])
        streams: dict[str, None] = {}
        for r in rows:
            streams.update(dict.fromkeys(r.safety))
        for sfx in streams:
            sel = [k for k, r in enumerate(rows) if sfx in r.safety]
            parts = [rows[k].safety[sfx] for k in sel]
            s_offs = _offsets(np.array([len(q[0]) for q in parts], dtype=np.int32))
            s_pos = np.concatenate([q[1] for q in parts]).reshape(-1, 2)
            s_vel = np.concatenate([q[2] for q in parts]).reshape(-1, 2)
            self._rec.send_columns(
                stream_entity(sfx),
                idx if len(sel) == len(rows) else self._index(t[sel], ticks[sel]), [
                    self._custom(SAFETY_ARCHETYPE, "suffix", [sfx] * len(sel), _offsets(
                        np.ones(len(sel), np.int32))),
                    self._custom(SAFETY_ARCHETYPE, "vehicle_id", np.concatenate(
                        [q[0] for q in parts]).astype(np.int64), s_offs),
                    self._custom(SAFETY_ARCHETYPE, "x_m", s_pos[:, 0], s_offs),
                    self._custom(SAFETY_ARCHETYPE, "y_m", s_pos[:, 1], s_offs),
                    self._custom(SAFETY_ARCHETYPE, "vx_m_s", s_vel[:, 0], s_offs),
                    self._custom(SAFETY_ARCHETYPE, "vy_m_s", s_vel[:, 1], s_offs),
                ])
        with_cmd = [k for k, r in enumerate(rows) if r.cmd is not None]
        if with_cmd:
            sub = [rows[k] for k in with_cmd]
            cl = _offsets(lengths[with_cmd])
            cpos = np.concatenate([r.pos for r in sub]).reshape(-1, 2)
            cmd = np.concatenate([r.cmd for r in sub if r.cmd is not None]).reshape(-1, 2)
            self._rec.send_columns(E_COMMANDS, self._index(t[with_cmd], ticks[with_cmd]), [
                col(rr.Arrows2D.descriptor_origins(), comps.Position2DBatch(
                    cpos.astype(np.float32)), cl),
                col(rr.Arrows2D.descriptor_vectors(), comps.Vector2DBatch(
                    (cmd * self.arrow_scale_s).astype(np.float32)), cl),
                self._custom(STATE_ARCHETYPE, "vehicle_id", np.concatenate(
                    [r.ids for r in sub]).astype(np.int64), cl),
                self._custom(STATE_ARCHETYPE, "cmd_x_m_s", cmd[:, 0], cl),
                self._custom(STATE_ARCHETYPE, "cmd_y_m_s", cmd[:, 1], cl),
            ])
        keys: dict[str, None] = {}
        for r in rows:
            keys.update(dict.fromkeys(r.metrics))
        for key in keys:
            sel = [k for k, r in enumerate(rows) if key in r.metrics]
            vals = np.array([rows[k].metrics[key] for k in sel], dtype=float)
            vals[~np.isfinite(vals)] = np.nan  # no pair in range etc.: a gap in the plot
            self._rec.send_columns(
                METRICS_PREFIX + key,
                idx if len(sel) == len(rows) else self._index(t[sel], ticks[sel]),
                [rr.ComponentColumn(rr.Scalars.descriptor_scalars(), comps.ScalarBatch(vals))])
        new_keys = keys.keys() - self._metric_keys_seen
        self._metric_keys_seen.update(keys)
        self._send_limits(t, ticks, new_keys, due=t[-1] >= self._next_limit_t or self.closed)

    def _send_limits(self, t: np.ndarray, ticks: np.ndarray, new_keys: Any, *, due: bool
                     ) -> None:
        """The safety limits as flat lines: a point at the first tick of each metric, then
        one every LIMIT_PERIOD_S of mission time and at the last batch (close)."""
        rr = self._rr
        last = len(t) - 1
        for key, values in self._limits.items():
            if key in new_keys or (due and key in self._metric_keys_seen):
                at = [0] if key in new_keys and not due else [0, last] if key in new_keys \
                    else [last]
                at = sorted(set(at))
                vals = np.tile(np.asarray(values, dtype=float), len(at))
                self._rec.send_columns(
                    LIMITS_PREFIX + key, self._index(t[at], ticks[at]),
                    [rr.ComponentColumn(rr.Scalars.descriptor_scalars(),
                                        rr.components.ScalarBatch(vals),
                                        lengths=[len(values)] * len(at))])
        if due:
            self._next_limit_t = t[last] + LIMIT_PERIOD_S

    def _send_status(self, row: _Row) -> None:
        speed = np.hypot(row.vel[:, 0], row.vel[:, 1]) if len(row.vel) else np.zeros(0)
        phases = row.looks.phase_strs or ["-"] * len(row.ids)
        lines = [f"t = {row.t_s:.2f} s, tick {row.tick}, {len(row.ids)} vehicles present", "",
                 "| id | phase | x [m] | y [m] | speed [m/s] |", "|---:|---|---:|---:|---:|"]
        lines += [f"| {i} | {p} | {x:.2f} | {y:.2f} | {s:.2f} |"
                  for i, p, (x, y), s in zip(row.ids.tolist(), phases, row.pos.tolist(),
                                             speed.tolist(), strict=True)]
        rr = self._rr
        self._rec.send_columns(
            E_STATUS, self._index([row.t_s], [row.tick]),
            rr.TextDocument.columns(text=["\n".join(lines)], media_type=["text/markdown"]))

    # ----- events, summary, close -------------------------------------------------------
    @_never_raises
    def log_metrics(self, t_s: np.ndarray, ticks: np.ndarray,
                    metrics: Mapping[str, np.ndarray], *, every: int = 1) -> None:
        """Per-step metric series (K,) in bulk, e.g. a simulator's chunk of steps.

        With ``every`` > 1 the steps are grouped by ``tick // every`` and each group is
        logged once, at its first tick, with its extreme (``min_*`` → min, ``max_*``,
        ``tick_duration_s``, ``link_latency_s`` → max, others → last), also when a group spans
        several calls (the open group is kept until a later tick or :meth:`close`). ±inf
        become NaN (a gap in the plot).
        """
        t = np.asarray(t_s, dtype=float).reshape(-1)
        k = np.asarray(ticks, dtype=np.int64).reshape(-1)
        if t.size == 0:
            return
        every = max(1, int(every))
        with self._lock:
            if self.closed or not self._enabled:
                return
            self._last_tick = max(self._last_tick, int(k[-1]))
            block = k // every
            starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
            ends = np.r_[starts[1:], k.size]
            out: dict[str, np.ndarray] = {}
            for key, vals in metrics.items():
                v = np.asarray(vals, dtype=float).reshape(-1)
                if key.startswith("min_"):
                    out[key] = np.fmin.reduceat(v, starts)
                elif key.startswith("max_") or key in ("tick_duration_s", "link_latency_s"):
                    out[key] = np.fmax.reduceat(v, starts)
                else:
                    out[key] = v[ends - 1]
            tt, kk, bb = t[starts], k[starts], block[starts]
            # merge with the group left open by the previous call
            op = self._open_block
            if op is not None and op[0] == bb[0]:
                tt[0], kk[0] = op[1], op[2]
                for key, v in out.items():
                    if key in op[3]:
                        v[0] = _merge(key, op[3][key], float(v[0]))
            elif op is not None:
                self._emit_metric_block(op)
            # the last group may continue in the next call
            self._open_block = (int(bb[-1]), float(tt[-1]), int(kk[-1]),
                                {key: float(v[-1]) for key, v in out.items()})
            if len(tt) > 1:
                self._mbuf.append((tt[:-1].copy(), kk[:-1].copy(),
                                   {key: v[:-1] for key, v in out.items()}))
                self._mbuf_n += len(tt) - 1
            self._maybe_send()

    def _emit_metric_block(self, op: tuple[int, float, int, dict[str, float]]) -> None:
        self._mbuf.append((np.array([op[1]]), np.array([op[2]], dtype=np.int64),
                           {key: np.array([v]) for key, v in op[3].items()}))
        self._mbuf_n += 1

    def _send_metric_chunks(self, chunks: list[tuple[np.ndarray, np.ndarray,
                                                     dict[str, np.ndarray]]]) -> None:
        """Buffered :meth:`log_metrics` blocks → one send per metric key."""
        keys: dict[str, None] = {}
        for _, _, ser in chunks:
            keys.update(dict.fromkeys(ser))
        if all(c[2].keys() == keys.keys() for c in chunks):
            t = np.concatenate([c[0] for c in chunks])
            k = np.concatenate([c[1] for c in chunks])
            self._send_metric_series(t, k, {key: np.concatenate([c[2][key] for c in chunks])
                                            for key in keys})
            return
        for c in chunks:  # differing key sets: rare, send chunk by chunk
            self._send_metric_series(c[0], c[1], c[2])

    def _send_metric_series(self, t: np.ndarray, k: np.ndarray,
                            series: Mapping[str, np.ndarray]) -> None:
        rr = self._rr
        idx = self._index(t, k)
        for key, vals in series.items():
            vals = np.where(np.isfinite(vals), vals, np.nan)
            self._rec.send_columns(METRICS_PREFIX + key, idx, [
                rr.ComponentColumn(rr.Scalars.descriptor_scalars(),
                                   rr.components.ScalarBatch(vals))])
        new_keys = series.keys() - self._metric_keys_seen
        self._metric_keys_seen.update(series)
        self._send_limits(t, k, new_keys, due=t[-1] >= self._next_limit_t)

    @_never_raises
    def log_exits(self, t_s: float, tick: int, ids: Sequence[int] | np.ndarray) -> None:
        """Explicit exits (the simulator knows the exact step); vehicles already reported
        exited are ignored, and the automatic detection will not report them again."""
        with self._lock:
            if self.closed:
                return
            gone = [int(i) for i in np.asarray(ids).reshape(-1).tolist() if int(i) not in
                    self._exited]
            if gone:
                self._exited.update(gone)
                t_s, tick = float(t_s), int(tick)
                self._xbuf.append((t_s, tick, gone))
                self._maybe_send()

    @_never_raises
    def log_event(
        self, t_s: float, text: str, *, vehicle_id: int | None = None, level: str = "info"
    ) -> None:
        with self._lock:
            if self.closed:
                return
            lvl = LOG_LEVELS.get(level.lower(), level.upper())
            t_s, tick, text = float(t_s), self._last_tick, str(text)
            if vehicle_id is None:
                rr = self._rr
                self._submit(lambda: self._rec.send_columns(
                    E_EVENTS, self._index([t_s], [tick]),
                    rr.TextLog.columns(text=[text], level=[lvl])))
            else:
                vid = int(vehicle_id)
                self._submit(lambda: self._send_vehicle_events(
                    t_s, tick, [vid], [f"vehicle {vid}: {text}"], [lvl]))

    @_never_raises
    def log_summary(self, summary: Mapping[str, Any]) -> None:
        rr = self._rr
        with self._lock:
            if self.closed:
                return
            text = json.dumps(json_safe(dict(summary)), indent=1)
            self._submit(lambda: self._rec.log(
                E_SUMMARY, rr.TextDocument(text, media_type=rr.MediaType.TEXT), static=True))

    @property
    def recorded_ticks(self) -> int:
        """Ticks recorded so far (including the final pending one once closed)."""
        return self._recorded

    @property
    def calls(self) -> int:
        """:meth:`log_tick` calls so far."""
        return self._calls

    @_never_raises
    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                atexit.unregister(self._atexit)
            except Exception:  # noqa: BLE001 - best effort at interpreter exit
                pass
            buffered = bool(self._rows or self._pending or self._mbuf or self._xbuf
                            or self._open_block)
            if not self._enabled or not (self._opened or buffered):
                log.info("rerun recording: nothing was logged, no recording written")
                return
            self._open()
            try:
                if not self._blueprint_sent:
                    self._guard(lambda: self._send_blueprint(None))
                if self._open_block is not None:
                    op, self._open_block = self._open_block, None
                    self._emit_metric_block(op)
                if self._pending is not None:
                    row, self._pending = self._pending, None
                    self._push(row)
                self._send_rows()
            finally:
                worker = self._worker
        if worker is not None:  # outside the lock: the sender takes it per job
            self._queue.put(None)
            worker.join(timeout=self.flush_timeout_s + 30.0)
            if worker.is_alive():
                log.warning("rerun recording: the sender did not finish within %.0f s",
                            self.flush_timeout_s + 30.0)
        try:
            try:
                self._rec.flush(timeout_sec=self.flush_timeout_s)
            except Exception as exc:  # noqa: BLE001 - e.g. live viewer went away
                log.warning("rerun recording: flush: %s", exc)
        finally:
            try:
                self._rec.disconnect()
            except Exception as exc:  # noqa: BLE001
                log.warning("rerun recording: close: %s", exc)
        if self.dropped_ticks:
            log.warning("rerun recording: %d ticks were dropped (sender fell behind)",
                        self.dropped_ticks)
        if self.path is not None:
            size = self.path.stat().st_size if self.path.exists() else 0
            log.info("recording saved: %s (%d ticks recorded of %d, %.1f kB)", self.path,
                     self._recorded, self._calls, size / 1e3)

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        where = [str(self.path)] if self.path else []
        if self.connect_url:
            where.append(self.connect_url)
        return f"RerunRecorder({', '.join(where)}, decimate={self.decimate})"


def _make_atexit(rec: RerunRecorder) -> Any:
    ref = weakref.ref(rec)

    def _close_at_exit() -> None:
        r = ref()
        if r is not None and not r.closed:
            r.close()

    return _close_at_exit


# ----------------------------------------------------------------------------------------------
# blueprint
# ----------------------------------------------------------------------------------------------
def default_blueprint(bounds: tuple[float, float, float, float] | None = None,
                      kind: str = "fleet") -> Any:
    """The default layout: the 2-D tube view (y up, framed on ``bounds`` = (x0, y0, x1, y1)
    when given) with the status table and the event log under it, the time series (Fig. 11
    quantities, and for ``kind="fleet"`` tick duration and link latency) on the right."""
    import rerun.blueprint as rrb

    series = []
    for name, keys in METRIC_VIEWS:
        if kind == "sim" and keys[0] in ("tick_duration_s", "link_latency_s"):
            continue
        contents = [f"/{METRICS_PREFIX}{k}" for k in keys] + [f"/{LIMITS_PREFIX}{k}" for k in keys]
        series.append(rrb.TimeSeriesView(origin="/", contents=contents, name=name))
    known = [k for _, keys in METRIC_VIEWS for k in keys]
    series.append(rrb.TimeSeriesView(
        origin="/metrics", name="other metrics",
        contents=["$origin/**"] + [f"- /{METRICS_PREFIX}{k}" for k in known]))
    view_kw: dict[str, Any] = {}
    if bounds is not None:
        x0, y0, x1, y1 = bounds
        # the view looks at "/", where "world" is mirrored (y up): its y range is negated
        view_kw["visual_bounds"] = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])
    tube_view = rrb.Spatial2DView(origin="/", contents=["/world/**"], name="tube", **view_kw)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                tube_view,
                rrb.Tabs(
                    rrb.TextDocumentView(origin=f"/{E_STATUS}", name="status"),
                    rrb.TextLogView(origin=f"/{E_EVENTS}", name="events"),
                ),
                row_shares=[3, 2],
            ),
            rrb.Grid(*series, grid_columns=2),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE_TIME),
        collapse_panels=False,
    )


# ----------------------------------------------------------------------------------------------
# factory and CLI glue
# ----------------------------------------------------------------------------------------------
def open_recorder(
    save_path: str | os.PathLike[str] | None,
    *,
    connect: str | None = None,
    app_id: str = "vtube_fleet",
    decimate: int = 1,
    kind: str = "sim",
    **options: Any,
) -> Recorder:
    """A :class:`RerunRecorder`, or a :class:`NullRecorder` when both targets are ``None``."""
    if save_path is None and connect is None:
        return NullRecorder()
    return RerunRecorder(save_path, connect=connect, app_id=app_id, decimate=decimate,
                         kind=kind, **options)
