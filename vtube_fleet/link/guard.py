"""What a link believes of its vehicle's telemetry: the plausibility checks (issue 33).

Most PX4 fleets cannot sign MAVLink (PX4 < 1.18), so the link itself is the guard. Who may speak
for the vehicle is settled by the backends (its system id and its source address); this module
refuses what the vehicle *cannot have flown*, whoever sent it (docs/links.md, "Identity, source
and plausibility"; docs/security.md, layer 6):

* a reported horizontal speed above ``max_speed_m_s`` or a vertical one above
  ``max_vertical_speed_m_s`` (``speed``);
* a position farther from the last accepted one than the vehicle can fly in the time between
  them plus the estimate's reported accuracy: ``max_speed × Δt + jump_floor_m + σ`` (``σ`` =
  ESTIMATOR_STATUS.pos_horiz_accuracy, at most ``accuracy_cap_m``), horizontally and
  vertically (``position_jump``); also against an *anchor*, an accepted sample 0.25-0.5 s older
  by our clock, so that a chain of small jumps cannot walk away faster than that either;
* a ``time_boot_ms`` that goes back (or repeats with another position: ``time_backwards``) or
  runs ahead of our clock by more than ``time_jump_s`` since the last sample seen
  (``time_jump``). Δt is the vehicle's (``time_boot_ms``) where there is one (mavlink backend),
  but never more than our clock moved since the reference + ``arrival_slack_s`` (a forged time
  buys no allowance); MAVSDK hands positions over without their time: there, our arrival clock.

Our arrival clock is the hub's reading when it read the datagram, so a reference read late (a
stalled loop) makes a prompt sample after it look early by that delay, with the datagrams in
between lost (a full socket buffer). ``time_jump`` therefore compares with the last sample seen
(accepted or not), so it heals after one sample, and the cap of Δt costs a refusal only when the
delay is large against the bound (it heals as our clock moves on: the allowed distance grows at
the bound, the true one at the vehicle's speed; test: a 1 s stall with losses, no refusal).

A refused sample changes nothing in the :class:`~vtube_fleet.link.base.VehicleState`; it is
counted in ``state.telemetry_refused`` by kind. **Persistent refusals are a fault**: when a
vehicle's refusals go on for ``fault_after_s`` (refusals less than ``episode_gap_s`` apart
belong together), ``state.telemetry_fault`` is set (once; it stays) to a human reason: ``position
jumped 14.2 m in 20 ms (25 of 25 position samples refused in 0.50 s)``, prefixed ``telemetry from
two sources:`` when the vehicle's samples were accepted in between (two streams interleaved).
:class:`TelemetryBounds` carries the limits; :meth:`TelemetryBounds.for_mission` derives them
from a mission.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "ANCHOR_S",
    "DEFAULT_BOUNDS",
    "PX4_CRUISE_M_S",
    "REFUSAL_KINDS",
    "SPEED_MARGIN_M_S",
    "TelemetryBounds",
    "TelemetryGuard",
    "VERTICAL_MARGIN_M_S",
]

log = logging.getLogger("vtube_fleet.link")

#: Every kind of refusal a link counts (``VehicleState.telemetry_refused``): the first two at
#: the door (another vehicle on the port; the vehicle's id from another address), the others
#: by the plausibility checks of this module.
REFUSAL_KINDS = ("other_sysid", "other_source", "speed", "position_jump", "time_backwards",
                 "time_jump")
#: Added to the fastest the mission flies (m/s): a gust the vehicle cannot hold against,
#: PX4's overshoot and its velocity estimate's error (≤ 0.8 m/s on SITL).
SPEED_MARGIN_M_S = 5.0
VERTICAL_MARGIN_M_S = 2.0
#: PX4's MPC_XY_CRUISE default: the speed of its own RTL (a mission with fence_action "rtl").
PX4_CRUISE_M_S = 5.0
#: The anchor sample is 0.25-0.5 s older than the newest accepted one (by our clock).
ANCHOR_S = 0.25
_M_PER_DEG = 6371000.0 * math.pi / 180.0
_WARN_S = 5.0


@dataclass(frozen=True)
class TelemetryBounds:
    """The limits of :class:`TelemetryGuard` (module docstring; m, m/s, s)."""

    max_speed_m_s: float = 12.0 + SPEED_MARGIN_M_S  #: PX4's MPC_XY_VEL_MAX default + margin
    max_vertical_speed_m_s: float = 3.0 + VERTICAL_MARGIN_M_S  #: MPC_Z_VEL_MAX_UP + margin
    jump_floor_m: float = 0.3
    accuracy_cap_m: float = 1.0
    time_jump_s: float = 2.0
    arrival_slack_s: float = 0.25
    fault_after_s: float = 0.5
    episode_gap_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("max_speed_m_s", "max_vertical_speed_m_s", "jump_floor_m",
                     "accuracy_cap_m", "time_jump_s", "arrival_slack_s", "fault_after_s",
                     "episode_gap_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"telemetry bound {name} must be finite and > 0, got {v}")

    @classmethod
    def for_mission(cls, mission: Any) -> TelemetryBounds:
        """The bounds of ``mission``'s vehicles: horizontally the fastest it flies (v_max; 5
        m/s of PX4's own RTL with ``fence_action = "rtl"``) + :data:`SPEED_MARGIN_M_S`;
        vertically PX4's climb limit (3 m/s, at least the mission's climb) +
        :data:`VERTICAL_MARGIN_M_S`; the accuracy term capped at the mission's
        ``max_position_accuracy_m`` (a larger σ is refused before arming anyway)."""
        from vtube_fleet.config.mission import PX4_MAX_CLIMB_M_S, PX4_MAX_DESCENT_M_S

        cfg = mission.config
        fastest = float(mission.scenario.robots.v_max)
        if cfg.fence_action == "rtl":
            fastest = max(fastest, PX4_CRUISE_M_S)
        vertical = max(PX4_MAX_CLIMB_M_S, PX4_MAX_DESCENT_M_S, float(cfg.climb_speed_m_s),
                       float(cfg.max_vertical_speed_m_s))
        return cls(max_speed_m_s=fastest + SPEED_MARGIN_M_S,
                   max_vertical_speed_m_s=vertical + VERTICAL_MARGIN_M_S,
                   accuracy_cap_m=float(cfg.max_position_accuracy_m))


DEFAULT_BOUNDS = TelemetryBounds()


_STREAM_SLOTS = ("ref_t", "ref_at", "ref_a", "ref_b", "ref_c", "anchor", "next", "next_at",
                 "seen_lead")


class _Stream:
    """One position stream's last accepted sample: ``ref_t`` the vehicle's time (s; or the
    arrival), ``ref_at`` its arrival, ``ref_a, ref_b, ref_c`` north, east, down (m); its anchor
    and the next anchor as tuples (t, arrival, a, b, c) (``next_at``: the next one's arrival);
    ``seen_lead``: the vehicle's time minus the arrival of the last sample seen after the
    reference, accepted or not (what ``time_jump`` compares with). Plain fields, no tuple per
    sample: with a thousand links in one process, every object a sample touches costs."""

    __slots__ = _STREAM_SLOTS

    def __init__(self) -> None:
        _stream_init(self)


def _stream_init(s: Any) -> None:
    s.ref_t = None
    s.ref_at = s.ref_a = s.ref_b = s.ref_c = s.next_at = s.seen_lead = 0.0
    s.anchor = s.next = None


class TelemetryGuard:
    """The plausibility checks of one link (module docstring). ``owner`` is the link (for its
    name in log lines); the counters and the fault go into ``state``. The local position's
    stream is the guard itself (the attributes of a :class:`_Stream`: one object fewer to
    touch per sample, which counts with a thousand links in one process)."""

    __slots__ = ("owner", "state", "bounds", "_vh", "_vh2", "_vz", "_jump_s", "_slack",
                 "_allow", "_anchor_s", "global_", "_global_origin", "_ep_start", "_ep_last",
                 "_ep_ok", "_ep_bad", "_warned_at", "_suppressed", *_STREAM_SLOTS)

    def __init__(self, owner: Any, state: Any, bounds: TelemetryBounds) -> None:
        self.owner = owner
        self.state = state
        self.bounds = bounds
        self._vh = bounds.max_speed_m_s
        self._vh2 = bounds.max_speed_m_s ** 2
        self._vz = bounds.max_vertical_speed_m_s
        self._jump_s = bounds.time_jump_s
        self._slack = bounds.arrival_slack_s
        self._allow = bounds.jump_floor_m
        self._anchor_s = ANCHOR_S
        _stream_init(self)  # the local position's stream
        self.global_ = _Stream()
        self._global_origin: tuple[float, float, float] | None = None
        self._ep_start = 0.0
        self._ep_last: float | None = None
        self._ep_ok = 0
        self._ep_bad = 0
        self._warned_at = -math.inf
        self._suppressed = 0

    def set_accuracy(self, sigma_m: float) -> None:
        """The estimate's reported accuracy (ESTIMATOR_STATUS.pos_horiz_accuracy) joins the
        allowance of a jump, capped at ``accuracy_cap_m`` (a spoofed σ cannot widen it more)."""
        s = sigma_m if math.isfinite(sigma_m) and sigma_m > 0 else 0.0
        self._allow = self.bounds.jump_floor_m + min(s, self.bounds.accuracy_cap_m)

    # -- the checks ------------------------------------------------------------------------------
    def check_local(self, tb_ms: int | None, n: float, e: float, d: float, vn: float,
                    ve: float, vd: float, now: float, stream: _Stream | None = None) -> bool:
        """A LOCAL_POSITION_NED sample (NED metres and m/s, ``tb_ms`` None: time it by
        ``now``): True to take it, False refused (counted). ``stream``: another stream than
        the local position's (:meth:`check_global`). This runs for every position sample of
        a fleet (1,000 vehicles at 25-50 Hz): the common case takes the short way."""
        vz = self._vz
        if vn * vn + ve * ve > self._vh2 or not -vz <= vd <= vz:
            return self._speed(vn, ve, vd, now)
        s: Any = self if stream is None else stream
        rt = s.ref_t
        if rt is None:
            t = now if tb_ms is None else tb_ms * 0.001
            s.ref_t, s.ref_at, s.ref_a, s.ref_b, s.ref_c = t, now, n, e, d
            s.anchor = s.next = (t, now, n, e, d)
            s.next_at = now
            s.seen_lead = t - now
            return True
        if tb_ms is None:
            t = now
            dt = now - s.ref_at
        else:
            t = tb_ms * 0.001
            dt = t - rt
            if dt <= 0.0:
                return self._backwards(s, tb_ms, n, e, d, dt, now)
            # ahead of the last sample seen by more than our clock moved (the last seen, not
            # the reference: a reference read late must not make every prompt sample a jump)
            lead = t - now
            ahead = lead - s.seen_lead
            s.seen_lead = lead
            if ahead > self._jump_s:
                return self._refuse("time_jump", now, lambda: (
                    f"time_boot_ms ran {ahead:.3g} s ahead of our clock"))
            cap = now - s.ref_at + self._slack  # Δt: at most what our clock allows
            if dt > cap:
                dt = cap
        dn, de = n - s.ref_a, e - s.ref_b
        vdt = self._vh * dt
        if dn * dn + de * de > vdt * vdt:
            # more than the bound flies in Δt: within the allowance of the last sample, and
            # of the anchor (so that the allowance cannot add up along a chain of samples;
            # samples within the bound cannot add up to more than the bound)
            lim = vdt + self._allow
            if dn * dn + de * de > lim * lim:
                return self._jump(math.hypot(dn, de), dt, now)
            an = s.anchor
            dt_a = min(t - an[0], now - an[1] + self._slack)
            lim = self._vh * dt_a + self._allow
            dn, de = n - an[2], e - an[3]
            if dn * dn + de * de > lim * lim:
                return self._jump(math.hypot(dn, de), dt_a, now)
        dd = d - s.ref_c
        if not -(lim := vz * dt + self._allow) <= dd <= lim:
            return self._jump(abs(dd), dt, now, "vertically ")
        s.ref_t = t
        s.ref_at = now
        s.ref_a = n
        s.ref_b = e
        s.ref_c = d
        if now - s.next_at >= self._anchor_s:
            s.anchor, s.next = s.next, (t, now, n, e, d)
            s.next_at = now
        if self._ep_last is not None:
            self._accepted(now)
        return True

    def check_global(self, tb_ms: int | None, lat_deg: float, lon_deg: float, alt_m: float,
                     vn: float, ve: float, vd: float, now: float) -> bool:
        """A GLOBAL_POSITION_INT sample (degrees, m AMSL, m/s): True to take it. Checked as
        :meth:`check_local` in metres about its first sample (a tangent plane: fine for the
        distances between two samples)."""
        o = self._global_origin
        if o is None:
            o = self._global_origin = (lat_deg, lon_deg,
                                       _M_PER_DEG * math.cos(math.radians(lat_deg)))
        return self.check_local(tb_ms, (lat_deg - o[0]) * _M_PER_DEG, (lon_deg - o[1]) * o[2],
                                -alt_m, vn, ve, vd, now, self.global_)

    def _backwards(self, s: Any, tb_ms: int, n: float, e: float, d: float, dt: float,
                   now: float) -> bool:
        if dt == 0.0 and (n, e, d) == (s.ref_a, s.ref_b, s.ref_c):
            return True  # the same sample again: nothing new, nothing wrong
        ref_ms = round(s.ref_t * 1000)
        return self._refuse("time_backwards", now, lambda: (
            f"time_boot_ms went back from {ref_ms} to {tb_ms} ms" if dt < 0
            else f"time_boot_ms {tb_ms} ms repeated with another position"))

    # -- refusals and the fault ------------------------------------------------------------------
    def _speed(self, vn: float, ve: float, vd: float, now: float) -> bool:
        def why() -> str:
            h = math.hypot(vn, ve)
            if h > self._vh:
                return f"reported speed {h:.3g} m/s above the bound {self._vh:.3g} m/s"
            return (f"reported vertical speed {abs(vd):.3g} m/s above the bound "
                    f"{self._vz:.3g} m/s")
        return self._refuse("speed", now, why)

    def _jump(self, dist_m: float, dt_s: float, now: float, how: str = "") -> bool:
        return self._refuse("position_jump", now, lambda: (
            f"position jumped {how}{dist_m:.3g} m in {dt_s * 1000:.0f} ms"))

    def _accepted(self, now: float) -> None:
        if self._ep_last is not None and now - self._ep_last > self.bounds.episode_gap_s:
            self._ep_last = None  # the episode is over
        else:
            self._ep_ok += 1

    def _refuse(self, kind: str, now: float, why: Callable[[], str]) -> bool:
        """Count a refusal of ``kind``; the text ``why()`` is made only when it is said (a
        flood of fakes must not cost a formatted line each)."""
        st = self.state
        st.telemetry_refused[kind] += 1
        last = self._ep_last
        if last is None or now - last > self.bounds.episode_gap_s:
            self._ep_start, self._ep_ok, self._ep_bad = now, 0, 0
        self._ep_last = now
        self._ep_bad += 1
        span = now - self._ep_start
        if (st.telemetry_fault is None and self._ep_bad >= 2
                and span >= self.bounds.fault_after_s):
            ok, bad = self._ep_ok, self._ep_bad
            head = ("telemetry from two sources: " if ok >= 2 and 5 * ok >= ok + bad else "")
            self.declare_fault(f"{head}{why()} ({bad} of {ok + bad} position samples refused "
                               f"in {span:.2f} s)")
        if now - self._warned_at < _WARN_S:
            self._suppressed += 1
        else:
            self._warn(f"{self.owner.name}: refused telemetry ({kind}): {why()}", now)
        return False

    def declare_fault(self, reason: str) -> None:
        """Set ``state.telemetry_fault`` (once: the first reason stays) and say so."""
        if self.state.telemetry_fault is None:
            self.state.telemetry_fault = reason
            log.error("%s: telemetry fault: %s", self.owner.name, reason)

    def _warn(self, message: str, now: float) -> None:
        if now - self._warned_at < _WARN_S:
            self._suppressed += 1
            return
        if self._suppressed:
            message += (f" ({self._suppressed} more refusals in the last "
                        f"{now - self._warned_at:.0f} s; so far {self.counts()})")
        self._warned_at, self._suppressed = now, 0
        log.warning(message)

    def counts(self) -> str:
        """``3 other_source, 12 position_jump`` (or ``none``)."""
        refused: Counter[str] = self.state.telemetry_refused
        return ", ".join(f"{n} {k}" for k, n in sorted(refused.items()) if n) or "none"
