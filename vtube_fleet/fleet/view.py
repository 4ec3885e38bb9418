"""The live terminal view of a fleet mission.

On a terminal: a compact status block redrawn in place about twice a second (vehicles connected
/ armed / in tube / exited / lost, the clearance flown so far against its limit, tick time and
control rate); events (phase changes, faults, errors) scroll above it as single lines. When the
output is not a terminal (CI logs, a pipe): one status line every ``log_every_s`` seconds plus
the event lines. Errors are always one line.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import TextIO

__all__ = ["FleetStatus", "FleetView"]


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


def _m(x: float) -> str:
    return "—" if not math.isfinite(x) else f"{x:.2f}"


class FleetView:
    """Render :class:`FleetStatus` to ``stream`` (stderr by default)."""

    def __init__(
        self,
        stream: TextIO | None = None,
        *,
        tty: bool | None = None,
        refresh_s: float = 0.5,
        log_every_s: float = 5.0,
        enabled: bool = True,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(self.stream.isatty()) if tty is None else tty
        self.refresh_s = refresh_s
        self.log_every_s = log_every_s
        self.enabled = enabled
        self._lines = 0
        self._last = -math.inf
        self._status: FleetStatus | None = None

    @staticmethod
    def lines(s: FleetStatus) -> list[str]:
        """The status block (also used for the non-terminal log line)."""
        head = (f"t={s.t_s:7.1f}s  {s.stage:<11} vehicles {s.vehicles}: connected {s.connected}"
                f"  armed {s.armed}  in tube {s.in_tube}  exited {s.exited}"
                f"  lost {s.lost}  landed {s.landed}")
        def mark(value: float, limit: float) -> str:
            return "" if not (math.isfinite(value) and math.isfinite(limit)) else (
                "" if value > limit else " BROKEN")

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

    def update(self, status: FleetStatus, *, force: bool = False) -> None:
        """Redraw if due (about every ``refresh_s`` on a terminal, ``log_every_s`` otherwise)."""
        self._status = status
        if not self.enabled:
            return
        now = time.monotonic()
        every = self.refresh_s if self.tty else self.log_every_s
        if not force and now - self._last < every:
            return
        self._last = now
        lines = self.lines(status)
        if self.tty:
            self._erase()
            self.stream.write("\n".join(lines) + "\n")
            self._lines = len(lines)
        else:
            self.stream.write(" | ".join(lines) + "\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """One event/error line, above the status block."""
        if not self.enabled:
            return
        line = " ".join(str(text).split())
        if self.tty:
            self._erase()
            self.stream.write(line + "\n")
            self._lines = 0
            if self._status is not None:
                lines = self.lines(self._status)
                self.stream.write("\n".join(lines) + "\n")
                self._lines = len(lines)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def _erase(self) -> None:
        if self._lines:
            self.stream.write(f"\x1b[{self._lines}F\x1b[J")
            self._lines = 0

    def close(self) -> None:
        """Leave the last status block on screen (final redraw)."""
        if self._status is not None and self.enabled:
            self.update(self._status, force=True)
