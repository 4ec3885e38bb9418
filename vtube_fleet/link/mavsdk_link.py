"""``mavsdk`` backend: the in-process ``mavsdk`` ≥ 4 asyncio API, one instance for the fleet.

* :class:`MavsdkHub` owns ONE ``mavsdk.asyncio.Mavsdk`` (component type GROUND_STATION: MAVSDK
  identifies itself as sysid 245 / compid 190) for the whole fleet: ``add_any_connection`` once
  per endpoint URL, systems mapped by ``await system.get_system_id()``; no ``mavsdk_server``.
* :class:`MavsdkLink` builds ``ActionAsync``, ``TelemetryAsync`` and ``OffboardAsync`` for its
  system; telemetry subscriptions (async generators) run as tasks that update the
  :class:`~vtube_fleet.link.base.VehicleState` in place.
* Setpoints: :meth:`MavsdkLink.send_velocity_ned` sets MAVSDK's offboard velocity setpoint
  (sent at once by MAVSDK and then **resent at 20 Hz by MAVSDK's own thread**). PX4's
  offboard-loss failsafe therefore cannot notice a stalled Python loop (MAVSDK-Python#374), so
  the hub runs a **watchdog thread**: when a link in offboard has not had
  ``send_velocity_ned`` for more than ``watchdog_s`` (default 0.5 s), it logs a warning naming
  the vehicle and the stall duration and stops offboard (MAVSDK ``offboard.stop()`` → PX4 Hold)
  from that thread. A thread, not an asyncio task, because the thing it guards against is the
  event loop itself stalling. After a trip the link stays out of offboard until
  :meth:`MavsdkLink.start_offboard` is called again.
* Latency: MAVSDK exposes no round-trip measurement; :attr:`MavsdkLink.latency_s` is half the
  smoothed duration of action calls answered on the first try (command → COMMAND_ACK plus a
  thread hop; an overestimate).
* Parameters and the fence (the onboard layer, ``docs/fleet.md``): MAVSDK's ``param`` plugin
  (PX4's int32/float types found by WRONG_TYPE and kept; set, then read back) and its
  ``geofence`` plugin (``upload_geofence`` / ``download_geofence`` / ``clear_geofence``);
  refusals carry MAVSDK's result name, not PX4's MAV_MISSION_RESULT.
* MAVSDK result names appear in :class:`CommandRejected` (``COMMAND_DENIED``, ``TIMEOUT`` → a
  :class:`LinkTimeout`); MAVSDK maps PX4's TEMPORARILY_REJECTED and DENIED both to
  COMMAND_DENIED, so :meth:`MavsdkLink.arm` retries COMMAND_DENIED until its deadline.

* Identity and source (docs/links.md, "Identity, source and plausibility"): each link flies
  one system id; MAVSDK merges a system's traffic from every connection and address and
  cannot be told to refuse any, so the hub
  *detects* instead: an autopilot system discovered that no link of the hub flies is a
  :class:`~vtube_fleet.link.base.LinkConflict` before arming, and a system id that MAVSDK
  reports from a second address (its log line ``New system on: IP:PORT (system ID: N)``) is
  counted (``other_source``), a conflict before arming and a telemetry fault at once in flight.
  The plausibility checks (:mod:`vtube_fleet.link.guard`) run on the positions MAVSDK hands
  over, timed by their arrival (MAVSDK passes no time_boot_ms).

Limits: the asyncio wrappers run blocking calls in the loop's default executor (a few threads),
so commands to many vehicles at once queue there; ``system_status`` and ``time_boot_ms`` are not
available through MAVSDK's telemetry (left "UNKNOWN"/None).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import re
import threading
import time
import weakref
from collections.abc import AsyncIterator, Callable
from typing import Any

from vtube_fleet.link import px4
from vtube_fleet.link.base import (
    CommandRejected,
    FenceItem,
    FenceRejected,
    GeoPoint,
    LinkError,
    LinkTimeout,
    StatusText,
    VehicleLink,
    cancel_tasks,
)
from vtube_fleet.link.endpoints import (
    Endpoint,
    parse_endpoint,
    px4_sitl_sysid,
    shared_port_cause,
)
from vtube_fleet.link.guard import DEFAULT_BOUNDS, TelemetryBounds, TelemetryGuard

__all__ = ["MavsdkHub", "MavsdkLink", "DEFAULT_WATCHDOG_S"]

log = logging.getLogger(__name__)

#: Default stall limit of the offboard watchdog (seconds without ``send_velocity_ned``).
DEFAULT_WATCHDOG_S = 0.5

_SEVERITY = {
    "EMERGENCY": 0, "ALERT": 1, "CRITICAL": 2, "ERROR": 3,
    "WARNING": 4, "NOTICE": 5, "INFO": 6, "DEBUG": 7,
}
_HEALTH_FIELDS = (
    ("is_gyrometer_calibration_ok", "gyro"),
    ("is_accelerometer_calibration_ok", "accel"),
    ("is_magnetometer_calibration_ok", "mag"),
    ("is_local_position_ok", "local position"),
    ("is_global_position_ok", "global position"),
    ("is_home_position_ok", "home position"),
    ("is_armable", "prearm"),
)
_RTT_ALPHA = 0.2
#: MAV_CMD_NAV_FENCE_* ↔ MAVSDK's geofence FenceType
_POLYGON_TYPES = {5001: "INCLUSION", 5002: "EXCLUSION"}
_CIRCLE_TYPES = {5003: "INCLUSION", 5004: "EXCLUSION"}
_FENCE_CMD = {**{("polygon", t): c for c, t in _POLYGON_TYPES.items()},
              **{("circle", t): c for c, t in _CIRCLE_TYPES.items()}}


def _import_mavsdk() -> Any:
    try:
        import mavsdk.asyncio as mavsdk_asyncio
    except Exception as exc:  # the native library is missing or broken
        raise LinkError(
            f"mavsdk backend unavailable: cannot import mavsdk.asyncio: {exc}"
        ) from None
    return mavsdk_asyncio


_mavsdk_log = logging.getLogger("mavsdk")
_log_routed = False
#: MAVSDK's log line for a new (address, system id) on a UDP connection (MAVSDK 4)
_NEW_REMOTE = re.compile(
    r"New system on: (?P<ip>[^ ]+):(?P<port>\d+) \(system ID: (?P<sysid>\d+)\)")
#: the running hubs, told of every new remote MAVSDK logs (the log callback is per process)
_HUBS: weakref.WeakSet[MavsdkHub] = weakref.WeakSet()


def _route_mavsdk_log() -> None:
    """Send MAVSDK's own log lines (stdout by default) to the ``mavsdk`` Python logger."""
    global _log_routed
    if _log_routed:
        return
    try:
        from mavsdk import log_subscribe
    except Exception:
        return
    levels = {"DEBUG": logging.DEBUG, "INFO": logging.INFO, "WARN": logging.WARNING,
              "ERROR": logging.ERROR}

    def forward(level: Any, message: str, file: str | None, line: int) -> bool:
        _mavsdk_log.log(levels.get(getattr(level, "name", ""), logging.INFO), "%s", message)
        if message.startswith("New system on"):
            m = _NEW_REMOTE.search(message)
            if m is not None:
                addr = (m["ip"], int(m["port"]))
                for hub in list(_HUBS):
                    hub._remote_logged(addr, int(m["sysid"]))
        return True  # suppress MAVSDK's default stdout output

    log_subscribe(forward)
    _log_routed = True


class MavsdkHub:
    """One in-process MAVSDK instance for all vehicles, plus the offboard watchdog thread.

    Use as ``async with MavsdkHub() as hub: link = hub.link("udpin://127.0.0.1:14540")``.
    """

    def __init__(
        self,
        *,
        watchdog_s: float = DEFAULT_WATCHDOG_S,
        watchdog_period_s: float | None = None,
    ) -> None:
        if not watchdog_s > 0:
            raise LinkError(f"mavsdk watchdog_s must be > 0 s, got {watchdog_s}")
        self.watchdog_s = watchdog_s
        self.watchdog_period_s = watchdog_period_s or min(0.05, watchdog_s / 4)
        self._mavsdk: Any = None
        self._urls: dict[str, Any] = {}
        self._url_lock = asyncio.Lock()
        self._systems: dict[int, Any] = {}
        self._systems_changed = asyncio.Condition()
        self._discovery_task: asyncio.Task[None] | None = None
        self._links: list[MavsdkLink] = []
        self._links_lock = threading.Lock()
        #: system id -> the link that flies it (made by :meth:`link`)
        self._flown: dict[int, MavsdkLink] = {}
        #: autopilot systems MAVSDK discovered (HEARTBEATs of a vehicle, any connection)
        self._autopilots: set[int] = set()
        #: system id -> the addresses MAVSDK logged it from
        self._remotes: dict[int, list[tuple[str, int]]] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._stopper = concurrent.futures.ThreadPoolExecutor(
            max_workers=8, thread_name_prefix="vtube-offboard-stop"
        )
        self.watchdog_trips = 0

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self) -> None:
        if self._mavsdk is not None:
            return
        mavsdk_asyncio = _import_mavsdk()
        _route_mavsdk_log()
        config = mavsdk_asyncio.Configuration.create_with_component_type(
            mavsdk_asyncio.ComponentType.GROUND_STATION
        )
        self._mavsdk = mavsdk_asyncio.Mavsdk(config)
        self._loop = asyncio.get_running_loop()
        _HUBS.add(self)
        self._discovery_task = asyncio.get_running_loop().create_task(
            self._discover(), name="mavsdk-discovery"
        )
        self._thread = threading.Thread(
            target=self._watchdog_run, name="vtube-offboard-watchdog", daemon=True
        )
        self._thread.start()

    async def close(self) -> None:
        _HUBS.discard(self)
        with self._links_lock:
            links = list(self._links)
        for link in links:
            await link.close()
        self._stop.set()
        if self._thread is not None:
            await asyncio.get_running_loop().run_in_executor(None, self._thread.join, 5.0)
            self._thread = None
        if self._discovery_task is not None:
            self._discovery_task.cancel()
            try:
                await self._discovery_task
            except (asyncio.CancelledError, Exception):
                pass
            self._discovery_task = None
        self._stopper.shutdown(wait=True)
        if self._mavsdk is not None:
            mav, self._mavsdk = self._mavsdk, None
            await asyncio.get_running_loop().run_in_executor(None, mav.destroy)

    async def __aenter__(self) -> MavsdkHub:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- connections and systems ---------------------------------------------------------------
    def link(self, endpoint: str | Endpoint, sysid: int | None = None, **kwargs: Any) -> MavsdkLink:
        """A link for the vehicle behind ``endpoint`` (not yet connected)."""
        link = MavsdkLink(self, endpoint, sysid, **kwargs)
        assert link.state.sysid is not None
        self._flown[link.state.sysid] = link
        return link

    # -- identity and source (docs/links.md) ---------------------------------------------------
    def _remote_logged(self, addr: tuple[str, int], sysid: int) -> None:
        """From MAVSDK's log thread: MAVSDK heard ``sysid`` from ``addr`` for the first time."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._remote_seen, addr, sysid)
            except RuntimeError:  # the loop closed meanwhile
                pass

    def _remote_seen(self, addr: tuple[str, int], sysid: int) -> None:
        seen = self._remotes.setdefault(sysid, [])
        if addr in seen or len(seen) >= 8:
            return
        seen.append(addr)
        link = self._flown.get(sysid)
        if link is not None and len(seen) > 1:
            link._second_source(seen)

    def identity_problem(self, link: MavsdkLink) -> str | None:
        """Vehicles discovered that no link of this hub flies (MAVSDK does not say on which
        connection: with one endpoint, on that one), or ``link``'s id from two addresses."""
        problems = []
        extra = sorted(self._autopilots - set(self._flown))
        if extra:
            urls = ", ".join(self._urls) or link.endpoint.transport_url
            froms = [a for s in extra for a in self._remotes.get(s, [])]
            ids = sorted({*extra, *self._flown})
            where = (f"its port hears {len(ids)} vehicles, systems "
                     f"{', '.join(map(str, ids))}" if len(self._urls) <= 1 else
                     f"the hub's connections ({urls}) hear systems "
                     f"{', '.join(map(str, extra))} that no link flies")
            problems.append(f"{where} (from {', '.join(f'{h}:{p}' for h, p in froms[:4])}"
                            f"{' …' if len(froms) > 4 else ''}): " + shared_port_cause(
                                [parse_endpoint(u).port for u in self._urls] or
                                [link.endpoint.port], [p for _, p in froms]))
        seen = self._remotes.get(link.state.sysid or -1, [])
        if len(seen) > 1:
            problems.append(
                f"system {link.state.sysid} speaks from {len(seen)} addresses, "
                f"{', '.join(f'{h}:{p}' for h, p in seen[:4])}: two vehicles with one "
                f"MAV_SYS_ID, one vehicle's two MAVLink links (PX4 SITL's GCS link sends from "
                f"18570+i), or someone else sending as system {link.state.sysid}")
        return "; ".join(problems) or None

    async def add_endpoint(self, url: str) -> None:
        """``add_any_connection(url)`` once per URL (idempotent, concurrency-safe)."""
        if self._mavsdk is None:
            await self.start()
        async with self._url_lock:
            if url in self._urls:
                return
            try:
                self._urls[url] = await self._mavsdk.add_any_connection(url)
            except Exception as exc:
                raise LinkError(f"mavsdk: cannot add connection {url}: {exc}") from None

    async def _refresh_systems(self) -> None:
        if self._mavsdk is None:
            return
        for system in await self._mavsdk.get_systems():
            sysid = await system.get_system_id()
            if sysid not in self._systems:
                self._systems[sysid] = system
            if sysid not in self._autopilots and await system.has_autopilot():
                self._autopilots.add(sysid)
        async with self._systems_changed:
            self._systems_changed.notify_all()

    async def _discover(self) -> None:
        try:
            await self._refresh_systems()
            async for _ in self._mavsdk.on_new_system():
                await self._refresh_systems()
        except Exception as exc:
            log.error("mavsdk: system discovery stopped: %s", exc)

    async def system(self, sysid: int, timeout_s: float) -> Any:
        """The MAVSDK system with ``sysid``; waits for its discovery (HEARTBEAT)."""
        try:
            async with asyncio.timeout(timeout_s):
                async with self._systems_changed:
                    await self._systems_changed.wait_for(lambda: sysid in self._systems)
        except TimeoutError:
            seen = sorted(self._systems)
            raise LinkTimeout(
                f"mavsdk: no system {sysid} discovered within {timeout_s:.1f} s "
                f"(systems seen: {seen or 'none'}; connections: {', '.join(self._urls)})"
            ) from None
        return self._systems[sysid]

    # -- watchdog ------------------------------------------------------------------------------
    def _register(self, link: MavsdkLink) -> None:
        with self._links_lock:
            self._links.append(link)

    def _unregister(self, link: MavsdkLink) -> None:
        with self._links_lock:
            if link in self._links:
                self._links.remove(link)

    def _watchdog_run(self) -> None:
        while not self._stop.wait(self.watchdog_period_s):
            now = time.monotonic()
            with self._links_lock:
                links = list(self._links)
            for link in links:
                try:
                    stall = link._stall_s(now)
                    if stall is not None:
                        self._trip(link, stall)
                except Exception:  # the watchdog must survive anything
                    log.exception("offboard watchdog failed for %s", link.name)

    def _trip(self, link: MavsdkLink, stall_s: float) -> None:
        link._offboard_active = False
        link.watchdog_trips += 1
        self.watchdog_trips += 1
        log.warning(
            "%s: control loop stalled: no setpoint for %.2f s while offboard (watchdog %.2f s); "
            "stopping offboard -> Hold, because MAVSDK keeps resending the last setpoint",
            link.name, stall_s, link.watchdog_s,
        )
        self._stopper.submit(link._watchdog_stop)


class MavsdkLink(VehicleLink):
    """One vehicle through the shared :class:`MavsdkHub`. See the module docstring.

    ``sysid`` defaults to PX4 SITL's scheme for ports 14540..14579 (instance i → i + 1); other
    ports need it explicitly.
    """

    def __init__(
        self,
        hub: MavsdkHub,
        endpoint: str | Endpoint,
        sysid: int | None = None,
        *,
        watchdog_s: float | None = None,
        position_rate_hz: float = 50.0,
        global_rate_hz: float = 10.0,
        signing: Any = None,
        telemetry: TelemetryBounds | None = DEFAULT_BOUNDS,
        pin_source: bool = True,
    ) -> None:
        super().__init__(endpoint, sysid)
        if signing is not None:  # MAVSDK has no MAVLink 2 signing API
            from vtube_fleet.link.backends import BACKENDS

            BACKENDS["mavsdk"].require_signing(self.endpoint.url)
        sysid = self.state.sysid  # (the endpoint's ?sysid= included)
        if sysid is None:
            sysid = px4_sitl_sysid(self.endpoint.port)
            if sysid is None:
                raise LinkError(
                    f"{self.endpoint}: the mavsdk backend needs the vehicle's system id for a "
                    f"port outside PX4 SITL's 14540..14579"
                )
            self.state.sysid = sysid
        self.hub = hub
        self.watchdog_s = hub.watchdog_s if watchdog_s is None else watchdog_s
        self.position_rate_hz = position_rate_hz
        self.global_rate_hz = global_rate_hz
        self._system: Any = None
        self._action: Any = None
        self._telemetry: Any = None
        self._offboard: Any = None
        self._offboard_sync: Any = None
        self._direct: Any = None
        self._param: Any = None
        self._geofence: Any = None
        self._param_types: dict[str, str] = {}  #: "int" / "float", as PX4 declared them
        self._velocity_cls: Any = None
        self._tasks: list[asyncio.Task[None]] = []
        self._connect_lock = asyncio.Lock()
        self._offboard_active = False
        self._offboard_seen = False
        self._yaw_hold_deg: float | None = None
        self._rtt_s: float | None = None
        self.watchdog_trips = 0
        #: the plausibility checks (link/guard.py); None: off (a test switch)
        self._guard: TelemetryGuard | None = (
            None if telemetry is None else TelemetryGuard(self, self.state, telemetry))
        #: a second address of the vehicle's id is a telemetry fault (MAVSDK cannot refuse
        #: either); False: a test switch that only counts it
        self.pin_source = bool(pin_source)

    # -- identity (docs/links.md, "Identity, source and plausibility") ------------------------
    def identity_problem(self) -> str | None:
        return self.hub.identity_problem(self)

    def _second_source(self, addrs: list[tuple[str, int]]) -> None:
        """MAVSDK logged the vehicle's id from another address: counted; a fault (MAVSDK takes
        both and sends to both; it cannot be told to refuse one) unless ``pin_source`` is off.
        Before arming, :meth:`identity_problem` refuses the port."""
        self.state.telemetry_refused["other_source"] += 1  # (MAVSDK took it: counted, per address)
        log.warning("%s: a second source (other_source): MAVSDK hears system %s from %s:%s too",
                    self.name, self.state.sysid, addrs[-1][0], addrs[-1][1])
        if self.pin_source and self._guard is not None:
            self._guard.declare_fault(
                f"telemetry from two sources: system {self.state.sysid} speaks from "
                f"{', '.join(f'{h}:{p}' for h, p in addrs[:4])} (MAVSDK takes both; it "
                f"cannot be told to refuse one)")

    # -- watchdog hooks (called from the hub's threads) -------------------------------------------
    def _stall_s(self, now: float) -> float | None:
        if not self._offboard_active:
            return None
        last = self._last_setpoint_s
        if last is None:
            return None
        stall = now - last
        return stall if stall > self.watchdog_s else None

    def _watchdog_stop(self) -> None:
        try:
            self._offboard_sync.stop()
        except Exception as exc:
            log.error("%s: watchdog could not stop offboard: %s", self.name, exc)

    @property
    def watchdog_tripped(self) -> bool:
        return self.watchdog_trips > 0

    @property
    def offboard_active(self) -> bool:
        """True between a successful :meth:`start_offboard` and stop/watchdog trip."""
        return self._offboard_active

    @property
    def latency_s(self) -> float | None:
        """Half the smoothed first-try action round trip (an overestimate); None before any."""
        return None if self._rtt_s is None else self._rtt_s / 2.0

    async def measure_round_trip_s(self, samples: int = 3, timeout_s: float = 1.0
                                   ) -> float | None:
        """MAVSDK has no ping: time a harmless command that PX4 acknowledges (re-setting the
        position stream rate: SET_MESSAGE_INTERVAL → COMMAND_ACK, plus a thread hop)."""
        self._require_connected("measure the round trip")
        loop = asyncio.get_running_loop()
        worst: float | None = None
        for _ in range(max(1, samples)):
            t0 = loop.time()
            try:
                async with asyncio.timeout(timeout_s):
                    await self._telemetry.set_rate_position_velocity_ned(self.position_rate_hz)
            except Exception:
                continue
            rtt = loop.time() - t0
            self._rtt_s = rtt if self._rtt_s is None else self._rtt_s + _RTT_ALPHA * (
                rtt - self._rtt_s)
            worst = rtt if worst is None else max(worst, rtt)
        return worst

    async def request_truth(self, rate_hz: float) -> None:
        """MAVSDK's ``set_rate_ground_truth`` (HIL_STATE_QUATERNION); read through
        mavlink_direct (for the velocity)."""
        self._require_connected("ask for the ground truth")
        if self._direct is None:
            raise LinkError(f"{self.name}: this MAVSDK has no mavlink_direct plugin to read "
                            f"the ground truth")
        try:
            await self._telemetry.set_rate_ground_truth(rate_hz)
        except Exception as exc:
            raise LinkError(f"{self.name}: ground truth (HIL_STATE_QUATERNION) at "
                            f"{rate_hz:g} Hz refused: {exc}") from None

    # -- onboard safety: parameters and the fence (MAVSDK's param and geofence plugins) ------
    def _plugins(self, what: str) -> tuple[Any, Any]:
        """(ParamAsync, GeofenceAsync) of this system, built on first use."""
        self._require_connected(what)
        if self._param is None:
            from mavsdk.asyncio.plugins.geofence import GeofenceAsync
            from mavsdk.asyncio.plugins.param import ParamAsync

            self._param = ParamAsync(self._system)
            self._geofence = GeofenceAsync(self._system)
        return self._param, self._geofence

    def _param_error(self, name: str, what: str, exc: Exception) -> LinkError:
        result = getattr(getattr(exc, "result", None), "name", None)
        if result == "TIMEOUT":
            return LinkTimeout(f"{self.name}: {what} {name}: no answer (MAVSDK TIMEOUT; PX4 "
                               f"does not answer unknown parameters)")
        return LinkError(f"{self.name}: {what} {name} failed: {result or exc}")

    async def read_param(self, name: str) -> float:
        """``param.get_param_float`` or ``get_param_int``, as PX4 declared ``name`` (MAVSDK
        answers WRONG_TYPE for the other; the type found is remembered): integers as floats,
        as :meth:`MavlinkLink.read_param <vtube_fleet.link.mavlink.MavlinkLink.read_param>`."""
        if len(name) > 16:
            raise LinkError(f"{self.name}: parameter names have at most 16 characters: {name!r}")
        param, _ = self._plugins("read a parameter")
        known = self._param_types.get(name)
        order = [known] if known else ["float", "int"]
        for kind in order:
            get = param.get_param_float if kind == "float" else param.get_param_int
            try:
                value = await get(name)
            except Exception as exc:
                result = getattr(getattr(exc, "result", None), "name", None)
                if result == "WRONG_TYPE" and known is None and kind == "float":
                    continue
                raise self._param_error(name, "read", exc) from None
            self._param_types[name] = kind
            return float(value)
        raise LinkError(f"{self.name}: read {name}: MAVSDK says it is neither float nor int32 "
                        f"(WRONG_TYPE for both)")

    async def set_param(self, name: str, value: float) -> float:
        """``set_param_int`` (rounded) or ``set_param_float``, the type PX4 declared (read
        first if unknown), then read back: returns the value the vehicle holds,
        :class:`LinkError` if it kept another one."""
        if not math.isfinite(value):
            raise LinkError(f"{self.name}: {name} must be finite, got {value}")
        param, _ = self._plugins("set a parameter")
        if name not in self._param_types:
            await self.read_param(name)
        is_int = self._param_types[name] == "int"
        try:
            if is_int:
                await param.set_param_int(name, int(round(value)))
            else:
                await param.set_param_float(name, float(value))
        except Exception as exc:
            raise self._param_error(name, "set", exc) from None
        got = await self.read_param(name)
        want = float(round(value)) if is_int else float(value)
        if not math.isclose(got, want, rel_tol=1e-6, abs_tol=1e-6):
            raise LinkError(f"{self.name}: set {name} = {value:g}: the vehicle kept {got:g}")
        return got

    async def upload_fence(self, items: list[FenceItem]) -> None:
        """``geofence.upload_geofence(GeofenceData(polygons, circles))`` (MAVSDK sends the
        mission protocol with mission_type FENCE: polygons first, then circles, frame GLOBAL,
        degrees * 1e7); an empty list is ``clear_geofence``. MAVSDK's result names
        (e.g. ``ERROR``, ``TOO_MANY_GEOFENCE_ITEMS``) are in :class:`FenceRejected`: MAVSDK
        does not pass on PX4's MAV_MISSION_RESULT."""
        _, geofence = self._plugins("upload the fence")
        from mavsdk.plugins.geofence import Circle, FenceType, GeofenceData, Point, Polygon

        polygons, circles = [], []
        k = 0
        while k < len(items):
            it = items[k]
            if it.command in _POLYGON_TYPES:
                n = int(round(it.param1))
                group = items[k:k + n]
                if n < 1 or len(group) < n or any(g.command != it.command for g in group):
                    raise FenceRejected(f"{self.name}: fence item {k}: polygon of {n} vertices "
                                        f"is not {n} consecutive {it.command} items",
                                        result="INVALID_ARGUMENT")
                polygons.append(Polygon([Point(g.lat_deg, g.lon_deg) for g in group],
                                        getattr(FenceType, _POLYGON_TYPES[it.command])))
                k += n
            elif it.command in _CIRCLE_TYPES:
                circles.append(Circle(Point(it.lat_deg, it.lon_deg), float(it.param1),
                                      getattr(FenceType, _CIRCLE_TYPES[it.command])))
                k += 1
            else:
                raise FenceRejected(f"{self.name}: fence item {k}: command {it.command} is not "
                                    f"a fence polygon vertex or circle (MAVSDK's geofence API "
                                    f"has no other items)", result="UNSUPPORTED")
        kinds = [it.command in _CIRCLE_TYPES for it in items]
        if True in kinds and False in kinds[kinds.index(True):]:
            raise FenceRejected(f"{self.name}: MAVSDK uploads polygons before circles; the "
                                f"items must be in that order to be read back alike",
                                result="INVALID_ARGUMENT")
        try:
            if items:
                await geofence.upload_geofence(GeofenceData(polygons, circles))
            else:
                await geofence.clear_geofence()
        except Exception as exc:
            result = getattr(getattr(exc, "result", None), "name", None) or "ERROR"
            if result == "TIMEOUT":
                raise LinkTimeout(f"{self.name}: fence upload of {len(items)} items: no answer "
                                  f"(MAVSDK TIMEOUT)") from None
            raise FenceRejected(f"{self.name}: fence upload refused: MAVSDK {result} "
                                f"({len(items)} items){self._recent_text()}",
                                result=result) from None

    async def download_fence(self) -> list[FenceItem]:
        """``geofence.download_geofence()`` as fence items (polygon vertices with param1 = the
        vertex count, then circles with param1 = the radius)."""
        _, geofence = self._plugins("download the fence")
        try:
            data = await geofence.download_geofence()
        except Exception as exc:
            result = getattr(getattr(exc, "result", None), "name", None) or "ERROR"
            if result == "TIMEOUT":
                raise LinkTimeout(f"{self.name}: fence download: no answer (MAVSDK TIMEOUT)"
                                  ) from None
            raise FenceRejected(f"{self.name}: fence download failed: MAVSDK {result}",
                                result=result) from None
        out: list[FenceItem] = []
        for poly in data.polygons or []:
            cmd = _FENCE_CMD[("polygon", poly.fence_type.name)]
            pts = list(poly.points)
            out += [FenceItem(cmd, float(p.latitude_deg), float(p.longitude_deg),
                              float(len(pts))) for p in pts]
        for c in data.circles or []:
            cmd = _FENCE_CMD[("circle", c.fence_type.name)]
            out.append(FenceItem(cmd, float(c.point.latitude_deg),
                                 float(c.point.longitude_deg), float(c.radius)))
        return out

    # -- connect -------------------------------------------------------------------------------
    async def connect(self, timeout_s: float = 10.0) -> None:
        """Add the endpoint to the hub's MAVSDK, wait for the system, start telemetry."""
        async with self._connect_lock:
            if self._system is not None:
                return
            if self._closed:
                raise LinkError(f"{self.name}: link is closed")
            await self.hub.add_endpoint(self.endpoint.transport_url)
            try:
                system = await self.hub.system(self.state.sysid, timeout_s)  # type: ignore[arg-type]
            except LinkTimeout as exc:
                raise LinkTimeout(f"{self.name}: {exc}") from None
            from mavsdk.asyncio.plugins.action import ActionAsync
            from mavsdk.asyncio.plugins.offboard import OffboardAsync
            from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
            from mavsdk.plugins.offboard import VelocityNedYaw

            self._system = system
            self._action = ActionAsync(system)
            self._telemetry = TelemetryAsync(system)
            self._offboard = OffboardAsync(system)
            try:  # raw MAVLink for what the telemetry plugin lacks (estimator accuracy, truth)
                from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync

                self._direct = MavlinkDirectAsync(system)
            except Exception as exc:  # an older MAVSDK: the budget falls back to GNSS h_acc
                log.info("%s: no MAVSDK mavlink_direct plugin (%s)", self.name, exc)
                self._direct = None
            # The synchronous plugin behind the async wrapper: set_velocity_ned only stores the
            # setpoint and sends it (no waiting), so it is called directly from the loop, and
            # the watchdog thread calls its stop().
            self._offboard_sync = self._offboard._plugin
            self._velocity_cls = VelocityNedYaw
            self.state.last_heartbeat_s = time.monotonic()
            self.hub._register(self)
            self._start_telemetry()
            for setter, rate in (
                (self._telemetry.set_rate_position_velocity_ned, self.position_rate_hz),
                (self._telemetry.set_rate_position, self.global_rate_hz),
            ):
                try:
                    await setter(rate)
                except Exception as exc:
                    log.warning("%s: could not set telemetry rate %g Hz: %s", self.name, rate, exc)
            log.info("%s: connected (mavsdk)", self.name)

    def _start_telemetry(self) -> None:
        t = self._telemetry
        loop = asyncio.get_running_loop()
        subs: list[tuple[Callable[[], AsyncIterator[Any]], Callable[[Any], None]]] = [
            (t.subscribe_position_velocity_ned, self._on_position_velocity_ned),
            (t.subscribe_position, self._on_position),
            (t.subscribe_home, self._on_home),
            (t.subscribe_armed, self._on_armed),
            (t.subscribe_flight_mode, self._on_flight_mode),
            (t.subscribe_landed_state, self._on_landed_state),
            (t.subscribe_health, self._on_health),
            (t.subscribe_heading, self._on_heading),
            (t.subscribe_status_text, self._on_status_text),
            (t.subscribe_raw_gps, self._on_raw_gps),
            (t.subscribe_gps_info, self._on_gps_info),
            (t.subscribe_battery, self._on_battery),
        ]
        d = self._direct
        if d is not None:
            subs += [
                (lambda: d.subscribe_message("ESTIMATOR_STATUS"), self._on_estimator_status),
                (lambda: d.subscribe_message("HIL_STATE_QUATERNION"), self._on_truth),
            ]
        for subscribe, handler in subs:
            self._tasks.append(loop.create_task(self._consume(subscribe, handler)))
        self._tasks.append(loop.create_task(self._watch_connection()))

    async def _consume(
        self, subscribe: Callable[[], AsyncIterator[Any]], handler: Callable[[Any], None]
    ) -> None:
        gen = subscribe()
        try:
            async for item in gen:
                try:
                    handler(item)
                except Exception:
                    log.exception("%s: bad telemetry item %r", self.name, item)
        except Exception as exc:  # a dead subscription must not die silently
            log.warning("%s: MAVSDK telemetry stream %s ended: %s", self.name,
                        getattr(subscribe, "__name__", subscribe), exc)
        finally:
            await gen.aclose()  # type: ignore[attr-defined]

    async def _watch_connection(self) -> None:
        gen = self._system.is_connected_state()
        try:
            async for connected in gen:
                if not connected:
                    log.warning("%s: MAVSDK reports the vehicle disconnected", self.name)
                else:
                    self.state.last_heartbeat_s = time.monotonic()
                    self._notify_state()
        finally:
            await gen.aclose()

    # -- telemetry handlers --------------------------------------------------------------------
    def _on_position_velocity_ned(self, pv: Any) -> None:
        st = self.state
        p, v = pv.position, pv.velocity
        now = time.monotonic()
        g = self._guard
        if g is not None and not g.check_local(None, p.north_m, p.east_m, p.down_m, v.north_m_s,
                                               v.east_m_s, v.down_m_s, now):
            return
        st.north_m, st.east_m, st.down_m = p.north_m, p.east_m, p.down_m
        st.vn_m_s, st.ve_m_s, st.vd_m_s = v.north_m_s, v.east_m_s, v.down_m_s
        st.last_position_s = st.last_packet_s = now
        st.rx_packets += 1
        self._notify_position()

    def _on_position(self, p: Any) -> None:
        g = self._guard
        if g is not None and not g.check_global(None, p.latitude_deg, p.longitude_deg,
                                                p.absolute_altitude_m, 0.0, 0.0, 0.0,
                                                time.monotonic()):
            return
        st = self.state
        st.lat_deg, st.lon_deg = p.latitude_deg, p.longitude_deg
        st.alt_m, st.relative_alt_m = p.absolute_altitude_m, p.relative_altitude_m
        st.last_global_s = st.last_packet_s = time.monotonic()
        st.rx_packets += 1
        self._notify_state()

    def _on_home(self, p: Any) -> None:
        self.state.home = GeoPoint(p.latitude_deg, p.longitude_deg, p.absolute_altitude_m)
        self._notify_state()

    def _on_armed(self, armed: bool) -> None:
        self.state.armed = bool(armed)
        self.state.last_heartbeat_s = time.monotonic()
        self._notify_state()

    def _on_flight_mode(self, mode: Any) -> None:
        st = self.state
        st.flight_mode = mode.name
        st.last_heartbeat_s = time.monotonic()
        if mode.name in px4.FLIGHT_MODES:
            main, sub = px4.FLIGHT_MODES[mode.name]
            st.custom_mode = px4.encode_custom_mode(main, sub)
            st.px4_mode = px4.px4_mode_name(st.custom_mode)
        else:
            st.custom_mode, st.px4_mode = None, "UNKNOWN"
        if mode.name == "OFFBOARD":
            self._offboard_seen = True
        elif self._offboard_active and self._offboard_seen:
            # PX4 left offboard by itself (failsafe, RC, another GCS): MAVSDK stops too.
            log.warning("%s: vehicle left OFFBOARD (now %s)", self.name, mode.name)
            self._offboard_active = False
        self._notify_state()

    def _on_battery(self, battery: Any) -> None:
        pct = float(battery.remaining_percent)  # 0..100 (MAVSDK >= 2); NaN: unknown
        self.state.battery_remaining = pct * 0.01 if 0.0 <= pct <= 100.0 else math.nan

    def _on_landed_state(self, landed: Any) -> None:
        self.state.landed_state = landed.name
        self._notify_state()

    def _on_health(self, health: Any) -> None:
        problems = tuple(name for attr, name in _HEALTH_FIELDS if not getattr(health, attr))
        st = self.state
        st.health_problems = problems
        st.health_ok = not problems
        self._notify_state()

    def _on_heading(self, heading: Any) -> None:
        self.state.heading_deg = heading.heading_deg

    def _on_raw_gps(self, g: Any) -> None:
        h = float(g.horizontal_uncertainty_m)
        self.state.gnss_h_acc_m = h if math.isfinite(h) and h > 0 else math.nan

    def _on_gps_info(self, g: Any) -> None:
        self.state.gnss_fix_type = int(getattr(g.fix_type, "value", g.fix_type))

    def _on_estimator_status(self, msg: Any) -> None:
        if msg.system_id != self.state.sysid:
            return
        acc = float(json.loads(msg.fields_json).get("pos_horiz_accuracy", math.nan))
        self.state.pos_accuracy_m = acc if math.isfinite(acc) and acc >= 0 else math.nan
        if self._guard is not None:
            self._guard.set_accuracy(self.state.pos_accuracy_m)

    def _on_truth(self, msg: Any) -> None:
        if msg.system_id != self.state.sysid:
            return
        f = json.loads(msg.fields_json)
        st = self.state
        st.truth_lat_deg = f["lat"] * 1e-7
        st.truth_lon_deg = f["lon"] * 1e-7
        st.truth_alt_m = f["alt"] * 1e-3
        st.truth_vn_m_s = f["vx"] * 0.01
        st.truth_ve_m_s = f["vy"] * 0.01
        st.last_truth_s = time.monotonic()

    def _on_status_text(self, text: Any) -> None:
        severity = _SEVERITY.get(getattr(text.type, "name", ""), -1)
        msg = str(text.text).rstrip("\t\r\n \x00")
        self.state.statustexts.append(StatusText(time.monotonic(), severity, msg))
        self._log_statustext(log, severity, msg)
        self._notify_state()

    async def _ready_tick(self, missing: list[str]) -> None:
        await self.hub._refresh_systems()  # (autopilots discovered meanwhile: identity)
        if "no GPS global origin" in missing and self._telemetry is not None:
            try:
                o = await self._telemetry.get_gps_global_origin()
            except Exception as exc:
                log.debug("%s: GPS global origin not available yet: %s", self.name, exc)
                return
            self.state.origin = GeoPoint(o.latitude_deg, o.longitude_deg, o.altitude_m)
            self._notify_state()

    async def wait_ready(self, timeout_s: float = 30.0) -> Any:
        if self._telemetry is not None and self.state.origin is None:
            await self._ready_tick(["no GPS global origin"])
        await self.hub._refresh_systems()
        return await super().wait_ready(timeout_s)

    # -- commands ------------------------------------------------------------------------------
    def _require_connected(self, what: str) -> None:
        if self._closed:
            raise LinkError(f"{self.name}: {what}: link is closed")
        if self._system is None:
            raise LinkError(f"{self.name}: {what}: not connected; call connect() first")

    async def _call(self, what: str, coro_fn: Callable[[], Any]) -> None:
        self._require_connected(what)
        t0 = time.monotonic()
        try:
            await coro_fn()
        except Exception as exc:
            result = getattr(getattr(exc, "result", None), "name", None)
            if result is None:
                raise LinkError(f"{self.name}: {what} failed: {exc}") from None
            if result == "TIMEOUT":
                raise LinkTimeout(f"{self.name}: {what}: no answer (MAVSDK TIMEOUT)") from None
            raise CommandRejected(
                f"{self.name}: {what} {result}{self._recent_text()}", command=what, result=result
            ) from None
        rtt = time.monotonic() - t0
        self._rtt_s = rtt if self._rtt_s is None else self._rtt_s + _RTT_ALPHA * (rtt - self._rtt_s)

    def _recent_text(self, window_s: float = 2.0) -> str:
        texts = self.state.statustexts
        if texts and time.monotonic() - texts[-1].time_s <= window_s and texts[-1].severity <= 4:
            return f'; vehicle says "{texts[-1].text}"'
        return ""

    async def arm(self, timeout_s: float = 10.0, retry_interval_s: float = 0.5) -> None:
        """``action.arm()``; COMMAND_DENIED (PX4's TEMPORARILY_REJECTED right after boot) is
        retried every ``retry_interval_s`` until ``timeout_s``."""
        await self.hub._refresh_systems()
        self.check_identity()  # a port carrying other vehicles is refused before arming
        loop = asyncio.get_running_loop()
        t_start = loop.time()
        attempts = 0
        while True:
            attempts += 1
            try:
                await self._call("arm", lambda: self._action.arm())
                return
            except CommandRejected as exc:
                elapsed = loop.time() - t_start
                if exc.result != "COMMAND_DENIED" or elapsed + retry_interval_s > timeout_s:
                    raise CommandRejected(
                        f"{exc} (after {attempts} attempt(s) in {elapsed:.1f} s)",
                        command=exc.command, result=exc.result,
                    ) from None
            await asyncio.sleep(retry_interval_s)  # back-off between attempts, not a sync

    async def disarm(self) -> None:
        await self._call("disarm", lambda: self._action.disarm())

    async def takeoff(self, altitude_m: float) -> None:
        """``set_takeoff_altitude(altitude_m)`` (PX4 MIS_TAKEOFF_ALT, relative to home) then
        ``action.takeoff()``."""
        if not (math.isfinite(altitude_m) and altitude_m > 0):
            raise LinkError(f"{self.name}: takeoff altitude must be > 0 m, got {altitude_m}")
        await self._call(
            "set_takeoff_altitude", lambda: self._action.set_takeoff_altitude(altitude_m)
        )
        await self._call("takeoff", lambda: self._action.takeoff())

    async def land(self) -> None:
        # leaving offboard by a mode change: the watchdog must not "stop offboard" (→ Hold)
        # a second later, before the 1 Hz HEARTBEAT has shown LAND (it did, on real SITL)
        self._offboard_active = False
        await self._call("land", lambda: self._action.land())

    async def hold(self) -> None:
        self._offboard_active = False
        await self._call("hold", lambda: self._action.hold())

    def send_velocity_ned(
        self,
        north_m_s: float,
        east_m_s: float,
        down_m_s: float,
        yaw_deg: float | None = None,
    ) -> None:
        """Set MAVSDK's offboard velocity setpoint (sent now, then resent by MAVSDK at 20 Hz).

        MAVSDK always sends a yaw; without ``yaw_deg`` the heading at the first setpoint is
        held."""
        self._check_setpoint(north_m_s, east_m_s, down_m_s)
        self._require_connected("send_velocity_ned")
        if yaw_deg is None:
            if self._yaw_hold_deg is None:
                h = self.state.heading_deg
                self._yaw_hold_deg = h if math.isfinite(h) else 0.0
            yaw_deg = self._yaw_hold_deg
        else:
            self._yaw_hold_deg = yaw_deg
        try:
            self._offboard_sync.set_velocity_ned(
                self._velocity_cls(north_m_s, east_m_s, down_m_s, yaw_deg)
            )
        except Exception as exc:
            raise LinkError(f"{self.name}: set_velocity_ned failed: {exc}") from None
        self._last_setpoint_s = time.monotonic()
        self._setpoints_sent += 1

    async def start_offboard(self) -> None:
        """``offboard.start()`` after checking we stream setpoints; arms the watchdog."""
        self._require_fresh_setpoints()
        self._offboard_seen = self.state.flight_mode == "OFFBOARD"
        await self._call("offboard.start", lambda: self._offboard.start())
        self._offboard_active = True

    async def stop_offboard(self) -> None:
        """``offboard.stop()`` (PX4 → Hold); disarms the watchdog."""
        self._offboard_active = False
        await self._call("offboard.stop", lambda: self._offboard.stop())

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._offboard_active = False
        self.hub._unregister(self)
        await cancel_tasks(self._tasks)
        for plugin in (self._action, self._telemetry, self._offboard, self._param,
                       self._geofence):
            if plugin is not None:
                try:
                    plugin.destroy()
                except Exception:
                    pass
        self._wake_all_closed()

