"""The live terminal view of a fleet mission.

On a terminal: a compact fleet header (time, stage, counts, clearance flown so far against its
limits, tick time and control rate) over a table with one row per vehicle — id, phase, the
route segment it flies (a route of several segments), position in the tube frame, speed,
distance to its nearest neighbour, to the nearest obstacle centre and to the nearest leg of its
segment, link age, estimate accuracy (and battery, when a link reports it) — redrawn
in place about twice a second by ``rich``'s refresh thread (:class:`rich.live.Live`; never on
the control loop). Values that break their limit are red, those within 20 % of it yellow;
events (phase changes, faults, errors) scroll above the table as single lines. When the output
is not a terminal (CI logs, a pipe): one plain status line every ``log_every_s`` seconds plus
the event lines, no escape codes. Errors are always one line.
"""

from __future__ import annotations

import math
import queue
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.state import COUNTED_AIRBORNE_PHASES, Phase

__all__ = ["FleetStatus", "FleetView", "VehicleRow", "vehicle_rows"]

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
    :class:`~vtube_fleet.core.route.Route`), ``segments[k]`` the segment pilot k flies (the
    table's column; None: each position's start segment). Neighbour distances among the
    vehicles that count as airborne (:data:`~vtube_fleet.state.COUNTED_AIRBORNE_PHASES`), the
    nearest obstacle centre of the route's configured obstacles, the leg distance to the legs of
    its own segment (:meth:`Route.leg_distances`) for those in the tube; each obstacle's limit is
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
                "takeoff": "bright_yellow", "arming": "bright_yellow"}


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
        """The plain status (the non-terminal log line, joined by " | ")."""
        head = (f"t={s.t_s:7.1f}s  {s.stage:<11} vehicles {s.vehicles}: connected {s.connected}"
                f"  armed {s.armed}  in tube {s.in_tube}  exited {s.exited}"
                f"  lost {s.lost}  landed {s.landed}")

        def mark(value: float, limit: float) -> str:
            return " BROKEN" if _level(value, limit) == "bad" else ""

        verdict = "  UNSAFE: a limit was broken" if s.unsafe else ""
        clear = (f"clearance flown: pair {_m(s.min_pair_m)} m (> 2 r_s = {_m(s.pair_limit_m)})"
                 f"{mark(s.min_pair_m, s.pair_limit_m)}  obstacle centre {_m(s.min_obstacle_m)}"
                 f" m (> {_m(s.obstacle_limit_m)}){mark(s.min_obstacle_m, s.obstacle_limit_m)}"
                 f"  legs {_m(s.min_leg_m)} m (> {_m(s.leg_limit_m)})"
                 f"{mark(s.min_leg_m, s.leg_limit_m)}  δ {_m(s.delta_m)} m{verdict}")
        if math.isfinite(s.truth_pair_m) or math.isfinite(s.truth_leg_m):
            clear += (f" | truth: pair {_m(s.truth_pair_m)}{mark(s.truth_pair_m, s.pair_limit_m)}"
                      f"  obstacle centre {_m(s.truth_obstacle_m)}"
                      f"{mark(s.truth_obstacle_m, s.obstacle_limit_m)}  legs {_m(s.truth_leg_m)}"
                      f"{mark(s.truth_leg_m, s.leg_limit_m)}")
        loop = (f"tick p50 {_m(s.tick_p50_ms)} ms  p99 {_m(s.tick_p99_ms)} ms"
                f"  rate {_m(s.rate_hz)} Hz  on time "
                f"{'—' if not math.isfinite(s.on_time) else f'{100 * s.on_time:.1f}%'}"
                f"  link latency {_m(s.latency_ms)} ms")
        return [head, clear, loop]

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
        """One row per vehicle (:class:`rich.table.Table`). With more vehicles than
        ``max_rows``, the rows with a problem (red / yellow) first, then by id, and a last line
        counting the others. The battery column only when some vehicle reports one."""
        from rich import box
        from rich.table import Table
        from rich.text import Text

        battery = any(math.isfinite(r.battery) for r in s.rows)
        route = any(r.segment >= 0 for r in s.rows)  # a route of several segments
        tab = Table(box=box.SIMPLE_HEAD, padding=(0, 1), pad_edge=False, show_edge=False,
                    header_style="bold")
        for name in ("id", "phase", *(("segment",) if route else ()), "x [m]", "y [m]",
                     "v [m/s]", "neighbour [m]", "obstacle [m]", "leg [m]", "link age [s]",
                     "accuracy [m]"):
            tab.add_column(Text(name), justify="left" if name == "phase" else "right",
                           no_wrap=True, overflow="ignore")  # Text: "[m]" is no markup
        if battery:
            tab.add_column(Text("battery"), justify="right", no_wrap=True,
                           overflow="ignore")

        def cells(r: VehicleRow) -> tuple[list[Any], int]:
            levels = [_level(r.neighbour_m, s.pair_limit_m),
                      _level(r.obstacle_m, r.obstacle_limit_m), _level(r.leg_m, s.leg_limit_m)]
            age = ("bad" if r.link_age_s > LINK_AGE_BAD_S else "near"
                   if r.link_age_s > LINK_AGE_WARN_S else "")
            acc = ("near" if math.isfinite(s.delta_m) and math.isfinite(r.accuracy_m)
                   and r.accuracy_m > s.delta_m else "")
            bat = ("bad" if r.battery < 0.15 else "near" if r.battery < 0.3 else "")
            ph = _PHASE_STYLE.get(r.phase, "")
            seg = ([Text("—" if r.segment < 0 else f"S{r.segment + 1}")] if route else [])
            row = [Text(str(r.vehicle_id)), Text(r.phase, style=ph), *seg, Text(_m(r.x_m)),
                   Text(_m(r.y_m)), Text(_m(r.speed_m_s)),
                   Text(_m(r.neighbour_m), style=_STYLE[levels[0]]),
                   Text(_m(r.obstacle_m), style=_STYLE[levels[1]]),
                   Text(_m(r.leg_m), style=_STYLE[levels[2]]),
                   Text(_m(r.link_age_s), style=_STYLE[age]),
                   Text(_m(r.accuracy_m), style=_STYLE[acc])]
            if battery:
                row.append(Text("—" if not math.isfinite(r.battery)
                                else f"{100 * r.battery:.0f} %", style=_STYLE[bat]))
            flags = [*levels, age, acc, bat if battery else ""]
            worst = 2 if "bad" in flags or ph == "bold red" else 1 if "near" in flags else 0
            return row, worst

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
        self.stream.write(" | ".join(self.lines(status)) + "\n")
        self.stream.flush()

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
