"""The live terminal view of a fleet mission.

On a terminal: a compact fleet header (time, stage, counts, clearance flown so far against its
limits, tick time and control rate) over a table with one row per vehicle — id, phase, the
sub-tube it flies, position in the tube frame, speed, distance to its nearest neighbour, to the
nearest obstacle centre and to the nearest leg, link age, estimate accuracy (and battery, when a
link reports it); the columns are declared once (:data:`COLUMNS`; the route segment it flies is
one more on a route of several segments) and fit a 100-column terminal — redrawn in place about
twice a second by ``rich``'s refresh thread (:class:`rich.live.Live`; never on the control
loop). Values that break their limit are red, those within 20 % of it yellow; events (phase
changes, faults, errors) scroll above the table as single lines. When the output is not a
terminal (CI logs, a pipe): every ``log_every_s`` seconds a short fleet headline (stage, phase
counts, control loop), the clearance flown so far against its limits and the worst vehicle now
per limit (:meth:`FleetView.lines`), plus the event lines, no escape codes. Errors are always
one line.
"""

from __future__ import annotations

import math
import queue
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.state import COUNTED_AIRBORNE_PHASES, Phase

__all__ = ["COLUMNS", "Column", "FleetStatus", "FleetView", "VehicleRow", "vehicle_rows"]

#: A value within this fraction of its limit (above it) is shown as a warning.
NEAR_LIMIT = 0.2
#: Link age (s) shown as a warning / as a problem.
LINK_AGE_WARN_S = 0.5
LINK_AGE_BAD_S = 2.0
_COUNTED = frozenset(p.value for p in COUNTED_AIRBORNE_PHASES)


@dataclass
class VehicleRow:
    """One vehicle's line of the table (NaN: not known / not applicable)."""

    vehicle_id: int
    phase: str
    sub_tube: str = ""  #: the sub-tube the switching rule puts it in (in the tube only)
    x_m: float = math.nan
    y_m: float = math.nan
    speed_m_s: float = math.nan
    neighbour_m: float = math.nan  #: distance to the nearest other airborne vehicle
    obstacle_m: float = math.nan  #: distance to the nearest obstacle centre
    obstacle_limit_m: float = math.nan  #: r_o + r_s of that obstacle
    leg_m: float = math.nan  #: distance to the nearest leg of its segment (in the tube only)
    link_age_s: float = math.nan  #: since the last packet from the vehicle
    accuracy_m: float = math.nan  #: the estimator's horizontal accuracy (1 σ)
    battery: float = math.nan  #: remaining charge, 0..1, when the link reports it
    segment: int = -1  #: the route segment it flies (0-based; −1: not shown, one segment)


@dataclass
class FleetStatus:
    """What the view shows (filled by the supervisor each tick)."""

    t_s: float = 0.0
    stage: str = "connecting"
    vehicles: int = 0
    connected: int = 0
    armed: int = 0
    in_tube: int = 0
    exited: int = 0
    lost: int = 0
    landed: int = 0
    min_pair_m: float = math.inf
    pair_limit_m: float = math.nan
    min_obstacle_m: float = math.inf
    obstacle_limit_m: float = math.nan
    min_leg_m: float = math.inf
    leg_limit_m: float = math.nan
    delta_m: float = math.nan
    tick_p50_ms: float = math.nan
    tick_p99_ms: float = math.nan
    rate_hz: float = math.nan
    on_time: float = math.nan
    latency_ms: float = math.nan
    phases: dict[str, int] = field(default_factory=dict)
    unsafe: bool = False  #: a limit was broken (telemetry or truth)
    truth_pair_m: float = math.nan  #: ground-truth figures (``run --truth``), NaN without
    truth_obstacle_m: float = math.nan
    truth_leg_m: float = math.nan
    rows: list[VehicleRow] = field(default_factory=list)  #: one per vehicle (the table)


def vehicle_rows(pilots: Sequence[Any], route: Any, limits: SafetyLimits,
                 segments: np.ndarray | None = None,
                 now_mono: float | None = None) -> list[VehicleRow]:
    """The table rows of the fleet's pilots (``VehiclePilot``: ``vehicle_id``, ``phase``,
    ``position()``, ``vel_xy``, ``link.state``, ``position_accuracy_m()``) flying ``route`` (a
    :class:`~vtube_fleet.core.route.Route`, the flight plan's: with the obstacles of lost
    vehicles), ``segments[k]`` the segment pilot k flies (None: each position's start segment).
    Neighbour distances among the vehicles that count as airborne
    (:data:`~vtube_fleet.state.COUNTED_AIRBORNE_PHASES`), the nearest obstacle centre of the
    route's configured obstacles; for those in the tube the leg distance to the legs of its own
    segment (:meth:`Route.leg_distances`) and the sub-tube the switching rule puts it in
    (:meth:`Route.locate`, named within its segment); each obstacle's limit is
    ``limits.obstacle_center_m`` (the physical r_s)."""
    obstacles = route.corridor.obstacles
    now = time.monotonic() if now_mono is None else now_mono
    m = len(pilots)
    pos = np.full((m, 2), np.nan)
    rows = []
    for k, p in enumerate(pilots):
        xy = np.asarray(p.position(), dtype=float)
        pos[k] = xy
        vel = np.asarray(getattr(p, "vel_xy", (math.nan, math.nan)), dtype=float)
        s = p.link.state
        last = s.last_packet_s if s.last_packet_s is not None else s.last_heartbeat_s
        rows.append(VehicleRow(
            vehicle_id=int(p.vehicle_id), phase=str(getattr(p.phase, "value", p.phase)),
            x_m=float(xy[0]), y_m=float(xy[1]), speed_m_s=float(np.hypot(*vel)),
            link_age_s=math.nan if last is None else max(0.0, now - last),
            accuracy_m=float(p.position_accuracy_m()),
            battery=float(getattr(s, "battery_remaining", math.nan))))
    flying = np.array([r.phase in _COUNTED for r in rows], dtype=bool) \
        & np.isfinite(pos).all(axis=1)
    if flying.sum() >= 2:
        q = pos[flying]
        d = np.hypot(q[:, None, 0] - q[None, :, 0], q[:, None, 1] - q[None, :, 1])
        np.fill_diagonal(d, np.inf)
        for k, v in zip(np.flatnonzero(flying).tolist(), d.min(axis=1).tolist(), strict=True):
            rows[k].neighbour_m = v
    if len(obstacles):
        c = np.array([o.center for o in obstacles], dtype=float).reshape(-1, 2)
        lim = np.array([limits.obstacle_center_m(o.radius) for o in obstacles])
        ok = flying
        if ok.any():
            d = np.hypot(pos[ok, None, 0] - c[None, :, 0], pos[ok, None, 1] - c[None, :, 1])
            near = d.argmin(axis=1)
            for k, j, dist in zip(np.flatnonzero(ok).tolist(), near.tolist(),
                                  d[np.arange(len(near)), near].tolist(), strict=True):
                rows[k].obstacle_m, rows[k].obstacle_limit_m = dist, float(lim[j])
    here = np.isfinite(pos).all(axis=1)
    seg = (np.full(m, -1, np.intp) if segments is None
           else np.asarray(segments, dtype=np.intp).reshape(m).copy())
    unset = here & (seg < 0)
    if unset.any():
        seg[unset] = route.start_segments(pos[unset])
    in_tube = np.array([r.phase == Phase.IN_TUBE.value for r in rows], dtype=bool) & here
    if in_tube.any():
        q = pos[in_tube]
        dh, dr = route.leg_distances(q, seg[in_tube])
        legs = np.minimum(dh, dr)
        for k, v in zip(np.flatnonzero(in_tube).tolist(), np.atleast_1d(legs).tolist(),
                        strict=True):
            rows[k].leg_m = v
        _, k = route.locate(q, seg[in_tube])
        names = route.sub_tubes
        for r, j in zip(np.flatnonzero(in_tube).tolist(), np.atleast_1d(k).tolist(),
                        strict=True):
            name = str(getattr(names[int(j)], "name", ""))
            rows[r].sub_tube = name.split(".", 1)[-1] if route.S > 1 else name
    if route.S > 1:
        for k, s in enumerate(seg.tolist()):
            rows[k].segment = s
    return rows


def _m(x: float) -> str:
    return "—" if not math.isfinite(x) else f"{x:.2f}"


def _level(value: float, limit: float) -> str:
    """"bad" (at or below the limit), "near" (within NEAR_LIMIT above it), "ok" or "" (unknown)."""
    if not (math.isfinite(value) and math.isfinite(limit)):
        return ""
    if value <= limit:
        return "bad"
    return "near" if value <= limit * (1.0 + NEAR_LIMIT) else "ok"


_STYLE = {"bad": "bold red", "near": "yellow", "ok": "", "": ""}
_PHASE_STYLE = {"lost": "bold red", "failed": "bold red", "holding": "yellow",
                "landing": "magenta", "in_tube": "cyan", "exited": "green", "landed": "dim",
                "takeoff": "bright_yellow", "arming": "bright_yellow", "waiting": "yellow",
                "stepping": "cyan"}


@dataclass(frozen=True)
class Column:
    """A column of the live table: its header (``name`` over ``unit``) and the cell of a row,
    ``cell(row, status) -> (text, rich style, level)`` with level "bad" / "near" / "" (the
    rows with a problem come first when the table is cut); shown when ``shown(status)``."""

    name: str
    unit: str
    cell: Callable[[VehicleRow, FleetStatus], tuple[str, str, str]]
    justify: str = "right"
    shown: Callable[[FleetStatus], bool] = lambda s: True

    @property
    def header(self) -> str:
        return f"{self.name}\n{self.unit}" if self.unit else self.name


def _limit_cell(value: float, limit: float) -> tuple[str, str, str]:
    lv = _level(value, limit)
    return _m(value), _STYLE[lv], "" if lv == "ok" else lv


def _age_cell(r: VehicleRow, s: FleetStatus) -> tuple[str, str, str]:
    lv = ("bad" if r.link_age_s > LINK_AGE_BAD_S else "near"
          if r.link_age_s > LINK_AGE_WARN_S else "")
    return _m(r.link_age_s), _STYLE[lv], lv


def _accuracy_cell(r: VehicleRow, s: FleetStatus) -> tuple[str, str, str]:
    lv = ("near" if math.isfinite(s.delta_m) and math.isfinite(r.accuracy_m)
          and r.accuracy_m > s.delta_m else "")
    return _m(r.accuracy_m), _STYLE[lv], lv


def _battery_cell(r: VehicleRow, s: FleetStatus) -> tuple[str, str, str]:
    lv = "bad" if r.battery < 0.15 else "near" if r.battery < 0.3 else ""
    return ("—" if not math.isfinite(r.battery) else f"{100 * r.battery:.0f} %"), _STYLE[lv], lv


def _phase_cell(r: VehicleRow, s: FleetStatus) -> tuple[str, str, str]:
    style = _PHASE_STYLE.get(r.phase, "")
    return r.phase, style, "bad" if style == "bold red" else ""


#: The table's columns, in order (a route's segment column goes before "sub-tube"); the two-line
#: headers keep the table within 100 terminal columns (tests/test_operator_view.py).
COLUMNS: tuple[Column, ...] = (
    Column("id", "", lambda r, s: (str(r.vehicle_id), "", "")),
    Column("phase", "", _phase_cell, justify="left"),
    Column("seg-", "ment", lambda r, s: ("—" if r.segment < 0 else f"S{r.segment + 1}", "", ""),
           shown=lambda s: any(r.segment >= 0 for r in s.rows)),
    Column("sub-", "tube", lambda r, s: (r.sub_tube or "—", "", ""), justify="left"),
    Column("x", "[m]", lambda r, s: (_m(r.x_m), "", "")),
    Column("y", "[m]", lambda r, s: (_m(r.y_m), "", "")),
    Column("v", "[m/s]", lambda r, s: (_m(r.speed_m_s), "", "")),
    Column("neighbour", "[m]", lambda r, s: _limit_cell(r.neighbour_m, s.pair_limit_m)),
    Column("obstacle", "[m]", lambda r, s: _limit_cell(r.obstacle_m, r.obstacle_limit_m)),
    Column("leg", "[m]", lambda r, s: _limit_cell(r.leg_m, s.leg_limit_m)),
    Column("link age", "[s]", _age_cell),
    Column("accuracy", "[m]", _accuracy_cell),
    Column("battery", "", _battery_cell,
           shown=lambda s: any(math.isfinite(r.battery) for r in s.rows)),
)


def worst_line(s: FleetStatus) -> str:
    """The worst vehicle now per limit, one short line ("" without rows): the nearest
    neighbour, obstacle centre and leg, the oldest link, the worst accuracy (the lowest
    battery), each marked BROKEN at or below its limit and near within 20 % above it."""
    parts = []

    def pick(name: str, key: Callable[[VehicleRow], float], unit: str, highest: bool = False,
             limit: Callable[[VehicleRow], float] = lambda r: math.nan,
             fmt: Callable[[float], str] = _m) -> None:
        rows = [r for r in s.rows if math.isfinite(key(r))]
        if not rows:
            return
        r = (max if highest else min)(rows, key=key)
        lv = _level(key(r), limit(r))
        tag = {"bad": " BROKEN", "near": " near its limit"}.get(lv, "")
        parts.append(f"{name} #{r.vehicle_id} {fmt(key(r))}{unit}{tag}")

    pick("pair", lambda r: r.neighbour_m, " m", limit=lambda r: s.pair_limit_m)
    pick("obstacle", lambda r: r.obstacle_m, " m", limit=lambda r: r.obstacle_limit_m)
    pick("leg", lambda r: r.leg_m, " m", limit=lambda r: s.leg_limit_m)
    pick("link age", lambda r: r.link_age_s, " s", highest=True)
    pick("accuracy", lambda r: r.accuracy_m, " m", highest=True)
    pick("battery", lambda r: r.battery, " %", fmt=lambda v: f"{100 * v:.0f}")
    return "  worst now: " + " · ".join(parts) if parts else ""


class FleetView:
    """Render :class:`FleetStatus` to ``stream`` (stderr by default): a ``rich`` live table on a
    terminal, plain lines otherwise (``tty`` overrides the detection)."""

    def __init__(
        self,
        stream: TextIO | None = None,
        *,
        tty: bool | None = None,
        refresh_s: float = 0.5,
        log_every_s: float = 5.0,
        enabled: bool = True,
        width: int | None = None,
        height: int | None = None,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(self.stream.isatty()) if tty is None else tty
        self.refresh_s = refresh_s
        self.log_every_s = log_every_s
        self.enabled = enabled
        self._last = -math.inf
        self._status: FleetStatus | None = None
        self._live: Any = None
        self._console: Any = None
        self._lines: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._printer: threading.Thread | None = None
        if self.tty and enabled:
            from rich.console import Console

            self._console = Console(file=self.stream, force_terminal=True, width=width,
                                    height=height, highlight=False)

    @staticmethod
    def lines(s: FleetStatus) -> list[str]:
        """The plain status (when the output is not a terminal): a fleet headline (time,
        stage, phase counts, the control loop), the clearance flown so far against its limits
        (and the truth's, with ``--truth``), and — when ``s.rows`` are given — the worst
        vehicle now per limit (:func:`worst_line`). Each line well under 150 characters."""

        def mark(value: float, limit: float) -> str:
            return " BROKEN" if _level(value, limit) == "bad" else ""

        phases = ", ".join(f"{n} {p.replace('_', ' ')}" for p, n in sorted(
            s.phases.items(), key=lambda kv: (-kv[1], kv[0])) if n) or "none yet"
        on_time = "—" if not math.isfinite(s.on_time) else f"{100 * s.on_time:.1f}%"
        head = (f"t={s.t_s:.1f}s {s.stage}: {s.vehicles} vehicles ({s.connected} connected): "
                f"{phases} | tick p99 {_m(s.tick_p99_ms)} ms, {_m(s.rate_hz)} Hz, on time "
                f"{on_time}, link {_m(s.latency_ms)} ms")
        flown = (f"  flown: pair {_m(s.min_pair_m)} m (> {_m(s.pair_limit_m)})"
                 f"{mark(s.min_pair_m, s.pair_limit_m)} · obstacle centre "
                 f"{_m(s.min_obstacle_m)} m (> {_m(s.obstacle_limit_m)})"
                 f"{mark(s.min_obstacle_m, s.obstacle_limit_m)} · legs {_m(s.min_leg_m)} m "
                 f"(> {_m(s.leg_limit_m)}){mark(s.min_leg_m, s.leg_limit_m)} · δ {_m(s.delta_m)}"
                 f" m{' · UNSAFE: a limit was broken' if s.unsafe else ''}")
        out = [head, flown]
        if math.isfinite(s.truth_pair_m) or math.isfinite(s.truth_leg_m):
            out.append(f"  truth: pair {_m(s.truth_pair_m)} m"
                       f"{mark(s.truth_pair_m, s.pair_limit_m)} · obstacle centre "
                       f"{_m(s.truth_obstacle_m)} m{mark(s.truth_obstacle_m, s.obstacle_limit_m)}"
                       f" · legs {_m(s.truth_leg_m)} m{mark(s.truth_leg_m, s.leg_limit_m)}")
        worst = worst_line(s)
        if worst:
            out.append(worst)
        return out

    # ----- the rich rendering ---------------------------------------------------------------
    @staticmethod
    def header(s: FleetStatus) -> Any:
        """The compact fleet header (:class:`rich.text.Text`, three short lines)."""
        from rich.text import Text

        t = Text()
        t.append(f"t {s.t_s:6.1f} s  ", style="bold")
        t.append(f"{s.stage}", style="bold cyan")
        t.append(f"   {s.vehicles} vehicles: {s.connected} connected · {s.armed} armed · "
                 f"{s.in_tube} in tube · {s.exited} exited · ")
        t.append(f"{s.lost} lost", style="bold red" if s.lost else "")
        t.append(f" · {s.landed} landed\n")
        t.append("clearance flown  ")

        def part(name: str, value: float, limit: float, sep: str = "   ") -> None:
            lv = _level(value, limit)
            t.append(f"{name} {_m(value)}", style=_STYLE[lv])
            t.append(f" (> {_m(limit)}){' BROKEN' if lv == 'bad' else ''}{sep}",
                     style="red" if lv == "bad" else "dim")

        part("pair", s.min_pair_m, s.pair_limit_m)
        part("obstacle centre", s.min_obstacle_m, s.obstacle_limit_m)
        part("legs", s.min_leg_m, s.leg_limit_m)
        t.append(f"δ {_m(s.delta_m)} m")
        if s.unsafe:
            t.append("   UNSAFE: a limit was broken", style="bold white on red")
        if math.isfinite(s.truth_pair_m) or math.isfinite(s.truth_leg_m):
            t.append("\ntruth            ")
            part("pair", s.truth_pair_m, s.pair_limit_m)
            part("obstacle centre", s.truth_obstacle_m, s.obstacle_limit_m)
            part("legs", s.truth_leg_m, s.leg_limit_m, sep="")
        on_time = "—" if not math.isfinite(s.on_time) else f"{100 * s.on_time:.1f} %"
        t.append(f"\ntick p50 {_m(s.tick_p50_ms)} ms · p99 {_m(s.tick_p99_ms)} ms · "
                 f"{_m(s.rate_hz)} Hz · on time {on_time} · link latency {_m(s.latency_ms)} ms",
                 style="dim")
        return t

    @staticmethod
    def table(s: FleetStatus, max_rows: int | None = None) -> Any:
        """One row per vehicle (:class:`rich.table.Table`), the columns of :data:`COLUMNS`
        (headers: name over unit). With more vehicles than ``max_rows``, the rows with a
        problem (red / yellow) first, then by id, and a last line counting the others. The
        battery column only when some vehicle reports one."""
        from rich import box
        from rich.table import Table
        from rich.text import Text

        cols = [c for c in COLUMNS if c.shown(s)]
        # no padding: the box's own separator is one blank (100 terminal columns)
        tab = Table(box=box.SIMPLE_HEAD, padding=(0, 0), pad_edge=False, show_edge=False,
                    header_style="bold")
        for c in cols:  # Text: "[m]" is no markup
            tab.add_column(Text(c.header), justify=c.justify, no_wrap=True, overflow="ignore")

        def cells(r: VehicleRow) -> tuple[list[Any], int]:
            out = [c.cell(r, s) for c in cols]
            levels = [lv for _, _, lv in out]
            worst = 2 if "bad" in levels else 1 if "near" in levels else 0
            return [Text(text, style=style) for text, style, _ in out], worst

        rendered = [(r.vehicle_id, *cells(r)) for r in s.rows]
        if max_rows is not None and len(rendered) > max_rows:
            ranked = sorted(rendered, key=lambda x: (-x[2], x[0]))
            shown, hidden = ranked[:max(max_rows - 1, 0)], ranked[max(max_rows - 1, 0):]
            for _, row, _ in shown:
                tab.add_row(*row)
            quiet = all(w == 0 for _, _, w in hidden)
            tab.caption = (f"… and {len(hidden)} more vehicles"
                           + (" without a problem" if quiet else ""))
        else:
            for _, row, _ in rendered:
                tab.add_row(*row)
        return tab

    def render(self, s: FleetStatus) -> Any:
        """The whole live display: header and table, the table cut to the terminal height."""
        from rich.console import Group

        max_rows = None
        if self._console is not None and self._console.height:
            max_rows = max(3, self._console.height - 10)
        return Group(self.header(s), self.table(s, max_rows) if s.rows else "")

    # ----- output -----------------------------------------------------------------------------
    def update(self, status: FleetStatus, *, force: bool = False) -> None:
        """Show ``status``. On a terminal the table is drawn by rich's refresh thread every
        ``refresh_s`` (drawing 50 rows takes tens of milliseconds: never on the control loop,
        which only hands over the status); otherwise a plain line every ``log_every_s``."""
        self._status = status
        if not self.enabled:
            return
        if self.tty:
            live = self._ensure_live()
            if force:
                live.refresh()
            return
        now = time.monotonic()
        if not force and now - self._last < self.log_every_s:
            return
        self._last = now
        self.stream.write("\n".join(self.lines(status)) + "\n")
        self.stream.flush()

    def wants_rows(self) -> bool:
        """Whether the next :meth:`update` shows the per-vehicle rows (the caller builds them
        only then): always on a terminal (the table), every ``log_every_s`` otherwise (the
        worst-vehicle line)."""
        if not self.enabled:
            return False
        return self.tty or time.monotonic() - self._last >= self.log_every_s

    def _current(self) -> Any:
        """What the refresh thread draws (never raises: a drawing bug must not kill it)."""
        from rich.text import Text

        try:
            return self.render(self._status) if self._status is not None else Text("")
        except Exception as exc:  # noqa: BLE001 - a view problem is shown, not raised
            return Text(f"(status view failed: {type(exc).__name__}: {exc})", style="red")

    def _ensure_live(self) -> Any:
        if self._live is None:
            from rich.live import Live

            # a redraw of 50 rows takes ~20 ms of Python (GIL) time: big fleets redraw at 1 Hz
            rows = len(self._status.rows) if self._status is not None else 0
            period = max(self.refresh_s, 0.05) if rows <= 20 else max(self.refresh_s, 1.0)
            self._live = Live(console=self._console, get_renderable=self._current,
                              auto_refresh=True, refresh_per_second=1.0 / period,
                              transient=False, redirect_stdout=False, redirect_stderr=False)
            self._live.start()
        return self._live

    def message(self, text: str) -> None:
        """One event/error line, above the live table."""
        if not self.enabled:
            return
        line = " ".join(str(text).split())
        if self.tty:
            from rich.text import Text

            style = "bold red" if " ERROR " in f" {line} " or "ABORT" in line else \
                "yellow" if " WARNING " in f" {line} " else ""
            # printed above the live table by a thread of the view's own: each print redraws
            # the table (tens of ms for 50 rows), which must not happen on the control loop
            self._lines.put(Text(line, style=style))
            if self._printer is None:
                self._printer = threading.Thread(target=self._print_lines, name="fleet-view",
                                                 daemon=True)
                self._printer.start()
        else:
            self.stream.write(line + "\n")
            self.stream.flush()

    def _print_lines(self) -> None:
        """The event printer: everything queued so far in one print (one table redraw)."""
        from rich.console import Group

        while True:
            batch = [self._lines.get()]
            while True:
                try:
                    batch.append(self._lines.get_nowait())
                except queue.Empty:
                    break
            stop = any(x is None for x in batch)
            batch = [x for x in batch if x is not None]
            if batch:
                try:
                    self._console.print(Group(*batch))
                except Exception:  # noqa: BLE001 - a view problem must not end the run
                    pass
            if stop:
                return

    def close(self) -> None:
        """Print the queued events, leave the last status on screen (final redraw), stop the
        live display."""
        if self._printer is not None:
            self._lines.put(None)
            self._printer.join(timeout=5.0)
            self._printer = None
        if self._status is not None and self.enabled:
            self.update(self._status, force=True)
        if self._live is not None:
            self._live.stop()
            self._live = None
