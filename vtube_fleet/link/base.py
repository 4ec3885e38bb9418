"""The vehicle-link interface shared by the ``mavlink`` and ``mavsdk`` backends.

A :class:`VehicleLink` is one PX4 vehicle seen through one endpoint. It keeps the latest telemetry
in a :class:`VehicleState` (updated in place as messages arrive), sends velocity setpoints from
*our* control loop (:meth:`VehicleLink.send_velocity_ned`, non-blocking) and runs commands with
retries (``async`` methods raising :class:`LinkError` subclasses). Units are in the names, as in
MAVSDK-Python; telemetry streams are async generators.

Errors are :class:`~vtube_fleet.errors.UserError` subclasses with one-line messages that name the
vehicle (``vehicle 3 (udpin://127.0.0.1:14542)``) and the numbers.
"""

from __future__ import annotations

import abc
import asyncio
import dataclasses
import logging
import math
import time
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from vtube_fleet.errors import UserError
from vtube_fleet.link.endpoints import Endpoint, parse_endpoint

__all__ = [
    "LinkConflict",
    "LinkError",
    "LinkTimeout",
    "CommandRejected",
    "FenceItem",
    "FenceRejected",
    "LinkUnsupported",
    "GeoPoint",
    "StatusText",
    "VehicleState",
    "VehicleLink",
    "IDENTITY_GATHER_S",
    "READY_MAX_AGE_S",
    "cancel_tasks",
    "send_velocities_ned",
    "setpoint_arrays",
]

#: A heartbeat / position older than this does not count for :meth:`VehicleLink.wait_ready`.
READY_MAX_AGE_S = 3.0
#: :meth:`VehicleLink.wait_ready` reports a port that carries other vehicles this long after it
#: first heard one (a bit more than PX4's 1 Hz HEARTBEAT: the message names them all).
IDENTITY_GATHER_S = 1.2


async def cancel_tasks(tasks: list[asyncio.Task]) -> None:
    """Cancel a link's background tasks and wait for them to end; errors are swallowed (a link
    being closed has nobody left to report them to). Clears ``tasks``."""
    for task in tasks:
        task.cancel()
    for task in tasks:
        try:
            await task
        except (asyncio.CancelledError, Exception):
            pass
    tasks.clear()


class LinkError(UserError):
    """Anything that went wrong talking to a vehicle (one line, names the vehicle)."""


class LinkTimeout(LinkError):
    """The vehicle did not answer / did not reach a state in time."""


class LinkConflict(LinkError):
    """Before arming, the link's port carries more than its one vehicle: the HEARTBEATs of
    other vehicles, or its system id from two addresses (docs/links.md, "Identity and
    source"). The message names the ids, the addresses and the likely cause."""


class CommandRejected(LinkError):
    """A command was answered with a MAV_RESULT other than ACCEPTED.

    Attributes: ``command`` (e.g. ``"COMPONENT_ARM_DISARM"``), ``result`` (MAV_RESULT name, e.g.
    ``"TEMPORARILY_REJECTED"``; for the mavsdk backend the MAVSDK result name).
    """

    def __init__(self, message: str, *, command: str, result: str) -> None:
        super().__init__(message)
        self.command = command
        self.result = result


class LinkUnsupported(LinkError):
    """This backend cannot do what was asked (e.g. the mavsdk backend and PX4 fences)."""


class FenceRejected(LinkError):
    """The vehicle answered a fence upload with a MISSION_ACK other than ACCEPTED, or the fence
    read back differs from the one uploaded. ``result``: the MAV_MISSION_RESULT name."""

    def __init__(self, message: str, *, result: str) -> None:
        super().__init__(message)
        self.result = result


class FenceItem(NamedTuple):
    """One PX4 fence item (MISSION_ITEM_INT of mission_type FENCE): ``command`` 5001 (polygon
    inclusion vertex; ``param1`` = the polygon's vertex count) or 5004 (exclusion circle;
    ``param1`` = radius in m), position in WGS84 degrees (sent as 1e-7 degree integers)."""

    command: int
    lat_deg: float
    lon_deg: float
    param1: float


class GeoPoint(NamedTuple):
    """A WGS84 position; ``alt_m`` above mean sea level (as PX4 reports it)."""

    lat_deg: float
    lon_deg: float
    alt_m: float


class StatusText(NamedTuple):
    """One STATUSTEXT (chunks joined, PX4's trailing tab stripped)."""

    time_s: float  #: time.monotonic() when received
    severity: int  #: MAV_SEVERITY (0 emergency … 7 debug); -1 if unknown (mavsdk backend)
    text: str


_NAN = math.nan
_SEVERITY_NAMES = {
    0: "EMERGENCY", 1: "ALERT", 2: "CRITICAL", 3: "ERROR",
    4: "WARNING", 5: "NOTICE", 6: "INFO", 7: "DEBUG", -1: "?",
}


@dataclass(eq=False)
class VehicleState:
    """Latest telemetry snapshot of one vehicle (updated in place by its link).

    Local position/velocity are PX4's LOCAL_POSITION_NED, relative to ``origin``
    (GPS_GLOBAL_ORIGIN), not to home. ``alt_m`` is AMSL (GLOBAL_POSITION_INT.alt);
    ``relative_alt_m`` is above home, and jumps by 1-2 m in PX4 SIH because home's altitude does:
    use ``down_m`` for height. NaN / None = not received yet. Timestamps are ``time.monotonic()``.
    """

    endpoint: str = ""
    sysid: int | None = None
    time_boot_ms: int | None = None
    north_m: float = _NAN
    east_m: float = _NAN
    down_m: float = _NAN
    vn_m_s: float = _NAN
    ve_m_s: float = _NAN
    vd_m_s: float = _NAN
    lat_deg: float = _NAN
    lon_deg: float = _NAN
    alt_m: float = _NAN
    relative_alt_m: float = _NAN
    heading_deg: float = _NAN  #: yaw, degrees clockwise from north (GLOBAL_POSITION_INT.hdg)
    #: the estimator's horizontal position accuracy, 1 σ (ESTIMATOR_STATUS.pos_horiz_accuracy)
    pos_accuracy_m: float = _NAN
    gnss_h_acc_m: float = _NAN  #: GNSS receiver horizontal accuracy (GPS_RAW_INT.h_acc)
    gnss_fix_type: int | None = None  #: GPS_RAW_INT.fix_type (3 = 3D, 6 = RTK fixed)
    #: remaining battery charge, 0..1 (SYS_STATUS / MAVSDK's battery ``remaining_percent``);
    #: NaN until reported, or when the vehicle does not know it (-1 on the wire)
    battery_remaining: float = _NAN
    #: the SITL simulator's ground truth (HIL_STATE_QUATERNION), only when asked for: WGS84
    #: position (alt AMSL) and NED velocity; NaN until received
    truth_lat_deg: float = _NAN
    truth_lon_deg: float = _NAN
    truth_alt_m: float = _NAN
    truth_vn_m_s: float = _NAN
    truth_ve_m_s: float = _NAN
    last_truth_s: float | None = None
    origin: GeoPoint | None = None
    home: GeoPoint | None = None
    armed: bool | None = None
    flight_mode: str = "UNKNOWN"  #: MAVSDK-style: HOLD, OFFBOARD, POSCTL, LAND, TAKEOFF …
    px4_mode: str = "UNKNOWN"  #: PX4's name: AUTO.LOITER, OFFBOARD, POSCTL … (mavlink backend)
    custom_mode: int | None = None
    base_mode: int | None = None
    landed_state: str = "UNKNOWN"  #: ON_GROUND, IN_AIR, TAKING_OFF, LANDING, UNKNOWN
    system_status: str = "UNKNOWN"  #: MAV_STATE name: UNINIT, STANDBY, ACTIVE, CRITICAL …
    health_ok: bool = False
    health_problems: tuple[str, ...] = ("no SYS_STATUS",)
    last_heartbeat_s: float | None = None
    last_position_s: float | None = None
    last_global_s: float | None = None
    last_packet_s: float | None = None
    statustexts: deque[StatusText] = field(default_factory=lambda: deque(maxlen=32))
    rx_packets: int = 0
    bad_packets: int = 0  #: datagrams (or parts) that failed to parse: garbage, bad CRC, cut off
    foreign_packets: int = 0  #: valid packets from another system id / a GCS, ignored
    #: what the link refused of this vehicle's port, by kind (link/guard.REFUSAL_KINDS):
    #: ``other_sysid`` (another vehicle), ``other_source`` (its id from another address),
    #: ``speed``, ``position_jump``, ``time_backwards``, ``time_jump`` (cannot be true)
    telemetry_refused: Counter[str] = field(default_factory=Counter)
    #: set (once, it stays) when the refusals persisted: the vehicle's telemetry is not to be
    #: trusted; a human reason ("telemetry from two sources: position jumped 14.2 m in 20 ms
    #: (…)"). None while it is.
    telemetry_fault: str | None = None
    source_changes: int = 0  #: times the vehicle's address was re-learned (logged)

    def accuracy_m(self, allow_gnss: bool = True) -> float:
        """The reported horizontal position accuracy (1 σ): the estimator's (ESTIMATOR_STATUS)
        or, if it sends none and ``allow_gnss``, the GNSS receiver's (GPS_RAW_INT h_acc);
        NaN if neither."""
        a = self.pos_accuracy_m
        return a if math.isfinite(a) or not allow_gnss else self.gnss_h_acc_m

    def copy(self) -> VehicleState:
        """An independent copy (the link keeps updating the original)."""
        new = dataclasses.replace(self)
        new.statustexts = deque(self.statustexts, maxlen=self.statustexts.maxlen)
        new.telemetry_refused = Counter(self.telemetry_refused)
        return new

    @property
    def has_local_position(self) -> bool:
        return self.last_position_s is not None

    @property
    def has_global_position(self) -> bool:
        return self.last_global_s is not None


def setpoint_arrays(links: Sequence[VehicleLink], north_m_s: np.ndarray, east_m_s: np.ndarray,
                    down_m_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of a batch of setpoints as float arrays; :class:`ValueError` naming the first
    link whose setpoint is not finite, or not finite in the float32 of the wire."""
    north, east, down = (np.asarray(a, dtype=float) for a in (north_m_s, east_m_s, down_m_s))
    with np.errstate(over="ignore"):
        wire = np.stack((north, east, down)).astype(np.float32)
    bad = np.flatnonzero(~np.isfinite(wire).all(axis=0))
    if bad.size:
        k = int(bad[0])
        raise ValueError(f"{links[k].name}: velocity setpoint must be finite, got "
                         f"({north[k]}, {east[k]}, {down[k]}) m/s")
    return north, east, down


def send_velocities_ned(links: Sequence[VehicleLink], north_m_s: np.ndarray,
                        east_m_s: np.ndarray, down_m_s: np.ndarray) -> list[LinkError | None]:
    """One velocity setpoint per link (row k to ``links[k]``), each link class's
    :meth:`VehicleLink.send_velocities_ned` for its own links (a fleet's setpoints in a tick).
    Returns per link None (sent) or the :class:`LinkError` its send raised; a non-finite
    setpoint raises :class:`ValueError` before anything is sent."""
    north, east, down = setpoint_arrays(links, north_m_s, east_m_s, down_m_s)
    groups: dict[type[VehicleLink], list[int]] = {}
    for k, link in enumerate(links):
        groups.setdefault(type(link), []).append(k)
    if len(groups) == 1:
        return type(links[0])._send_velocities(links, north, east, down)
    out: list[LinkError | None] = [None] * len(links)
    for cls, ks in groups.items():
        for k, exc in zip(ks, cls._send_velocities([links[k] for k in ks], north[ks],
                                                      east[ks], down[ks]), strict=True):
            out[k] = exc
    return out


class VehicleLink(abc.ABC):
    """One PX4 vehicle behind one endpoint. See ``docs/links.md``.

    Subclasses implement the transport; this base class holds the state, the waiters behind
    :meth:`states`/:meth:`positions`/:meth:`wait_until`, and the readiness check.
    """

    #: Seconds a setpoint may be old for :meth:`start_offboard` to accept that we stream.
    offboard_setpoint_max_age_s: float = 0.5

    def __init__(self, endpoint: str | Endpoint, sysid: int | None = None) -> None:
        self.endpoint: Endpoint = (
            endpoint if isinstance(endpoint, Endpoint) else parse_endpoint(endpoint)
        )
        if sysid is not None and not 1 <= int(sysid) <= 255:
            raise LinkError(f"{self.endpoint}: system id must be 1..255, got {sysid}")
        given = self.endpoint.sysid
        if given is not None and sysid is not None and int(sysid) != given:
            raise LinkError(f"{self.endpoint}: system id {sysid} given for an endpoint that "
                            f"says sysid={given}")
        sysid = given if sysid is None else sysid
        self.state = VehicleState(endpoint=self.endpoint.url, sysid=sysid)
        self._state_waiters: list[asyncio.Future[None]] = []
        self._position_waiters: list[asyncio.Future[None]] = []
        self._closed = False
        self._last_setpoint_s: float | None = None
        self._setpoints_sent = 0
        self._last_logged_text: tuple[str, float] | None = None

    # -- naming ------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        """``vehicle 3 (udpin://127.0.0.1:14542)``: how errors and logs name this vehicle."""
        sysid = self.state.sysid
        return f"vehicle {sysid if sysid is not None else '?'} ({self.endpoint.url})"

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}>"

    @property
    def sysid(self) -> int | None:
        return self.state.sysid

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def telemetry_fault(self) -> str | None:
        """``state.telemetry_fault``: why this vehicle's telemetry is not to be trusted."""
        return self.state.telemetry_fault

    # -- identity (docs/links.md, "Identity, source and plausibility") ------------------------
    def identity_problem(self) -> str | None:
        """Why the vehicle behind this port is ambiguous (other vehicles heard on it, its id
        from two addresses), None if it is not. Backends fill it in."""
        return None

    def check_identity(self) -> None:
        """:class:`LinkConflict` if :meth:`identity_problem`: called by :meth:`wait_ready`
        and ``arm`` (so, before arming; ``connect`` does not, so that the fleet reports it as
        a vehicle that is not ready rather than one that did not connect)."""
        problem = self.identity_problem()
        if problem is not None:
            raise LinkConflict(f"{self.name}: {problem}")

    def _log_statustext(self, logger: logging.Logger, severity: int, text: str) -> None:
        """Log a vehicle's STATUSTEXT (WARNING for severity <= 4, else INFO); a repeat of the
        previous text within 10 s (e.g. "Arming denied" on every arm retry) goes to DEBUG."""
        now = time.monotonic()
        last = self._last_logged_text
        repeat = last is not None and last[0] == text and now - last[1] < 10.0
        self._last_logged_text = (text, now)
        if repeat:
            level = logging.DEBUG
        else:
            level = logging.WARNING if 0 <= severity <= 4 else logging.INFO
        name = _SEVERITY_NAMES.get(severity, str(severity))
        logger.log(level, "%s says [%s]: %s", self.name, name, text)

    # -- notification (called by backends on every update) -----------------------------------
    def _notify_state(self) -> None:
        waiters = self._state_waiters
        if waiters:
            self._state_waiters = []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(None)

    def _notify_position(self) -> None:
        waiters = self._position_waiters
        if waiters:
            self._position_waiters = []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(None)
        self._notify_state()

    def _wake_all_closed(self) -> None:
        for lst in (self._state_waiters, self._position_waiters):
            for fut in lst:
                if not fut.done():
                    fut.set_result(None)
            lst.clear()

    async def _next(self, waiters_attr: str) -> None:
        if self._closed:
            raise LinkError(f"{self.name}: link is closed")
        fut = asyncio.get_running_loop().create_future()
        getattr(self, waiters_attr).append(fut)
        await fut

    # -- telemetry streams -------------------------------------------------------------------
    async def states(self) -> AsyncIterator[VehicleState]:
        """Yield :attr:`state` (the live object, updated in place: use ``.copy()`` to keep one)
        after every telemetry update. A slow consumer skips updates (latest-value semantics).
        Ends when the link is closed."""
        while not self._closed:
            await self._next("_state_waiters")
            if self._closed:
                return
            yield self.state

    async def positions(self) -> AsyncIterator[VehicleState]:
        """Like :meth:`states` but only after local-position (LOCAL_POSITION_NED) updates."""
        while not self._closed:
            await self._next("_position_waiters")
            if self._closed:
                return
            yield self.state

    async def wait_until(
        self, predicate: Callable[[VehicleState], bool], timeout_s: float, what: str
    ) -> VehicleState:
        """Wait until ``predicate(state)`` holds; :class:`LinkTimeout` naming ``what`` and the
        current mode/armed/landed state otherwise."""
        if predicate(self.state):
            return self.state
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    await self._next("_state_waiters")
                    if self._closed:
                        raise LinkError(f"{self.name}: link closed while waiting for {what}")
                    if predicate(self.state):
                        return self.state
        except TimeoutError:
            s = self.state
            raise LinkTimeout(
                f"{self.name}: {what} not reached within {timeout_s:.1f} s (mode {s.flight_mode}, "
                f"armed {s.armed}, landed {s.landed_state}, status {s.system_status})"
            ) from None

    # -- readiness -----------------------------------------------------------------------------
    def missing_for_ready(self, now: float | None = None) -> list[str]:
        """What :meth:`wait_ready` still waits for (empty list = ready)."""
        s = self.state
        now = time.monotonic() if now is None else now
        missing = []
        if s.last_heartbeat_s is None:
            missing.append("no HEARTBEAT")
        elif now - s.last_heartbeat_s > READY_MAX_AGE_S:
            missing.append(f"last HEARTBEAT {now - s.last_heartbeat_s:.1f} s ago")
        if s.last_position_s is None:
            missing.append("no local position")
        elif now - s.last_position_s > READY_MAX_AGE_S:
            missing.append(f"last local position {now - s.last_position_s:.1f} s ago")
        if s.last_global_s is None:
            missing.append("no global position")
        if s.home is None:
            missing.append("no home position")
        if s.origin is None:
            missing.append("no GPS global origin")
        if not s.health_ok:
            missing.append(
                f"not healthy ({', '.join(s.health_problems) or '?'}; "
                f"system_status {s.system_status})"
            )
        return missing

    async def _ready_tick(self, missing: list[str]) -> None:
        """Called about once a second while :meth:`wait_ready` waits (backends re-request)."""
        return None

    async def wait_ready(self, timeout_s: float = 30.0) -> VehicleState:
        """Wait for heartbeat, local and global position, home, GPS origin and health.

        Raises :class:`LinkTimeout` listing what is still missing, :class:`LinkConflict`
        when the port carries more than its vehicle (:meth:`identity_problem`; reported
        :data:`IDENTITY_GATHER_S` after it was first seen, so that the message names every
        vehicle heard by then).
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        next_tick = loop.time() + 1.0
        conflict_at: float | None = None
        while True:
            now = loop.time()
            missing = self.missing_for_ready()
            if self.identity_problem() is not None:
                if conflict_at is None:
                    conflict_at = now
                if now - conflict_at >= IDENTITY_GATHER_S or now >= deadline:
                    self.check_identity()
            elif not missing:
                return self.state
            if now >= deadline:
                raise LinkTimeout(
                    f"{self.name}: not ready after {timeout_s:.1f} s: {'; '.join(missing)}"
                )
            if now >= next_tick:
                next_tick = now + 1.0
                await self._ready_tick(missing)
            wake = min(deadline, next_tick,
                       math.inf if conflict_at is None else conflict_at + IDENTITY_GATHER_S)
            try:
                async with asyncio.timeout(max(0.0, wake - now)):
                    await self._next("_state_waiters")
            except TimeoutError:
                pass

    # -- setpoints bookkeeping ---------------------------------------------------------------
    def _check_setpoint(self, north_m_s: float, east_m_s: float, down_m_s: float) -> None:
        if self._closed:
            raise LinkError(f"{self.name}: link is closed")
        if not (math.isfinite(north_m_s) and math.isfinite(east_m_s) and math.isfinite(down_m_s)):
            raise ValueError(
                f"{self.name}: velocity setpoint must be finite, got "
                f"({north_m_s}, {east_m_s}, {down_m_s}) m/s"
            )

    def _require_fresh_setpoints(self) -> None:
        last = self._last_setpoint_s
        age = None if last is None else time.monotonic() - last
        if age is None or age > self.offboard_setpoint_max_age_s:
            when = "never sent one" if age is None else f"last one {age:.2f} s ago"
            raise LinkError(
                f"{self.name}: cannot start offboard: stream velocity setpoints first "
                f"(PX4 needs them before and during OFFBOARD; {when}, need one within "
                f"{self.offboard_setpoint_max_age_s:.2f} s)"
            )

    @property
    def setpoint_age_s(self) -> float | None:
        """Seconds since the last :meth:`send_velocity_ned`, None if never."""
        last = self._last_setpoint_s
        return None if last is None else time.monotonic() - last

    # -- the interface -----------------------------------------------------------------------
    @abc.abstractmethod
    async def connect(self, timeout_s: float = 10.0) -> None:
        """Open the endpoint and wait for the vehicle's first HEARTBEAT."""

    @abc.abstractmethod
    async def arm(self, timeout_s: float = 10.0) -> None:
        """Arm; PX4 answers TEMPORARILY_REJECTED for ~3-4 s after boot, so retry until
        ``timeout_s``; other rejections raise :class:`CommandRejected` at once."""

    @abc.abstractmethod
    async def disarm(self) -> None: ...

    @abc.abstractmethod
    async def takeoff(self, altitude_m: float) -> None:
        """Take off (AUTO.TAKEOFF) to ``altitude_m`` above the current position."""

    @abc.abstractmethod
    async def land(self) -> None: ...

    @abc.abstractmethod
    async def hold(self) -> None:
        """Switch to Hold (PX4 AUTO.LOITER)."""

    @abc.abstractmethod
    async def start_offboard(self) -> None:
        """Switch to OFFBOARD; requires setpoints sent within
        :attr:`offboard_setpoint_max_age_s` (else :class:`LinkError`)."""

    @abc.abstractmethod
    async def stop_offboard(self) -> None:
        """Leave OFFBOARD into Hold."""

    @abc.abstractmethod
    def send_velocity_ned(
        self,
        north_m_s: float,
        east_m_s: float,
        down_m_s: float,
        yaw_deg: float | None = None,
    ) -> None:
        """Send one velocity setpoint in the vehicle's LOCAL_NED frame now (non-blocking)."""

    @classmethod
    def send_velocities_ned(cls, links: Sequence[VehicleLink], north_m_s: np.ndarray,
                            east_m_s: np.ndarray, down_m_s: np.ndarray
                            ) -> list[LinkError | None]:
        """:meth:`send_velocity_ned` for many links of this class (velocity only), in order:
        row k to ``links[k]``. Returns, per link, None (sent) or the :class:`LinkError` that
        one send raised; a non-finite setpoint raises :class:`ValueError` before anything is
        sent. Backends may send the whole batch at once (``mavlink``: their
        :meth:`_send_velocities`)."""
        return cls._send_velocities(links, *setpoint_arrays(links, north_m_s, east_m_s,
                                                            down_m_s))

    @classmethod
    def _send_velocities(cls, links: Sequence[VehicleLink], north: np.ndarray,
                         east: np.ndarray, down: np.ndarray) -> list[LinkError | None]:
        """:meth:`send_velocities_ned` once the setpoints are checked (:func:`setpoint_arrays`)."""
        out: list[LinkError | None] = []
        for link, n, e, d in zip(links, north.tolist(), east.tolist(), down.tolist(),
                                 strict=True):
            try:
                link.send_velocity_ned(n, e, d)
            except LinkError as exc:
                out.append(exc)
            else:
                out.append(None)
        return out

    @property
    @abc.abstractmethod
    def latency_s(self) -> float | None:
        """One-way link latency estimate in seconds (half a smoothed round trip), None if no
        sample yet. Each backend documents its source."""

    async def measure_round_trip_s(self, samples: int = 3, timeout_s: float = 1.0
                                   ) -> float | None:
        """Measure the link's round trip now (``samples`` request → answer exchanges, the
        largest returned; None if none was answered). Also refreshes :attr:`latency_s`."""
        return None

    # -- onboard safety: parameters and fences (mavlink backend; others raise) ----------------
    async def read_param(self, name: str) -> float:
        """PX4 parameter ``name`` (PARAM_REQUEST_READ → PARAM_VALUE; integers as floats).
        :class:`LinkTimeout` if the vehicle does not answer (PX4 ignores unknown names)."""
        raise LinkUnsupported(f"{self.name}: this backend cannot read PX4 parameters")

    async def set_param(self, name: str, value: float) -> float:
        """Set ``name`` (PARAM_SET, the type PX4 reported) and return the value PX4 echoes."""
        raise LinkUnsupported(f"{self.name}: this backend cannot set PX4 parameters")

    async def upload_fence(self, items: list[FenceItem]) -> None:
        """Replace the vehicle's fence (MISSION_COUNT … MISSION_ACK, mission_type FENCE);
        :class:`FenceRejected` on a MISSION_ACK other than ACCEPTED."""
        raise LinkUnsupported(f"{self.name}: this backend cannot upload PX4 fences")

    async def download_fence(self) -> list[FenceItem]:
        """Read the vehicle's fence back (MISSION_REQUEST_LIST … MISSION_ACK)."""
        raise LinkUnsupported(f"{self.name}: this backend cannot download PX4 fences")

    async def request_truth(self, rate_hz: float) -> None:
        """Ask the vehicle for the SITL ground truth (HIL_STATE_QUATERNION) at ``rate_hz``
        (PX4 SITL and sim_stub send it; real vehicles do not). Fills the ``truth_*`` fields of
        :attr:`state`. :class:`LinkError` if refused."""
        raise LinkError(f"{self.name}: this backend cannot ask for the ground truth")

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop background work and release the endpoint; idempotent."""

    async def __aenter__(self) -> VehicleLink:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
