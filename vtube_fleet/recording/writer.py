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
from array import array
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar
from urllib.parse import urlparse

import numpy as np

from vtube_fleet.artifacts import json_safe
from vtube_fleet.recording.api import NullRecorder, Recorder, RecordingError
from vtube_fleet.recording.events import ChangeDetector, merge_metric, phase_str
from vtube_fleet.recording.geo import circle as _circle
from vtube_fleet.recording.geo import closed as _closed
from vtube_fleet.recording.geo import map_layers, map_zoom, to_lat_lon
from vtube_fleet.recording.layout import (
    COMMAND_COLOR,
    DEFAULT_CONNECT_URL,
    E_AXES,
    E_COMMANDS,
    E_EVENTS,
    E_EXITS,
    E_JUNCTIONS,
    E_LEGEND,
    E_MAP,
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
    E_WORLD,
    EVENT_ARCHETYPE,
    EXIT_ARCHETYPE,
    LABELS_MAX_VEHICLES,
    LIMIT_COLOR,
    LIMIT_PERIOD_S,
    LIMITS_PREFIX,
    LOG_LEVELS,
    MAP_POINT_RADIUS_PT,
    META_FORMAT,
    META_VERSION,
    METRIC_COLORS,
    METRIC_VARIANTS,
    METRIC_VIEWS,
    METRICS_PREFIX,
    OBSTACLE_COLOR,
    PATH_COLOR,
    PATH_STEP_S,
    PHASE_CLASSES,
    SAFETY_ARCHETYPE,
    STATE_ARCHETYPE,
    SUB_TUBE_COLOR,
    TIMELINE_TICK,
    TIMELINE_TIME,
    TRAIL_S,
    TRAIL_STEP_S,
    TRIANGLE_COLOR,
    TUBE_COLOR,
    VELOCITY_COLOR,
    class_color,
    class_of,
    metric_name,
    metric_variants,
    stream_entity,
    vehicle_entity,
    vehicle_path_entity,
)
from vtube_fleet.recording.live import (
    DEFAULT_BIND,
    VIEWER_PORT,
    WebViewerServer,
    spawn_viewer,
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
def _pt(p: np.ndarray) -> list[float]:
    return [float(p[0]), float(p[1])]


def _present_rows(ids: np.ndarray, pos: Any, vel: Any
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Copies of (ids, pos, vel) restricted to the rows with a finite position."""
    pos = np.asarray(pos, dtype=float)
    vel = np.asarray(vel, dtype=float)
    present = ~np.isnan(pos[:, 0])
    return ids[present], pos[present], vel[present]


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


def _end_strip(strip: array, xy: tuple[float, float]) -> None:
    """End a path strip (flat x, y pairs) at ``xy`` unless it already ends there."""
    if len(strip) < 2 or (strip[-2], strip[-1]) != xy:
        strip.extend(xy)


@dataclass(frozen=True, eq=False)
class _Looks:
    """Display data of one (ids, phases) combination, converted to arrow once and reused."""

    phases: Any | None  # pyarrow StringArray of phase names, or None
    phase_strs: list[str] | None
    classes: np.ndarray  # (M,) uint16 annotation class ids (layout.PHASE_CLASSES)


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


def _metric_color(key: str) -> int | None:
    """Curve colour of a metric series: its base key's colour, lighter for a variant (robot
    centre, truth); ``None`` (the viewer picks) for unknown keys."""
    if key in METRIC_COLORS:
        return METRIC_COLORS[key]
    for base, _ in metric_variants(key):
        if base in METRIC_COLORS:
            return (METRIC_COLORS[base] & 0xFFFFFF00) | 0x90
    return None


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
    The per-vehicle display entities (``world/vehicles/<id>``) are sent every
    ``display_period_s`` of wall time or ``display_max_ticks`` recorded ticks (what a live
    viewer lags behind at most; each send costs a chunk per vehicle in the file).

    Live viewing (:mod:`vtube_fleet.recording.live`): ``serve_web`` = PORT starts the rerun web
    viewer server (page on PORT, data on PORT + 1, bound to ``serve_bind``; its URL in
    ``self.web.url``; stopped at close), ``viewer`` spawns the native viewer on ``viewer_port``
    (or uses the one listening there; ``self.viewer_url``, ``self.viewer_pid``); each is one
    more sink of the same stream. With a log_scene ``mission`` (a geodetic anchor) the recording
    also has the map (``map/*``, GeoPoints on every vehicle; :mod:`vtube_fleet.recording.geo`).

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
        display_period_s: float = 1.0,
        display_max_ticks: int = 256,
        serve_web: int | None = None,
        serve_bind: str = DEFAULT_BIND,
        viewer: bool = False,
        viewer_port: int = VIEWER_PORT,
    ) -> None:
        import pyarrow as pa
        import rerun as rr

        if save_path is None and connect is None and serve_web is None and not viewer:
            raise ValueError("RerunRecorder needs a file, a viewer address, a web server or a "
                             "viewer to spawn (else NullRecorder)")
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
        self._changes = ChangeDetector(self.detect_exits)  # phase changes and exits
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
        self._xbuf: list[tuple[float, int, list[int], bool]] = []
        # display state (sender thread): vehicles drawn, their trails, per-vehicle statics
        self._has_phases = False
        self._visible: set[int] = set()
        self._trails: dict[int, list[tuple[float, float, float, float, float]]] = {}
        self._trail_next: dict[int, float] = {}
        # whole-flight paths (written at close): per vehicle, strips of x, y pairs
        self._paths: dict[int, list[array]] = {}
        self._path_next: dict[int, float] = {}
        self._path_tail: dict[int, tuple[float, float] | None] = {}  # its latest position
        self._vehicle_static: set[int] = set()
        self._r_s = math.nan
        self._robots = 0
        self._tube_box: tuple[float, float, float, float] | None = None
        self._flown_lo = np.full(2, np.inf)
        self._flown_hi = np.full(2, -np.inf)
        self._extremes: dict[str, tuple[float, float]] = {}  # metric key → (min, max) seen
        # metric key → its curve's shape, a point every SHAPE_STEP_S (where a legend fits)
        self._shapes: dict[str, list[tuple[float, float]]] = {}
        self._styled: set[str] = set()  # metric keys whose legend name / colour were sent
        self._blueprint_state: tuple[Any, ...] | None = None
        self._cmd_styled = False
        self.display_period_s = float(display_period_s)
        self.display_max_ticks = int(display_max_ticks)
        self._disp: list[tuple[np.ndarray, ...]] = []
        self._disp_n = 0
        self._disp_last = time.monotonic()

        if self.path is not None:
            _check_writable(self.path)
        where = f"; recording to {self.path} only" if self.path else "; nothing recorded"
        if connect is not None:
            url = normalize_connect_url(connect)
            if _viewer_reachable(url, connect_timeout_s):
                self.connect_url = url
            else:
                log.warning("no rerun viewer answers at %s%s (start one with `rerun`)", url, where)
        #: ``serve_web``: the web viewer server (a child process; :mod:`.live`), its page URL
        self.web: WebViewerServer | None = None
        if serve_web is not None:
            self.web = WebViewerServer(serve_bind, int(serve_web))
            self.web.start()  # a RecordingError (port in use ...) before anything flies
        #: ``viewer``: the native viewer streamed to, and its process id when we started it
        self.viewer_url: str | None = None
        self.viewer_pid: int | None = None
        if viewer:
            sv = spawn_viewer(viewer_port)
            if sv.url is None:
                log.warning("no rerun viewer could be started: %s%s", sv.problem, where)
            self.viewer_url, self.viewer_pid = sv.url, sv.pid
        self._live_urls = list(dict.fromkeys(
            u for u in (self.connect_url, self.viewer_url,
                        None if self.web is None else self.web.grpc_url) if u is not None))
        self._geo_frame: Any = None  # the mission's TubeFrame once log_scene gave one (the map)
        self._map_zoom: float | None = None
        self._enabled = self.path is not None or bool(self._live_urls)
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
        sinks: list[Any] = [rr.GrpcSink(url) for url in self._live_urls]
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

    def _send_blueprint(self, bounds: tuple[float, float, float, float] | None, *,
                        make_active: bool = True, final: bool = False) -> None:
        """The default blueprint; ``final`` (at close, the sender thread done): with the metric
        keys and extremes the run produced (the sender thread owns them until then)."""
        keys = tuple(sorted(self._metric_keys_seen)) if final else ()
        extremes = dict(self._extremes) if final else {}
        shapes = {k: list(v) for k, v in self._shapes.items()} if final else None
        state = (bounds, keys)
        if self._blueprint_sent and state == self._blueprint_state:
            return
        self._rec.send_blueprint(
            default_blueprint(bounds, self.kind, limits=self._limits, metric_keys=keys or None,
                              extremes=extremes, shapes=shapes,
                              map_view=self._geo_frame is not None, map_zoom=self._map_zoom),
            make_active=make_active, make_default=True)
        self._blueprint_sent = True
        self._blueprint_state = state

    def _send_final_view(self) -> None:
        """At close: frame the view on the tube ∪ the flown extent, and give the metrics that
        appeared their views. Sent only when that differs from the blueprint sent at the start;
        a live viewer keeps the layout it shows (the new one becomes its default)."""
        self._send_paths()
        frame = self._frame()
        if frame is None:
            return
        if frame != self._tube_box:
            self._send_frame_keys(frame)
        self._send_blueprint(self._view_bounds(frame), make_active=not self._live_urls,
                             final=True)

    def _send_paths(self) -> None:
        """Each vehicle's whole flight, one static thin strip per stretch it was present (a
        point every PATH_STEP_S), under ``world/vehicles/<id>/path``."""
        rr = self._rr
        for vid, strips in self._paths.items():
            tail = self._path_tail.get(vid)
            if tail is not None:
                _end_strip(strips[-1], tail)
            pts = [np.frombuffer(a, dtype=np.float64).reshape(-1, 2)
                   for a in strips if len(a) >= 4]
            if pts:
                geo = [] if self._geo_frame is None else [rr.GeoLineStrings(
                    lat_lon=to_lat_lon(self._geo_frame, pts), colors=[PATH_COLOR],
                    radii=[rr.Radius.ui_points(1.0)])]
                self._rec.log(vehicle_path_entity(vid), rr.LineStrips2D(
                    [q.astype(np.float32) for q in pts], colors=[PATH_COLOR],
                    radii=[rr.Radius.ui_points(0.8)], draw_order=28.0), *geo, static=True)

    def _frame(self) -> tuple[float, float, float, float] | None:
        """The region a user should see: the tube ∪ everything flown so far."""
        box = self._tube_box
        if box is None:
            return None
        lo = np.fmin(np.array(box[:2]), self._flown_lo)
        hi = np.fmax(np.array(box[2:]), self._flown_hi)
        if np.isfinite(self._r_s):
            flown = np.isfinite(self._flown_lo).all()
            lo, hi = lo - (self._r_s if flown else 0.0), hi + (self._r_s if flown else 0.0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def _legend_rows(self) -> int:
        n = sum(1 for cid, *_ in PHASE_CLASSES if self._legend_class(cid))
        return 0 if n == 0 else 1 + (n - 1) // 6

    def _legend_class(self, cid: int) -> bool:
        """Which annotation classes the legend lists: the phases (fleet), none for the
        simulator (one colour, no phases)."""
        return self.kind != "sim" and 0 < cid != PHASE_CLASSES[-1][0]

    def _view_bounds(self, frame: tuple[float, float, float, float]
                     ) -> tuple[float, float, float, float]:
        """``frame`` with a margin, the axis key above it and the legend below it."""
        x0, y0, x1, y1 = frame
        span = max(x1 - x0, y1 - y0, 1e-6)
        pad = 0.05 * span
        rows = self._legend_rows()
        return (x0 - pad, y0 - 2.5 * pad, x1 + pad, y1 + pad + rows * 1.2 * pad + (pad if rows
                                                                                     else 0.0))

    def _send_frame_keys(self, frame: tuple[float, float, float, float]) -> None:
        """The axis key (``world/axes``: +x and +y arrows from the frame's top-left corner, so
        the y-down drawing is explicit) and the phase colour legend (``world/legend``: one
        labelled point per phase class, below the frame). Static; re-sent when the frame
        grows."""
        rr = self._rr
        x0, y0, x1, y1 = frame
        span = max(x1 - x0, y1 - y0, 1e-6)
        pad = 0.05 * span
        length = 0.08 * span
        # short arrow labels (rerun centres a label on its arrow: a long one on the vertical
        # arrow at the frame's left edge is cut off), the sentence centred above the frame
        self._rec.log(E_AXES, rr.Arrows2D(
            origins=[[x0, y0 - 1.5 * pad], [x0, y0 - 1.5 * pad]],
            vectors=[[length, 0.0], [0.0, length]], colors=[0xFFFFFFC0, 0xFFFFFFC0],
            labels=["+x", "+y"], radii=rr.Radius.ui_points(1.0), show_labels=True,
            draw_order=40.0),
            rr.Points2D([[0.5 * (x0 + x1), y0 - 1.5 * pad]], radii=rr.Radius.ui_points(0.5),
                        colors=[0xFFFFFFC0], show_labels=True, draw_order=40.0,
                        labels=["x along the tube, y to the left of the heading "
                                "(drawn downwards: the mirror image of the paper's figures)"]),
            static=True)
        classes = [(cid, label) for cid, _, label, _ in PHASE_CLASSES if self._legend_class(cid)]
        if not classes:
            return
        per_row = 6
        step = (x1 - x0) / per_row
        pts = [[x0 + (k % per_row) * step + 0.5 * pad, y1 + 2.0 * pad + (k // per_row) * 1.2 * pad]
               for k in range(len(classes))]
        self._rec.log(E_LEGEND, rr.Points2D(
            pts, class_ids=[c for c, _ in classes], labels=[f"{lab}" for _, lab in classes],
            radii=[0.3 * pad], show_labels=True, draw_order=40.0), static=True)

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
        # one annotation class per phase: the colour of a vehicle's point and trail, and the
        # name the viewer shows for it (hover, selection)
        self._rec.log(E_WORLD, rr.AnnotationContext([
            rr.AnnotationInfo(id=cid, label=label, color=color)
            for cid, _, label, color in PHASE_CLASSES]), static=True)

    def _style_metrics(self, keys: Any) -> None:
        """Legend name and colour of each metric series, sent when the key first appears (no
        empty series for metrics a run never has)."""
        rr = self._rr
        for key in keys:
            if key in self._styled:
                continue
            self._styled.add(key)
            kw: dict[str, Any] = {"names": [metric_name(key)]}
            color = _metric_color(key)
            if color is not None:
                kw["colors"] = [color]
            self._rec.log(METRICS_PREFIX + key, rr.SeriesLines(**kw), static=True)

    def _note_shape(self, key: str, t: np.ndarray, vals: np.ndarray) -> None:
        """Keep the first finite value of every SHAPE_STEP_S bucket of a metric's curve."""
        ok = np.isfinite(vals)
        if not ok.any():
            return
        t, vals = np.asarray(t, dtype=float)[ok], vals[ok]
        bucket = np.floor(t / SHAPE_STEP_S)
        pts = self._shapes.setdefault(key, [])
        last = math.floor(pts[-1][0] / SHAPE_STEP_S) if pts else -math.inf
        first = np.r_[True, bucket[1:] != bucket[:-1]] & (bucket > last)
        pts.extend(zip(t[first].tolist(), vals[first].tolist(), strict=True))

    def _note_extremes(self, key: str, lo: float, hi: float) -> None:
        old = self._extremes.get(key)
        if old is not None:
            lo, hi = min(lo, old[0]), max(hi, old[1])
        self._extremes[key] = (lo, hi)

    @_never_raises
    def log_scene(
        self, scenario: Scenario, partition: Partition | None = None, *,
        mission: MissionConfig | None = None, meta: Mapping[str, Any] | None = None,
    ) -> None:
        rr = self._rr
        corridor = getattr(scenario, "corridor", None)  # (a scenario-like without one: a tube)
        segments = tuple(corridor.segments) if corridor is not None else (scenario.tube,)
        obstacles = tuple(scenario.obstacles)
        robots = scenario.robots
        params = scenario.controller
        r_s = float(params.r_s)
        doc = self._scene_meta(scenario, mission, meta)
        if partition is not None:  # the h_k flown (also the ones "auto" chose, core/plan.py)
            tri_h = {int(t.obstacle): float(t.h) for t in getattr(partition, "triangles", ())}
            doc["apex_distances_m"] = [tri_h.get(i) for i in range(len(obstacles))]
        with self._lock:
            if self.closed or not self._open():
                return
            self._meta = doc
            self._r_s = r_s
            self._robots = int(robots.count)
            poly = np.concatenate([t.polygon() for t in segments])
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            self._tube_box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
            self._set_limits(r_s, obstacles, float(robots.v_min), float(robots.v_max))
            layers = []
            if mission is not None:  # a geodetic anchor: the map (recording/geo.py)
                self._geo_frame = mission.frame
                layers = map_layers(scenario, mission, fence=doc.get("fence", True) is not False)
                self._map_zoom = map_zoom(layers)
            # no transform: the view shows the tube frame as it is (hover and selection read the
            # true x, y); rerun draws 2-D y downwards, which the axis key says in the view
            self._send_frame_keys(self._tube_box)
            self._send_blueprint(self._view_bounds(self._tube_box))
            self._rec.log(E_META, rr.TextDocument(json.dumps(doc, indent=1),
                                                  media_type=rr.MediaType.TEXT), static=True)
            single = len(segments) == 1
            self._rec.log(E_TUBE, rr.LineStrips2D(
                [_closed(t.polygon()) for t in segments], colors=[TUBE_COLOR],
                radii=rr.Radius.ui_points(2.0), draw_order=25.0,
                labels=["tube T"] if single else [f"segment {t.name}" for t in segments]),
                static=True)
            if not single:  # each junction: its mitre line and its waypoint
                geo = corridor.geometry
                strips, labels = [], []
                for jn in geo.junctions:
                    strips.append(np.stack(geo.mitre_corners(jn.index)))
                    labels.append(f"waypoint {jn.waypoint + 1}: {jn.theta_deg:+.1f}°")
                self._rec.log(E_JUNCTIONS, rr.LineStrips2D(
                    strips, colors=[TUBE_COLOR], radii=rr.Radius.ui_points(1.0),
                    draw_order=24.0, labels=labels), static=True)
            # display defaults of the partition outlines (their strips are temporal)
            self._rec.log(E_SUB_TUBES, rr.LineStrips2D.from_fields(
                radii=[rr.Radius.ui_points(0.8)], draw_order=22.0), static=True)
            self._rec.log(E_TRIANGLES, rr.LineStrips2D.from_fields(
                radii=[rr.Radius.ui_points(1.0)], draw_order=23.0), static=True)
            if obstacles:
                centers = np.array([o.center for o in obstacles], dtype=float)
                radii = np.array([o.radius for o in obstacles], dtype=float)
                self._rec.log(E_OBSTACLES, rr.Points2D(centers, radii=radii,
                                                       colors=[OBSTACLE_COLOR],
                                                       labels=[f"O{i + 1}" for i in
                                                               range(len(obstacles))]),
                              static=True)
                self._rec.log(E_OBSTACLES_EXT, rr.LineStrips2D(
                    [_circle(c, r + r_s) for c, r in zip(centers, radii, strict=True)],
                    colors=[OBSTACLE_COLOR], radii=rr.Radius.ui_points(0.7)), static=True)
            for layer in layers:
                self._rec.log(layer.entity, rr.GeoLineStrings(
                    lat_lon=layer.strips,
                    colors=np.full(len(layer.strips), layer.color, dtype=np.uint32),
                    radii=[rr.Radius.ui_points(layer.width_pt)] * len(layer.strips)),
                    static=True)
            if partition is not None:
                self._log_partition_now(partition, t_s=0.0, tick=0)

    def _scene_meta(self, scenario: Scenario, mission_cfg: MissionConfig | None,
                    meta: Mapping[str, Any] | None) -> dict[str, Any]:
        corridor = getattr(scenario, "corridor", None)
        tube = corridor.segments[0] if corridor is not None else scenario.tube
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
                 "apex_distance": (o.apex_distance if o.apex_distance is None
                                   or isinstance(o.apex_distance, str)
                                   else float(o.apex_distance))}
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
        if corridor is not None and corridor.S > 1:  # every segment and junction (review)
            # (the controller's parameters too: review plans the route again to replay its
            # hand-overs; "controller" may be replaced by the law's name below)
            doc["controller_params"] = json_safe(params)
            doc["route"] = {
                "segments": [{k: _pt(getattr(t, k)) for k in ("p_h0", "p_h1", "p_r0", "p_r1")}
                             for t in corridor.segments],
                "junctions": [{"waypoint": j.waypoint, "center": _pt(j.center),
                               "theta_deg": j.theta_deg, "prolong_m": list(j.prolong_m)}
                              for j in corridor.junctions]}
        if mission_cfg is not None:
            doc["mission"] = json_safe(mission_cfg)
        if meta:
            doc.update(json_safe(dict(meta)))
        return doc

    def _set_limits(self, r_s: float, obstacles: Sequence[Obstacle], v_min: float,
                    v_max: float) -> None:
        from vtube_fleet.core.metrics import METRIC_KEYS, SafetyLimits

        lim = SafetyLimits(r_s, v_min, v_max)
        radii = [float(o.radius) for o in obstacles]
        self._limits = {}
        for key in METRIC_KEYS:  # each key's limit from SafetyLimits.limit
            if key == "min_obstacle_center_distance_m":  # a line per obstacle radius
                if radii:
                    self._limits[key] = tuple(sorted({lim.obstacle_center_m(r) for r in radii}))
            elif key == "min_obstacle_clearance_m" and not radii:
                continue
            elif (value := lim.limit(key, radii)) is not None:
                self._limits[key] = (value,)
        what = {"min_pair_distance_m": "2 r_s", "min_left_leg_distance_m": "r_s",
                "min_right_leg_distance_m": "r_s", "min_speed_m_s": "v_min",
                "max_speed_m_s": "v_max", "min_obstacle_center_distance_m": "r_o + r_s",
                "min_obstacle_clearance_m": "r_s"}
        for key, values in self._limits.items():
            unit = "m/s" if key.endswith("_m_s") else "m"
            names = [f"limit {what[key]} = {v:g} {unit}" for v in values]
            self._rec.log(LIMITS_PREFIX + key, self._rr.SeriesLines(
                colors=[LIMIT_COLOR] * len(values), names=names, widths=[1.0] * len(values)),
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
            colors=np.full(len(subs), SUB_TUBE_COLOR, dtype=np.uint32)).partition([len(subs)]))
        tri_strips = [_closed(np.stack([t.p_oth, t.p_otu, t.p_otd])) for t in tris]
        self._rec.send_columns(E_TRIANGLES, idx, rr.LineStrips2D.columns(
            strips=tri_strips, labels=[f"I_{k + 1}" for k in range(len(tris))],
            colors=np.full(len(tris), TRIANGLE_COLOR, dtype=np.uint32)).partition([len(tris)]))

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
                looks = _Looks(None, None, np.full(len(ids), class_of(None), dtype=np.uint16))
            else:
                ph = [phase_str(p) for p in phases]
                looks = _Looks(pa.array(ph, type=pa.string()), ph,
                               np.array([class_of(p) for p in ph], dtype=np.uint16))
                self._has_phases = True
            self._looks_key, self._looks = key, looks
        return self._looks

    def _aggregate(self, metrics: Mapping[str, float]) -> None:
        agg = self._agg
        for k, v in metrics.items():
            old = agg.get(k)
            agg[k] = float(v) if old is None else merge_metric(k, old, float(v))

    def _push(self, row: _Row) -> None:
        row.metrics, self._agg = self._agg, {}
        if len(row.pos):
            self._flown_lo = np.fmin(self._flown_lo, row.pos.min(axis=0))
            self._flown_hi = np.fmax(self._flown_hi, row.pos.max(axis=0))
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
        """Phase changes (→ ``events/vehicles``) and exits (→ ``events/exits``), every call
        (:class:`~vtube_fleet.recording.events.ChangeDetector`)."""
        changes, exits = self._changes.update(ids, pos, phases)
        if changes is not None:
            self._submit(lambda: self._send_vehicle_events(t_s, tick, changes.ids,
                                                           changes.texts, changes.levels))
        if exits is not None:
            self._xbuf.append((t_s, tick, exits.ids, exits.untold))

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

    def _send_exits(self, exits: list[tuple[float, int, list[int], bool]]) -> None:
        """Exit times (the data ``review`` reads) and, unless a phase-change event already
        said so (the fleet: "in_tube → exited"), the text "vehicle(s) … exited"."""
        rr = self._rr
        ids = np.array([i for _, _, g, _ in exits for i in g], dtype=np.int64)
        cols = [self._custom(EXIT_ARCHETYPE, "vehicle_id", ids,
                             _offsets(np.array([len(g) for _, _, g, _ in exits], np.int32)))]
        if any(e[3] for e in exits):
            texts = [("vehicle " if len(g) == 1 else "vehicles ") + ", ".join(map(str, g))
                     + " exited" if say else "" for _, _, g, say in exits]
            cols = [*rr.TextLog.columns(text=texts, level=["INFO"] * len(exits)), *cols]
        self._rec.send_columns(
            E_EXITS, self._index([e[0] for e in exits], [e[1] for e in exits]), cols)

    def _send_vehicle_events(self, t_s: float, tick: int, vids: list[int], texts: list[str],
                             levels: list[str]) -> None:
        n = len(texts)
        rr = self._rr
        self._rec.send_columns(E_VEHICLE_EVENTS, self._index([t_s] * n, [tick] * n), [
            *rr.TextLog.columns(text=texts, level=levels),
            self._custom(EVENT_ARCHETYPE, "vehicle_id", np.asarray(vids, np.int64),
                         _offsets(np.ones(n, np.int32)))])

    def _flush_display(self) -> None:
        """Send the buffered display rows (sender thread, or the closing thread once the
        sender has finished)."""
        buf, self._disp, self._disp_n = self._disp, [], 0
        self._disp_last = time.monotonic()
        if buf:
            self._send_vehicle_display(*(np.concatenate([b[k] for b in buf])
                                         for k in range(7)))

    def _send_vehicle_display(self, t: np.ndarray, ticks: np.ndarray, lengths: np.ndarray,
                              ids: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                              classes: np.ndarray) -> None:
        """``world/vehicles/<id>``: the point (radius r_s, phase class), the velocity arrow and
        the trail (the last TRAIL_S of its path, a point every TRAIL_STEP_S) of each vehicle —
        one send per vehicle and batch, plus one for the trails that changed. A vehicle that
        disappears (exited from the simulator, or left the fleet's rows) is cleared (an empty
        row), so it does not stay drawn at its last position."""
        rr = self._rr
        comps = rr.components
        n_rows = len(t)
        row_of = np.repeat(np.arange(n_rows), lengths)
        order = np.argsort(ids, kind="stable")
        sid = ids[order]
        groups: dict[int, np.ndarray] = {}
        if len(sid):
            starts = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1]])
            for a, b in zip(starts.tolist(), np.r_[starts[1:], len(sid)].tolist(), strict=True):
                groups[int(sid[a])] = order[a:b]
        for vid in self._visible - groups.keys():
            groups[vid] = np.zeros(0, dtype=np.int64)
        pos32 = pos.astype(np.float32)
        vec32 = (vel * self.arrow_scale_s).astype(np.float32)
        show = (self._robots or len(groups)) <= LABELS_MAX_VEHICLES
        # the map: every position of the batch in WGS84, one vectorized conversion
        geo = None if self._geo_frame is None else to_lat_lon(self._geo_frame, [pos])[0]
        for vid, sel in groups.items():
            ent = vehicle_entity(vid)
            if vid not in self._vehicle_static:
                self._vehicle_static.add(vid)
                radius = self._r_s if math.isfinite(self._r_s) else 0.25
                geo_defaults = [] if geo is None else [
                    rr.GeoPoints.from_fields(radii=[rr.Radius.ui_points(MAP_POINT_RADIUS_PT)]),
                    rr.GeoLineStrings.from_fields(radii=[rr.Radius.ui_points(1.5)])]
                self._rec.log(ent, rr.Points2D.from_fields(
                    radii=[radius], labels=[str(vid)], show_labels=show, draw_order=30.0),
                    rr.Arrows2D.from_fields(colors=[VELOCITY_COLOR], draw_order=31.0),
                    rr.LineStrips2D.from_fields(radii=[rr.Radius.ui_points(1.2)],
                                                show_labels=False, draw_order=29.0),
                    *geo_defaults, static=True)
            rows_here = row_of[sel]
            present = np.zeros(n_rows, dtype=bool)
            present[rows_here] = True
            before = np.r_[vid in self._visible, present[:-1]]
            off = ~present & before
            send = present | off
            if present[-1] if n_rows else False:
                self._visible.add(vid)
            else:
                self._visible.discard(vid)
            if not send.any():
                continue
            at = np.flatnonzero(send)
            lens = present[at].astype(np.int32)
            offs = _offsets(lens)
            cols = [
                rr.ComponentColumn(rr.Points2D.descriptor_positions(),
                                   comps.Position2DBatch(pos32[sel]), offsets=offs),
                rr.ComponentColumn(rr.Points2D.descriptor_class_ids(),
                                   comps.ClassIdBatch(classes[sel]), offsets=offs),
                rr.ComponentColumn(rr.Arrows2D.descriptor_origins(),
                                   comps.Position2DBatch(pos32[sel]), offsets=offs),
                rr.ComponentColumn(rr.Arrows2D.descriptor_vectors(),
                                   comps.Vector2DBatch(vec32[sel]), offsets=offs),
            ]
            if geo is not None:  # the same point on the map, coloured by phase
                cols += [rr.ComponentColumn(rr.GeoPoints.descriptor_positions(),
                                            comps.LatLonBatch(geo[sel]), offsets=offs),
                         rr.ComponentColumn(rr.GeoPoints.descriptor_class_ids(),
                                            comps.ClassIdBatch(classes[sel]), offsets=offs)]
            self._rec.send_columns(ent, self._index(t[at], ticks[at]), cols)
            self._send_trail(ent, vid, t, ticks, at, present, pos[sel], classes[sel],
                             None if geo is None else geo[sel])

    def _send_trail(self, ent: str, vid: int, t: np.ndarray, ticks: np.ndarray,
                    at: np.ndarray, present: np.ndarray, p: np.ndarray, cls: np.ndarray,
                    geo: np.ndarray | None = None) -> None:
        """The trail rows of one vehicle in one batch: a new strip whenever a sample is added,
        an empty one where the vehicle disappears; with ``geo`` (the rows' lat, lon) the same
        trail on the map (``GeoLineStrings`` in the phase's colour)."""
        trail = self._trails.setdefault(vid, [])
        nxt = self._trail_next.get(vid, -math.inf)
        path = self._paths.setdefault(vid, [array("d")])
        pnext = self._path_next.get(vid, -math.inf)
        tail = self._path_tail.get(vid)
        rows: list[int] = []
        strips: list[np.ndarray] = []
        geo_strips: list[np.ndarray] = []
        strip_cls: list[int] = []
        lens: list[int] = []
        k = 0
        for r in at.tolist():
            if not present[r]:
                trail.clear()
                nxt = -math.inf
                if tail is not None:  # gone: the stretch ends where it was last seen
                    _end_strip(path[-1], tail)
                    tail = None
                if len(path[-1]):
                    path.append(array("d"))  # the path resumes as a new strip
                rows.append(r)
                lens.append(0)
                continue
            x, y = float(p[k, 0]), float(p[k, 1])
            la, lo = (math.nan, math.nan) if geo is None else (float(geo[k, 0]),
                                                                float(geo[k, 1]))
            c = int(cls[k])
            k += 1
            tr = float(t[r])
            tail = (x, y)
            if tr >= pnext:
                path[-1].extend(tail)
                pnext = tr + PATH_STEP_S
            if tr < nxt:
                continue
            trail.append((tr, x, y, la, lo))
            while trail and trail[0][0] < tr - TRAIL_S:
                trail.pop(0)
            nxt = tr + TRAIL_STEP_S
            if len(trail) >= 2:
                rows.append(r)
                lens.append(1)
                strips.append(np.array([(q[1], q[2]) for q in trail], dtype=np.float32))
                if geo is not None:
                    geo_strips.append(np.array([(q[3], q[4]) for q in trail]))
                strip_cls.append(c)
        self._trail_next[vid] = nxt
        self._path_next[vid] = pnext
        self._path_tail[vid] = tail
        if not rows:
            return
        rr = self._rr
        comps = rr.components
        idx = self._index(t[rows], ticks[rows])
        offs = _offsets(np.asarray(lens, dtype=np.int32))
        cls = np.array(strip_cls, np.uint16)
        cols = [rr.ComponentColumn(rr.LineStrips2D.descriptor_strips(), comps.LineStrip2DBatch(
                    self._strip_array(strips, comps.LineStrip2DBatch)), offsets=offs),
                rr.ComponentColumn(rr.LineStrips2D.descriptor_class_ids(),
                                   comps.ClassIdBatch(cls), offsets=offs)]
        if geo is not None:  # the same trail on the map, in the same send
            cols += [rr.ComponentColumn(rr.GeoLineStrings.descriptor_line_strings(),
                                        comps.GeoLineStringBatch(self._strip_array(
                                            geo_strips, comps.GeoLineStringBatch)), offsets=offs),
                     rr.ComponentColumn(rr.GeoLineStrings.descriptor_colors(), comps.ColorBatch(
                         np.array([class_color(c) for c in strip_cls], dtype=np.uint32)),
                         offsets=offs)]
        self._rec.send_columns(ent, idx, cols)

    def _strip_array(self, strips: Sequence[np.ndarray], batch: Any) -> Any:
        """Polylines → the arrow list array of ``batch``'s type in one go (rerun's own converter
        walks the strips in Python: ~1 ms per call, once per vehicle and batch)."""
        pa = self._pa
        typ = batch._ARROW_DATATYPE
        inner = typ.value_type  # fixed-size list of 2
        flat = np.concatenate([np.asarray(q).reshape(-1, 2) for q in strips]) if strips else \
            np.zeros((0, 2))
        values = pa.FixedSizeListArray.from_arrays(
            pa.array(flat.reshape(-1).astype(inner.value_type.to_pandas_dtype(), copy=False)),
            type=inner)
        offsets = _offsets(np.array([len(q) for q in strips], dtype=np.int32))
        return pa.ListArray.from_arrays(pa.array(offsets), values, type=typ)

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
        classes = np.concatenate([r.looks.classes for r in rows])

        def col(desc: Any, batch: Any, offs: np.ndarray = offsets) -> Any:
            return rr.ComponentColumn(desc, batch, offsets=offs)

        # the exact state of the whole fleet, one row per tick (what review reads) ...
        cols = [
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
        # ... and what the view draws, one entity per vehicle (in longer batches: a chunk per
        # vehicle and send costs ~2 kB in the file)
        self._disp.append((t, ticks, lengths, ids, pos, vel, classes))
        self._disp_n += len(t)
        if (self._disp_n >= self.display_max_ticks
                or time.monotonic() - self._disp_last >= self.display_period_s):
            self._flush_display()
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
        if with_cmd and not self._cmd_styled:
            self._cmd_styled = True
            self._rec.log(E_COMMANDS, rr.Arrows2D.from_fields(colors=[COMMAND_COLOR]),
                          static=True)
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
            if np.isfinite(vals).any():
                self._note_extremes(key, float(np.nanmin(vals)), float(np.nanmax(vals)))
                self._note_shape(key, t[sel], vals)
            self._rec.send_columns(
                METRICS_PREFIX + key,
                idx if len(sel) == len(rows) else self._index(t[sel], ticks[sel]),
                [rr.ComponentColumn(rr.Scalars.descriptor_scalars(), comps.ScalarBatch(vals))])
        new_keys = keys.keys() - self._metric_keys_seen
        self._style_metrics(keys)
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
        phases = row.looks.phase_strs
        lines = [f"t = {row.t_s:.2f} s, tick {row.tick}, {len(row.ids)} vehicles present", ""]
        if phases is None:  # the simulator: no phases, no phase column
            lines += ["| id | x [m] | y [m] | speed [m/s] |", "|---:|---:|---:|---:|"]
            lines += [f"| {i} | {x:.2f} | {y:.2f} | {s:.2f} |"
                      for i, (x, y), s in zip(row.ids.tolist(), row.pos.tolist(),
                                              speed.tolist(), strict=True)]
        else:
            lines += ["| id | phase | x [m] | y [m] | speed [m/s] |", "|---:|---|---:|---:|---:|"]
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
                        v[0] = merge_metric(key, op[3][key], float(v[0]))
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
            if np.isfinite(vals).any():
                self._note_extremes(key, float(np.nanmin(vals)), float(np.nanmax(vals)))
                self._note_shape(key, t, vals)
            self._rec.send_columns(METRICS_PREFIX + key, idx, [
                rr.ComponentColumn(rr.Scalars.descriptor_scalars(),
                                   rr.components.ScalarBatch(vals))])
        new_keys = series.keys() - self._metric_keys_seen
        self._style_metrics(series)
        self._metric_keys_seen.update(series)
        self._send_limits(t, k, new_keys, due=t[-1] >= self._next_limit_t)

    @_never_raises
    def log_exits(self, t_s: float, tick: int, ids: Sequence[int] | np.ndarray) -> None:
        """Explicit exits (the simulator knows the exact step); vehicles already reported
        exited are ignored, and the automatic detection will not report them again."""
        with self._lock:
            if self.closed:
                return
            exits = self._changes.explicit_exits(ids)
            if exits is not None:
                self._xbuf.append((float(t_s), int(tick), exits.ids, exits.untold))
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
                self._changes.announced(vid, text)
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
        try:
            self._close()
        finally:
            if self.web is not None:  # after the flush: the server has had everything
                self.web.stop()

    def _close(self) -> None:
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
        if worker is None or not worker.is_alive():
            self._guard(self._flush_display)
            self._guard(self._send_final_view)
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
        where += self._live_urls
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
def _variants(key: str) -> list[str]:
    return [key] + [pattern.format(key) for pattern, _ in METRIC_VARIANTS]


def _y_range(keys: Sequence[str], limits: Mapping[str, Sequence[float]],
             extremes: Mapping[str, tuple[float, float]]) -> tuple[float, float] | None:
    """The y-range of a safety view: from 0 (or below the lowest value) to well above the
    limit, so the part of the curve near the limit fills the plot and end-of-run jumps (a
    vehicle that leaves the tube) do not squash it; always containing the lowest value (and
    for speeds the highest). None without limits (the viewer picks)."""
    lim = [float(v) for k in keys for v in limits.get(k, ())]
    if not lim:
        return None
    seen = [extremes[v] for k in keys for v in _variants(k) if v in extremes]
    lows = [e[0] for e in seen if math.isfinite(e[0])]
    highs = [e[1] for e in seen if math.isfinite(e[1])]
    lo = min([0.0] + [1.1 * x for x in lows if x < 0])
    if any(k.endswith("_m_s") for k in keys):  # speeds: both bounds matter
        hi = max([1.4 * max(lim)] + [1.1 * x for x in highs])
    else:
        hi = max([4.0 * max(lim)] + [2.0 * x for x in lows])
    return lo, hi


#: The recorder keeps the shape of every metric curve, a point per this many seconds of its time
#: axis, to place each view's legend at close (:func:`_legend_corner`).
SHAPE_STEP_S = 0.5

#: Legend corners in the order of preference when as many points cross them (rerun's names).
LEGEND_CORNERS = ("RightTop", "LeftTop", "RightBottom", "LeftBottom")


def _legend_corner(curves: Sequence[Sequence[tuple[float, float]]], lines: Sequence[float],
                   y_range: tuple[float, float]) -> str:
    """The corner of a time-series view whose box (the outer 35 % of the width, 30 % of the
    height, where a legend sits) the fewest curve points and limit lines cross: values above
    the y-range count at the top (the curve leaves the plot there), below at the bottom."""
    pts = [p for c in curves for p in c]
    if not pts:
        return LEGEND_CORNERS[0]
    t = np.array([p[0] for p in pts])
    y = np.array([p[1] for p in pts])
    t0, t1 = float(t.min()), float(t.max())
    span = t1 - t0 if t1 > t0 else 1.0
    u = (t - t0) / span
    lo, hi = y_range
    v = np.clip((y - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    # a limit line crosses a box over its whole width: as many points as a curve there
    per_line = max(1, len(pts) // max(1, len(curves)))
    lv = [min(max((x - lo) / (hi - lo if hi > lo else 1.0), 0.0), 1.0) for x in lines]
    counts = []
    for name in LEGEND_CORNERS:
        right, top = name.startswith("Right"), name.endswith("Top")
        in_u = u >= 0.65 if right else u <= 0.35
        in_v = v >= 0.7 if top else v <= 0.3
        n = int(np.count_nonzero(in_u & in_v))
        n += per_line * sum(1 for x in lv if (x >= 0.7 if top else x <= 0.3)) * 35 // 100
        counts.append(n)
    return LEGEND_CORNERS[int(np.argmin(counts))]


def default_blueprint(bounds: tuple[float, float, float, float] | None = None,
                      kind: str = "fleet", *,
                      limits: Mapping[str, Sequence[float]] | None = None,
                      metric_keys: Sequence[str] | None = None,
                      extremes: Mapping[str, tuple[float, float]] | None = None,
                      shapes: Mapping[str, Sequence[tuple[float, float]]] | None = None,
                      map_view: bool = False, map_zoom: float | None = None) -> Any:
    """The default layout: the 2-D tube view (origin ``/world``, the tube frame as it is, y
    drawn downwards; framed on ``bounds`` = (x0, y0, x1, y1) when given) with the status table
    and the event log under it, the time series (Fig. 11 quantities with their limits, and for
    ``kind="fleet"`` tick duration and link latency) on the right; the blueprint and selection
    panels collapsed, the time panel (collapsed to its slider) on ``mission_time``; every time
    series shows the whole run on its time axis (either timeline).

    ``limits`` (metric key → limit values) set each safety view's y-range around its limits
    (see :func:`_y_range`, using the ``extremes`` (min, max) seen per key); ``metric_keys``
    (the keys the run logged, None: not known yet): only the views of those keys, and keys that
    no view shows get an "other metrics" view — without any, there is none. ``shapes`` (metric
    key → (t, value) points of its curve, the recorder's at close): each safety view's legend
    goes to the corner its curves and limit lines cross least (:func:`_legend_corner`; without
    shapes: the top right). ``map_view`` (a run with a geodetic anchor): a map (WGS84) of the
    ``map/*`` outlines and the vehicles, between the tube view and the time series, centred on
    everything drawn (rerun's map view follows the data) at zoom ``map_zoom``
    (:func:`~vtube_fleet.recording.geo.map_zoom`; None: rerun's fit, which gives up beyond the
    tiles' deepest zoom); it draws the geometry whether or not map tiles can be fetched."""
    import rerun.blueprint as rrb
    from rerun import TimeRange as rr_range
    from rerun import TimeRangeBoundary as rr_bound

    limits = limits or {}
    extremes = extremes or {}
    # the whole recorded run on the time axis, on either timeline (rerun's default is a window
    # around the time cursor: a narrow one on `tick`, "+0s" as the only label)
    whole = rr_range(start=rr_bound.infinite(), end=rr_bound.infinite())
    series = []
    shown: set[str] = set()
    for name, keys in METRIC_VIEWS:
        if kind == "sim" and keys[0] in ("tick_duration_s", "link_latency_s"):
            continue
        every = [v for k in keys for v in _variants(k)]
        shown.update(every)
        if metric_keys is not None and not set(every) & set(metric_keys):
            continue  # the run never logged it: no empty panel
        lim_keys, lim_seen = [], set()
        for k in keys:  # one limit line per distinct value (left and right leg share r_s)
            vals = tuple(limits.get(k, ()))
            if vals and vals not in lim_seen:
                lim_seen.add(vals)
                lim_keys.append(k)
        contents = ([f"/{METRICS_PREFIX}{k}" for k in every]
                    + [f"/{LIMITS_PREFIX}{k}" for k in lim_keys])
        kw: dict[str, Any] = {}
        rng = _y_range(keys, limits, extremes)
        if rng is not None:
            kw["axis_y"] = rrb.ScalarAxis(range=rng, zoom_lock=False)
        if not lim_keys:
            corner = rrb.Corner2D.LeftTop
        elif shapes and rng is not None:
            curves = [shapes[v] for v in every if v in shapes]
            lines = [v for k in lim_keys for v in limits.get(k, ())]
            corner = getattr(rrb.Corner2D, _legend_corner(curves, lines, rng))
        else:
            corner = rrb.Corner2D.RightTop
        series.append(rrb.TimeSeriesView(origin="/", contents=contents, name=name,
                                         plot_legend=rrb.PlotLegend(corner=corner),
                                         axis_x=rrb.TimeAxis(view_range=whole), **kw))
    other = sorted(k for k in (metric_keys or ()) if k not in shown)
    if other:
        series.append(rrb.TimeSeriesView(
            origin="/", name="other metrics",
            contents=[f"/{METRICS_PREFIX}{k}" for k in other]
            + [f"/{LIMITS_PREFIX}{k}" for k in other if k in limits],
            plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop),
            axis_x=rrb.TimeAxis(view_range=whole)))
    view_kw: dict[str, Any] = {}
    if bounds is not None:
        x0, y0, x1, y1 = bounds
        view_kw["visual_bounds"] = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[y0, y1])
    tube_view = rrb.Spatial2DView(origin=f"/{E_WORLD}", contents=["$origin/**"],
                                  name="tube (x →, y ↓ drawn downwards)", **view_kw)
    left = rrb.Vertical(
        tube_view,
        rrb.Tabs(
            rrb.TextLogView(origin=f"/{E_EVENTS}", name="events"),
            rrb.TextDocumentView(origin=f"/{E_STATUS}", name="status"),
        ),
        row_shares=[3, 1],
    )
    columns: list[Any] = [left]
    if map_view:
        # the map's outlines and, from each vehicle's own entity, its GeoPoints and trail
        columns.append(rrb.MapView(origin="/", contents=[f"/{E_MAP}/**", f"/{E_VEHICLES}/**"],
                                   name="map (WGS84)", zoom=map_zoom))
    columns.append(rrb.Grid(*series, grid_columns=2))
    return rrb.Blueprint(
        rrb.Horizontal(*columns, column_shares=[5, 3, 4] if map_view else [3, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        # collapsed: the play controls and the time slider, without the streams tree
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_TIME),
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
    """A :class:`RerunRecorder`, or a :class:`NullRecorder` when there is nowhere to record to
    (no file, no viewer address, no ``serve_web``, no ``viewer``)."""
    if (save_path is None and connect is None and options.get("serve_web") is None
            and not options.get("viewer")):
        return NullRecorder()
    return RerunRecorder(save_path, connect=connect, app_id=app_id, decimate=decimate,
                         kind=kind, **options)
