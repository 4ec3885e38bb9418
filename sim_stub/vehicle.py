"""A mock PX4 SITL vehicle on the wire: MAVLink 2 over UDP, PX4's streams, commands and rules.

Ground truth is the captures in ``tests/data/px4_sitl/`` (README there, cited "capture"); where
they are silent the behaviour follows PX4 source of the same era (cited "PX4 source") and is
listed as such in ``docs/sim_stub.md``.

One :class:`MockVehicle` is PX4 SITL instance ``i``: sysid ``i+1``, compid 1, bound to
``host:vehicle_port(i)`` and streaming to ``host:gcs_port(i)`` until something is received; from
then on it answers (and streams to) whoever sent the last valid MAVLink datagram.
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
import socket
import struct
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from . import px4
from .codec import SPECS, DatagramParser, Encoder, MsgSpec, fast_decoder, mcrf4xx
from .errors import SimStubError
from .estimator import EstimatorProfile, estimator_profile
from .faults import Faults
from .geo import project, reproject
from .ports import PortScheme, resolve_port_scheme
from .px4 import (
    LANDED_IN_AIR,
    LANDED_ON_GROUND,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MAV_RESULT_UNSUPPORTED,
    MODE_BY_NAME,
    Mode,
)
from .scheduler import Scheduler

__all__ = [
    "MockVehicle",
    "VehicleCounters",
    "StreamState",
    "DEFAULT_HOME",
    "STREAM_CATALOG",
    "PROFILES",
    "GCS_LINK_STREAMS",
    "GCS_LINK_PROFILES",
    "BOOT",
    "validate_home",
]

log = logging.getLogger("sim_stub")

DEFAULT_HOME = (47.397742, 8.545594, 489.4)  # PX4 SIH default SIH_LOC_LAT0/LON0/H0

# Boot timeline, seconds after start (capture: first packet 0.37-0.44 s, HEARTBEAT 1.3-1.45 s,
# GLOBAL_POSITION_INT 2.9-3.2 s, system_status STANDBY between the 3.4 s and 4.4 s heartbeats,
# health reports at ~4.3 s, unsolicited CAL_BARO0_* at ~5.5 s).
BOOT = {
    "time_boot_zero": 0.22,  # time_boot_ms 0 (capture: first GPS_RAW_INT at 0.39 s has 164 ms)
    "event_boot": 0.44,
    "origin": 1.38,  # GPS_GLOBAL_ORIGIN (sent once) and home become valid
    "health_report": 2.25,
    "sensors": 2.40,
    "logger": 2.70,
    "global_position": 2.95,
    "ready": 4.30,
    "cal_baro": 5.55,
}

# Takeoff/landing timing (capture, see dynamics fit): spool-up COM_SPOOLUP_TIME (1 s), then the
# takeoff ramp: "Takeoff detected"/IN_AIR 0.9 s and lift-off 2.0 s after the ramp starts (capture:
# "Takeoff detected" 1.7-2.0 s and lift-off ~3.0 s after ARM with a climb command waiting);
# "Landing detected" 1.5 s after touchdown (capture: 1.0-2.0 s).
TAKEOFF_DETECT_S = 0.9
LIFTOFF_S = 2.0
LAND_DETECT_S = 1.5
TAKEOFF_ACCEPT_M = 0.8  # NAV_MC_ALT_RAD: takeoff counts as done within this of the target
MAX_STREAM_HZ = 500.0  # SET_MESSAGE_INTERVAL requests above this rate are capped (mock)
# hard speed caps whatever the parameters say (PX4 parameter metadata maxima of MPC_XY_VEL_MAX,
# MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN)
XY_SPEED_CAP, UP_SPEED_CAP, DOWN_SPEED_CAP = 20.0, 8.0, 4.0


@dataclass(frozen=True)
class StreamDef:
    """A telemetry stream: MAVLink ``name``, default rate (Hz) per profile, boot start time."""

    name: str
    full_hz: float
    lite_hz: float
    start_s: float


# Rates: capture (PX4 SITL Onboard link) unless noted. LOCAL_POSITION_NED defaults to 30 Hz
# (capture, before SET_MESSAGE_INTERVAL); GLOBAL_POSITION_INT 50 Hz and HOME_POSITION 0.5 Hz are
# PX4 source defaults for the Onboard mode (the captures only show the GCS-requested 10 Hz/1 Hz).
STREAM_CATALOG: tuple[StreamDef, ...] = (
    StreamDef("HEARTBEAT", 1.0, 1.0, 1.38),
    StreamDef("SYS_STATUS", 5.0, 5.0, 0.55),
    StreamDef("EXTENDED_SYS_STATE", 5.0, 5.0, 0.55),
    StreamDef("ATTITUDE", 100.0, 100.0, 1.90),
    StreamDef("ATTITUDE_QUATERNION", 50.0, 0.0, 1.90),
    StreamDef("HIGHRES_IMU", 50.0, 0.0, 0.40),
    StreamDef("LOCAL_POSITION_NED", 30.0, 30.0, 0.55),
    StreamDef("ODOMETRY", 30.0, 0.0, 0.55),
    StreamDef("GLOBAL_POSITION_INT", 50.0, 50.0, 0.55),
    StreamDef("GPS_RAW_INT", 8.0, 8.0, 0.38),
    StreamDef("TIMESYNC", 10.0, 0.0, 0.48),
    StreamDef("ALTITUDE", 10.0, 0.0, 0.48),
    StreamDef("DISTANCE_SENSOR", 10.0, 0.0, 0.48),
    StreamDef("SERVO_OUTPUT_RAW", 10.0, 0.0, 0.48),
    StreamDef("ATTITUDE_TARGET", 10.0, 0.0, 0.55),
    StreamDef("POSITION_TARGET_LOCAL_NED", 10.0, 10.0, 0.55),
    StreamDef("VFR_HUD", 10.0, 0.0, 0.55),
    StreamDef("HOME_POSITION", 0.5, 0.5, 1.38),
    StreamDef("MISSION_CURRENT", 1.0, 0.0, 1.18),
    StreamDef("ESTIMATOR_STATUS", 1.0, 0.0, 1.38),
    StreamDef("OPEN_DRONE_ID_LOCATION", 1.0, 0.0, 1.38),
    StreamDef("OPEN_DRONE_ID_SYSTEM", 1.0, 0.0, 1.38),
    StreamDef("PING", 1.0, 0.0, 1.38),
    StreamDef("SCALED_PRESSURE", 1.0, 0.0, 1.38),
    StreamDef("SYSTEM_TIME", 1.0, 0.0, 1.38),
    StreamDef("LINK_NODE_STATUS", 1.0, 0.0, 1.38),
    StreamDef("TIME_ESTIMATE_TO_TARGET", 0.5, 0.0, 2.20),
    StreamDef("BATTERY_STATUS", 0.5, 0.5, 2.40),
    StreamDef("VIBRATION", 0.5, 0.0, 2.40),
    StreamDef("CURRENT_MODE", 0.5, 0.5, 2.40),
    StreamDef("CURRENT_EVENT_SEQUENCE", 1.0 / 3.0, 0.0, 0.44),
    # SITL ground truth: sent only when asked for (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE)
    StreamDef("HIL_STATE_QUATERNION", 0.0, 0.0, 0.55),
)
PROFILES = ("full", "lite")

#: Default stream rates (Hz) on PX4's GCS link (udp 18570+i → 14550), ``full``: as measured on
#: real PX4 SITL's GCS link in the fleet-truth flights (the observer only added
#: HIL_STATE_QUATERNION and ESTIMATOR_STATUS); ``lite`` (the mock's default): what a GCS or an
#: outside observer needs at low cost; ``off``: no GCS link. Anything else on request.
GCS_LINK_STREAMS: dict[str, dict[str, float]] = {
    "full": {
        "HEARTBEAT": 1.0, "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0, "ATTITUDE": 48.0,
        "ATTITUDE_QUATERNION": 48.0, "LOCAL_POSITION_NED": 49.5, "GLOBAL_POSITION_INT": 46.5,
        "GPS_RAW_INT": 5.0, "SERVO_OUTPUT_RAW": 49.5, "ATTITUDE_TARGET": 49.5,
        "POSITION_TARGET_LOCAL_NED": 49.5, "VFR_HUD": 4.0, "ALTITUDE": 1.0,
        "MISSION_CURRENT": 1.0, "OPEN_DRONE_ID_LOCATION": 1.0, "OPEN_DRONE_ID_SYSTEM": 1.0,
        "SCALED_PRESSURE": 1.0, "BATTERY_STATUS": 0.5, "DISTANCE_SENSOR": 0.5,
        "HOME_POSITION": 0.5, "VIBRATION": 0.1,
    },
    "lite": {
        "HEARTBEAT": 1.0, "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0,
        "GLOBAL_POSITION_INT": 5.0, "GPS_RAW_INT": 5.0, "HOME_POSITION": 0.5,
        "BATTERY_STATUS": 0.5,
    },
    "off": {},
}
GCS_LINK_PROFILES = tuple(GCS_LINK_STREAMS)
_STREAM_BY_NAME = {s.name: s for s in STREAM_CATALOG}
_STREAM_BY_ID = {SPECS[s.name].msgid: s for s in STREAM_CATALOG}
# messages REQUEST_MESSAGE can produce besides the streams
_REQUESTABLE_EXTRA = {148: "AUTOPILOT_VERSION", 49: "GPS_GLOBAL_ORIGIN", 242: "HOME_POSITION"}

_S = {name: sp.struct for name, sp in SPECS.items()}
_CRC = struct.Struct("<H")
_NAN = float("nan")
_TWO_PI = 2.0 * math.pi

# MAV_CMD numbers
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_DO_CHANGE_SPEED = 178
CMD_DO_SET_HOME = 179
CMD_DO_REPOSITION = 192
CMD_COMPONENT_ARM_DISARM = 400
CMD_GET_MESSAGE_INTERVAL = 510
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512
CMD_REQUEST_PROTOCOL_VERSION = 519
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520

# AUTOPILOT_VERSION.capabilities: MISSION_FLOAT|PARAM_FLOAT|MISSION_INT|COMMAND_INT|
# PARAM_ENCODE_BYTEWISE|SET_ATTITUDE_TARGET|SET_POSITION_TARGET_LOCAL_NED|
# SET_POSITION_TARGET_GLOBAL_INT|MAVLINK2|MISSION_FENCE|MISSION_RALLY (no FTP: not modelled)
_CAPABILITIES = 1 | 2 | 4 | 8 | 16 | 128 | 256 | 512 | 8192 | 16384 | 32768
_FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 0  # 1.16.0 dev (capture era)


def validate_home(home: tuple[float, float, float]) -> tuple[float, float, float]:
    """Return ``home`` as floats or raise :class:`SimStubError` naming the bad number."""
    try:
        lat, lon, alt = (float(x) for x in home)
    except (TypeError, ValueError):
        raise SimStubError(f"home must be (lat_deg, lon_deg, alt_m), got {home!r}") from None
    if not (math.isfinite(lat) and -90.0 < lat < 90.0):
        raise SimStubError(f"home latitude must be in (-90, 90) deg, got {lat}")
    if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise SimStubError(f"home longitude must be in [-180, 180] deg, got {lon}")
    if not (math.isfinite(alt) and -500.0 <= alt <= 9000.0):
        raise SimStubError(f"home altitude must be in [-500, 9000] m AMSL, got {alt}")
    return lat, lon, alt


@dataclass
class VehicleCounters:
    """Datagram/packet counters of one vehicle (a snapshot)."""

    rx_datagrams: int = 0
    rx_packets: int = 0
    rx_malformed: int = 0  # datagrams with garbage, truncation or a bad CRC
    rx_unknown: int = 0  # well-framed packets of message ids the mock does not know
    rx_ignored: int = 0  # valid packets not for this vehicle or not handled
    rx_dropped: int = 0  # dropped by a loss fault or because the vehicle is dead
    tx_packets: int = 0
    tx_dropped: int = 0  # dropped by a loss fault or because the vehicle is dead
    tx_errors: int = 0  # socket errors (e.g. send buffer full)
    rx_errors: int = 0  # valid packets whose handling raised (logged; should stay 0)


class StreamState:
    """A configured stream of one vehicle (rate, current wheel entry, builder)."""

    __slots__ = ("name", "spec", "build", "interval", "default_interval", "entry", "link")

    def __init__(self, name: str, spec: MsgSpec, build: Callable[[float], bytes | None],
                 link: GcsLink | None = None) -> None:
        self.name = name
        self.spec = spec
        self.build = build
        self.interval = 0.0
        self.default_interval = 0.0
        self.entry: list | None = None
        self.link = link  # None: the API link


class GcsLink:
    """PX4's second MAVLink instance: the GCS link (SITL: udp 18570+i → 14550). Its own
    socket, peer, sequence numbers and streams; no link faults (they model the API link)."""

    def __init__(self, vehicle: MockVehicle, bind: tuple[str, int], remote: tuple[str, int],
                 profile: str) -> None:
        self.vehicle = vehicle
        self.bind_address = bind
        self.remote = remote
        self.profile = profile
        self.enc = Encoder(vehicle.sysid, vehicle.compid)
        self.sock: socket.socket | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self.streams: dict[str, StreamState] = {}
        self.tx_packets = 0
        self.rx_packets = 0


@dataclass
class _Setpoint:
    """The last SET_POSITION_TARGET_*, resolved to NED at reception."""

    pos: list[float | None] = field(default_factory=lambda: [None, None, None])
    vel: list[float | None] = field(default_factory=lambda: [None, None, None])
    yaw: float | None = None
    yaw_rate: float | None = None


class _Proto(asyncio.DatagramProtocol):
    def __init__(self, vehicle: MockVehicle) -> None:
        self.v = vehicle

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.v._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP errors on loopback
        self.v._tx_errors += 1


class _GcsProto(asyncio.DatagramProtocol):
    def __init__(self, link: GcsLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        v = self.link.vehicle
        if v.dead == "freeze" or not v.started:
            return
        v._process_datagram(data, addr, v._now(), self.link)

    def error_received(self, exc: Exception) -> None:  # nobody listens on 14550: normal
        pass


class MockVehicle:
    """PX4 SITL instance ``instance`` as seen on its MAVLink API link.

    ``home``: (lat, lon, alt AMSL) of the start point on the ground; it is the vehicle's
    GPS_GLOBAL_ORIGIN and initial home, and LOCAL_POSITION_NED is (0, 0, 0) there.
    ``ports``: ``"px4"``, ``"wide"`` or a :class:`~sim_stub.ports.PortScheme`.
    ``faults``: :class:`~sim_stub.faults.Faults`. ``params``: parameter overrides by name.
    ``seed``: seeds loss/noise randomness and stream phases. ``clock``: seconds, monotonic
    (default: the event loop's clock). ``profile``: ``"full"`` (every stream PX4 sent in the
    captures) or ``"lite"`` (what clients rely on). ``boot_time_scale``: multiplies the boot
    timeline (1.0 = PX4's; tests that are not about boot may shorten it). ``scheduler``: share
    a :class:`~sim_stub.scheduler.Scheduler` (a :class:`MockFleet` does); by default the vehicle
    runs its own. ``sysid``: MAVLink system id (default PX4's ``instance + 1``; must be given
    from instance 254 on, since sysids are 8-bit). ``estimator``: the estimate-error profile
    (``"px4-sih"`` like real PX4 SITL, ``"rtk"``, ``"ideal"`` = the estimate is the truth; see
    :mod:`sim_stub.estimator`), ``estimator_shared``: the same error sequence as every other
    shared vehicle of the scheduler (SIH-like). ``gcs_link``: default stream set of PX4's GCS
    link (``"lite"``, ``"full"`` or ``"off"``; ports from the scheme, none if it has no GCS link).

    Use ``async with MockVehicle(0) as v:`` or ``await v.start()`` / ``await v.stop()``.
    """

    def __init__(
        self,
        instance: int = 0,
        *,
        home: tuple[float, float, float] = DEFAULT_HOME,
        ports: str | PortScheme = "px4",
        faults: Faults | None = None,
        params: dict[str, float] | None = None,
        seed: int = 0,
        clock: Callable[[], float] | None = None,
        profile: str = "full",
        boot_time_scale: float = 1.0,
        scheduler: Scheduler | None = None,
        sysid: int | None = None,
        estimator: str = "px4-sih",
        estimator_shared: bool = False,
        gcs_link: str = "lite",
    ) -> None:
        if instance < 0:
            raise SimStubError(f"instance must be >= 0, got {instance}")
        if sysid is None:
            if instance > 253:
                raise SimStubError(
                    f"instance {instance}: PX4's sysid = instance+1 exceeds 254 (MAVLink sysids "
                    "are 8-bit, 255 is the GCS); pass sysid= explicitly"
                )
            sysid = instance + 1
        if not 1 <= sysid <= 254:
            raise SimStubError(f"sysid must be in 1..254, got {sysid}")
        if profile not in PROFILES:
            raise SimStubError(f"profile must be one of {PROFILES}, got {profile!r}")
        if not 0.0 < boot_time_scale <= 10.0:
            raise SimStubError(f"boot_time_scale must be in (0, 10], got {boot_time_scale}")
        try:
            self.estimator: EstimatorProfile = estimator_profile(estimator)
        except ValueError as exc:
            raise SimStubError(str(exc)) from None
        if gcs_link not in GCS_LINK_STREAMS:
            raise SimStubError(f"gcs_link must be one of {', '.join(GCS_LINK_PROFILES)}, got "
                               f"{gcs_link!r}")
        self.estimator_shared = bool(estimator_shared)
        self.instance = instance
        self.sysid = sysid
        self.compid = 1
        self.origin = validate_home(home)
        self.ports = resolve_port_scheme(ports)
        self.ports.check(instance + 1)
        self.faults = faults or Faults()
        try:
            self.params = px4.param_table(params, sysid=self.sysid)
        except KeyError as exc:
            raise SimStubError(str(exc.args[0])) from None
        self.seed = seed
        self.profile = profile
        self.boot_time_scale = boot_time_scale
        self._clock = clock
        self._own_scheduler = scheduler is None
        self._sched = scheduler or Scheduler(1, clock=clock, seed=seed * 1000 + instance)
        self.bind_address = (self.ports.host, self.ports.vehicle_port(instance))
        self.gcs_address = (self.ports.host, self.ports.gcs_port(instance))
        self._remote = self.gcs_address
        gport = self.ports.gcs_link_port(instance)
        self.gcs_link: GcsLink | None = None
        if gport is not None and gcs_link != "off":
            self.gcs_link = GcsLink(self, (self.ports.host, gport),
                                    (self.ports.host, self.ports.gcs_link_remote(instance)),
                                    gcs_link)
        self._reply: GcsLink | None = None  # the link of the datagram being handled
        self._push_until: float | None = None
        self._rng = random.Random(hash((seed, instance, "link")))
        self._enc = Encoder(self.sysid, self.compid)
        self._parser = DatagramParser(
            {84: fast_decoder("SET_POSITION_TARGET_LOCAL_NED"), 0: fast_decoder("HEARTBEAT")}
        )
        self._sock: socket.socket | None = None
        self._link_plain = False  # no fault, not dead: the fast send path
        self._transport: asyncio.DatagramTransport | None = None
        self.slot = -1
        self.t0 = 0.0
        self._tb0 = 0.0
        self.wall_t0 = 0.0
        self.started = False
        # counters
        self._rx_datagrams = self._rx_packets = self._rx_malformed = 0
        self._rx_unknown = self._rx_ignored = self._rx_dropped = 0
        self._tx_packets = self._tx_dropped = self._tx_errors = self._rx_errors = 0
        self._tx_bytes = self._rx_bytes = 0
        self._reset_state()

    # ------------------------------------------------------------------------------------------
    # state
    def _reset_state(self) -> None:
        self.armed = False
        self.arm_time = 0.0
        self.intended: Mode = MODE_BY_NAME["AUTO.LOITER"]  # capture: boot mode AUTO.LOITER
        self.failsafe: Mode | None = None
        self.landed_state = LANDED_ON_GROUND
        self.phase = "ground"  # ground | spoolup | idle | ramp | flying | landed
        self.phase_t = 0.0
        self.took_off = False
        self.touchdown_t: float | None = None
        self.landed_t: float | None = None
        self.sp = _Setpoint()
        self.sp_time: float | None = None
        self.sp_ever = False
        self.sp_fresh = False
        self.hold: list[float] | None = None
        self.takeoff_z = 0.0
        self.rtl_phase = ""
        self.cruise_speed = None
        self.home: tuple[float, float, float] | None = None  # lat, lon, alt
        self.home_ned = (0.0, 0.0, 0.0)
        self.home_q = (1.0, 0.0, 0.0, 0.0)
        self.home_time_us = 0
        self.origin_time_us = 0
        self.ready = False
        self.stage = 0
        self.dead: str | None = None
        self.statustexts: list[tuple[float, int, str]] = []
        self.mode_log: list[tuple[float, str, bool]] = []
        self._text_id = 0
        self._event_seq = 0xFFF6  # capture: PX4's event sequence started at 65526
        self._ping_seq = 0
        self._streams: dict[str, StreamState] = {}
        self._delay_out: deque = deque()
        self._delay_in: deque = deque()
        self._last_gcs_heartbeat: float | None = None
        self.ignored_msgids: Counter[int] = Counter()  # valid messages the mock does not handle
        self.commands: Counter[int] = Counter()  # MAV_CMD ids received (for tests/diagnostics)
        # (uptime, MAV_CMD, params 1..7, MAV_RESULT) of the last 1000 commands
        self.command_log: deque[tuple[float, int, tuple[float, ...], int]] = deque(maxlen=1000)
        self._link_stat = (0.0, 0, 0)

    # ------------------------------------------------------------------------------------------
    # lifecycle
    async def __aenter__(self) -> MockVehicle:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Bind the UDP socket and start booting (streams begin ~0.4 s later)."""
        if self.started:
            return
        loop = asyncio.get_running_loop()
        if self._own_scheduler:
            self._sched.start()
        elif not self._sched.running:
            raise SimStubError("the shared scheduler must be started before its vehicles")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.bind(self.bind_address)
        except OSError as exc:
            sock.close()
            if self._own_scheduler:
                self._sched.stop()
            raise SimStubError(
                f"vehicle {self.instance}: cannot bind UDP {self.bind_address[0]}:"
                f"{self.bind_address[1]}: {exc.strerror or exc}"
            ) from None
        sock.setblocking(False)
        gl = self.gcs_link
        if gl is not None:
            gsock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                gsock.bind(gl.bind_address)
            except OSError as exc:
                gsock.close()
                sock.close()
                if self._own_scheduler:
                    self._sched.stop()
                raise SimStubError(
                    f"vehicle {self.instance}: cannot bind the GCS link UDP "
                    f"{gl.bind_address[0]}:{gl.bind_address[1]}: {exc.strerror or exc}"
                ) from None
            gsock.setblocking(False)
            gl.sock = gsock
            gl.transport, _ = await loop.create_datagram_endpoint(lambda: _GcsProto(gl),
                                                                  sock=gsock)
        self._sock = sock
        self._link_plain = not self.faults.affects_link
        self._transport, _ = await loop.create_datagram_endpoint(lambda: _Proto(self), sock=sock)
        self.slot = self._sched.attach(self)
        self._sched.est.configure(self.slot, self.estimator, self.estimator_shared)
        self.t0 = self._sched.now()
        # time_boot 0 (clamped so that no message carries a negative time)
        self._tb0 = self.t0 + min(BOOT["time_boot_zero"] * self.boot_time_scale, 0.3)
        self.wall_t0 = time.time()
        self._reset_state()
        self._sched.airborne[self.slot] = False
        self._sched.frozen[self.slot] = False
        self._sched.u[self.slot] = 0.0
        self._sched.yaw_sp[self.slot] = _NAN
        if self.faults.gps_noise_m > 0.0:
            self._sched.set_noise(
                self.slot, self.faults.gps_noise_m, self.seed * 1000 + self.instance
            )
        d = self._sched.dyn
        s = self.slot
        d.p[s] = d.v[s] = d.vf[s] = d.vs[s] = d.c[s] = d.acc[s] = 0.0
        d.yaw[s] = d.yaw_rate[s] = d.roll[s] = d.pitch[s] = 0.0
        if self._own_scheduler:
            self._sched._export()
        self._setup_streams()
        self.started = True

    async def stop(self) -> None:
        """Stop streaming and close the socket."""
        if not self.started:
            return
        self.started = False
        for st in self._streams.values():
            st.entry = None
        self._sched.delayed.discard(self)
        self._sched.detach(self)
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        self._sock = None
        gl = self.gcs_link
        if gl is not None:
            for st in gl.streams.values():
                st.entry = None
            if gl.transport is not None:
                gl.transport.close()
                gl.transport = None
            gl.sock = None
        if self._own_scheduler:
            self._sched.stop()

    def kill(self, how: str = "silent") -> None:
        """Make the vehicle die now: ``"silent"`` (link dead, autopilot keeps running) or
        ``"freeze"`` (keeps streaming, holds position, ignores everything); see
        :class:`~sim_stub.faults.Faults`."""
        if how not in ("silent", "freeze"):
            raise SimStubError(f"kill how must be 'silent' or 'freeze', got {how!r}")
        if self.dead is not None:
            return
        self.dead = how
        self._link_plain = False
        if how == "silent":
            for st in self._streams.values():
                st.entry = None
            self._delay_out.clear()
        else:
            self._sched.frozen[self.slot] = True
        self._log_mode(self._now(), f"DEAD({how})")

    def push(self, north_m_s: float, east_m_s: float, duration_s: float) -> None:
        """Carry the vehicle along at (north, east) m/s for ``duration_s`` whatever it is told
        (a gust it cannot hold against; its estimate moves along): fault injection on demand,
        like :class:`~sim_stub.faults.Faults` ``push_*``."""
        if not (math.isfinite(north_m_s) and math.isfinite(east_m_s) and duration_s > 0):
            raise SimStubError("push needs finite velocities and a duration > 0 s")
        self._sched.push[self.slot] = (north_m_s, east_m_s, 0.0)
        self._push_until = self._now() + duration_s

    # ------------------------------------------------------------------------------------------
    # introspection (true state)
    def _now(self) -> float:
        return self._sched.now()

    @property
    def uptime(self) -> float:
        return self._now() - self.t0 if self.started else 0.0

    @property
    def position_ned(self) -> tuple[float, float, float]:
        """True position [m] relative to this vehicle's own origin (its start point)."""
        x, y, z = self._sched.p_true_rows[self.slot]
        return (x, y, z)

    @property
    def velocity_ned(self) -> tuple[float, float, float]:
        """True velocity [m/s] NED."""
        x, y, z = self._sched.v_true_rows[self.slot]
        return (x, y, z)

    @property
    def estimated_position_ned(self) -> tuple[float, float, float]:
        """PX4's estimate of :attr:`position_ned` (what LOCAL_POSITION_NED reports)."""
        x, y, z = self._sched.p_rows[self.slot]
        return (x, y, z)

    @property
    def estimated_velocity_ned(self) -> tuple[float, float, float]:
        """PX4's estimate of :attr:`velocity_ned` (what its velocity controller tracks)."""
        x, y, z = self._sched.v_rows[self.slot]
        return (x, y, z)

    @property
    def global_position(self) -> tuple[float, float, float]:
        """True (lat, lon, alt AMSL)."""
        x, y, z = self.position_ned
        lat, lon = reproject(self.origin[0], self.origin[1], x, y)
        return (lat, lon, self.origin[2] - z)

    @property
    def mode(self) -> Mode:
        """The mode PX4 is flying (a failsafe action overrides the user's intended mode)."""
        return self.failsafe or self.intended

    @property
    def mode_name(self) -> str:
        return self.mode.name

    @property
    def system_status(self) -> int:
        if self.armed:
            return px4.MAV_STATE_CRITICAL if self.failsafe else px4.MAV_STATE_ACTIVE
        return px4.MAV_STATE_STANDBY if self._prearm_ok() else px4.MAV_STATE_UNINIT

    @property
    def base_mode(self) -> int:
        return px4.base_mode(self.mode, self.armed, self.sp_ever)

    @property
    def custom_mode(self) -> int:
        return self.mode.custom_mode

    @property
    def counters(self) -> VehicleCounters:
        return VehicleCounters(
            self._rx_datagrams,
            self._rx_packets,
            self._rx_malformed,
            self._rx_unknown,
            self._rx_ignored,
            self._rx_dropped,
            self._tx_packets,
            self._tx_dropped,
            self._tx_errors,
            self._rx_errors,
        )

    @property
    def endpoint(self) -> str:
        return self.ports.endpoint(self.instance)

    def stream_rates(self) -> dict[str, float]:
        """Configured stream rates in Hz (0 = off)."""
        return {
            n: (1.0 / st.interval if st.interval > 0 else 0.0) for n, st in self._streams.items()
        }

    def __repr__(self) -> str:
        return (
            f"MockVehicle(instance={self.instance}, sysid={self.sysid}, bind={self.bind_address}, "
            f"mode={self.mode_name}, armed={self.armed})"
        )

    # ------------------------------------------------------------------------------------------
    # streams
    def _setup_streams(self) -> None:
        rng = random.Random(hash((self.seed, self.instance, "phase")))
        gl = self.gcs_link
        gcs_rates = GCS_LINK_STREAMS[gl.profile] if gl is not None else {}
        for sd in STREAM_CATALOG:
            build = getattr(self, "_b_" + sd.name.lower())
            hz_api = sd.full_hz if self.profile == "full" else sd.lite_hz
            for link, hz, table in ((None, hz_api, self._streams),
                                    (gl, gcs_rates.get(sd.name, 0.0),
                                     gl.streams if gl is not None else None)):
                if table is None:
                    continue
                st = StreamState(sd.name, SPECS[sd.name], build, link)
                st.default_interval = 1.0 / hz if hz > 0 else 0.0
                st.interval = st.default_interval
                table[sd.name] = st
                if st.interval > 0:
                    phase = rng.uniform(0.0, min(st.interval, 0.1))
                    start = self.t0 + sd.start_s * self.boot_time_scale + phase
                    self._sched.schedule(self, st, start)

    def set_stream_rate(self, name: str, hz: float | None, first_due: float | None = None,
                        link: GcsLink | None = None) -> None:
        """Set a stream's rate in Hz (None = profile default, 0 = off), like SET_MESSAGE_INTERVAL,
        on the API link (default) or on ``link`` (the GCS link).

        The next message goes out at ``first_due`` (default: at once, or at the stream's boot
        start time if that is later)."""
        st = (self._streams if link is None else link.streams)[name]
        if hz is None:
            st.interval = st.default_interval
        else:
            st.interval = 1.0 / min(hz, MAX_STREAM_HZ) if hz > 0 else 0.0
        if st.interval > 0 and (link is not None or self.dead != "silent"):
            now = self._now()
            sd = _STREAM_BY_NAME[name]
            start = max(now + 0.001, self.t0 + sd.start_s * self.boot_time_scale)
            self._sched.schedule(self, st, start if first_due is None else first_due)
        else:
            st.entry = None

    # ------------------------------------------------------------------------------------------
    # output
    def _send(self, spec: MsgSpec, payload: bytes) -> None:
        """Send a reply: on the link whose datagram is being handled (API link otherwise)."""
        if self._reply is None:
            self._send_api(spec, payload)
        else:
            self._send_gcs(self._reply, spec, payload)

    def _send_stream(self, st: StreamState, payload: bytes) -> None:
        """Send one message of stream ``st`` on its link (the scheduler's path)."""
        if st.link is None:
            self._send_api(st.spec, payload)
        else:
            self._send_gcs(st.link, st.spec, payload)

    def _broadcast(self, spec: MsgSpec, payload: bytes) -> None:
        """Send on every link (PX4 sends STATUSTEXT and EVENT on all its MAVLink instances)."""
        self._send_api(spec, payload)
        if self.gcs_link is not None:
            self._send_gcs(self.gcs_link, spec, payload)

    def _send_gcs(self, link: GcsLink, spec: MsgSpec, payload: bytes) -> None:
        if link.sock is None:
            return
        data = link.enc.frame(spec, payload)
        link.tx_packets += 1
        try:
            link.sock.sendto(data, link.remote)
        except OSError:
            pass

    def _send_api(self, spec: MsgSpec, payload: bytes) -> None:
        """Frame ``payload`` (MAVLink 2, zero-truncated, CRC) and send it to the API remote.

        Inlined equivalent of :meth:`Encoder.frame` (this is the hot path: ~390 calls per
        vehicle per second)."""
        payload = payload.rstrip(b"\x00") or b"\x00"
        enc = self._enc
        seq = enc.seq
        enc.seq = (seq + 1) & 0xFF
        body = bytes((len(payload), 0, 0, seq, self.sysid, 1)) + spec.id3 + payload
        data = b"\xfd" + body + _CRC.pack(mcrf4xx(spec.crc_byte, mcrf4xx(body, 0xFFFF)))
        self._tx_packets += 1
        self._tx_bytes += len(data)
        if self._link_plain:
            try:
                self._sock.sendto(data, self._remote)  # type: ignore[union-attr]
            except OSError:
                self._tx_errors += 1
            return
        if self.dead == "silent":
            self._tx_dropped += 1
            return
        f = self.faults
        if f.loss_pct > 0.0 and self._rng.random() * 100.0 < f.loss_pct:
            self._tx_dropped += 1
            return
        if f.latency_s > 0.0:
            self._delay_out.append((self._now() + f.latency_s, data, self._remote))
            self._sched.delayed.add(self)
            return
        try:
            self._sock.sendto(data, self._remote)  # type: ignore[union-attr]
        except OSError:
            self._tx_errors += 1

    def _flush_delayed(self, now: float) -> None:
        q = self._delay_out
        while q and q[0][0] <= now:
            _, data, addr = q.popleft()
            if self._sock is not None and self.dead != "silent":
                try:
                    self._sock.sendto(data, addr)
                except OSError:
                    self._tx_errors += 1
        qi = self._delay_in
        while qi and qi[0][0] <= now:
            _, data, addr = qi.popleft()
            self._process_datagram(data, addr, now)
        if not q and not qi:
            self._sched.delayed.discard(self)

    def _send_named(self, name: str, payload: bytes) -> None:
        self._send(SPECS[name], payload)

    def _text(self, severity: int, text: str) -> None:
        """STATUSTEXT as PX4 formats it: text + TAB, 50-byte chunks sharing an id (capture)."""
        text = text + "\t"
        self.statustexts.append((self._now() - self.t0, severity, text))
        msg_id = self._text_id
        self._text_id = (self._text_id + 1) & 0xFFFF
        chunks = px4.statustext_chunks(text)
        pack = _S["STATUSTEXT"].pack
        spec = SPECS["STATUSTEXT"]
        for seq, chunk in enumerate(chunks):
            self._broadcast(spec, pack(severity, chunk, msg_id, seq))

    def _event(self, tpl: px4.EventTemplate, args: bytes | None = None) -> None:
        seq = self._event_seq
        self._event_seq = (seq + 1) & 0xFFFF
        self._broadcast(
            SPECS["EVENT"],
            _S["EVENT"].pack(
                tpl.event_id,
                self._tboot_ms(self._now()),
                seq,
                0,
                0,
                tpl.log_levels,
                tpl.args if args is None else args,
            ),
        )

    def _events(self, burst: tuple[px4.EventTemplate, ...]) -> None:
        for tpl in burst:
            self._event(tpl)

    def _ack(self, command: int, result: int, tsys: int, tcomp: int) -> None:
        self._send_named("COMMAND_ACK", _S["COMMAND_ACK"].pack(command, result, 0, 0, tsys, tcomp))

    def _param_value(self, name: str) -> None:
        p = self.params[name]
        index = list(self.params).index(name)
        self._send_named(
            "PARAM_VALUE",
            _S["PARAM_VALUE"].pack(
                px4.param_to_wire(p), len(self.params), index, name.encode(), p.type
            ),
        )

    def _log_mode(self, now: float, what: str) -> None:
        self.mode_log.append((now - self.t0, what, self.armed))

    # ------------------------------------------------------------------------------------------
    # helpers
    def _tboot_ms(self, now: float) -> int:
        t = int((now - self._tb0) * 1000.0)
        return t if t > 0 else 0

    def _tboot_us(self, now: float) -> int:
        t = int((now - self._tb0) * 1000.0)
        return t * 1000 if t > 0 else 0

    def _param(self, name: str) -> float:
        return self.params[name].value

    def _boot_at(self, key: str) -> float:
        return BOOT[key] * self.boot_time_scale

    def _can_run(self, mode: Mode) -> bool:
        if mode.needs == "position":
            return True
        if mode.needs == "offboard":
            return self.sp_fresh
        return False  # manual control (no RC), mission (none), unsupported modes

    def _prearm_ok(self) -> bool:
        return self.ready and self._can_run(self.intended)

    def _pos(self) -> list[float]:
        """The estimated position: PX4's position loops close on it."""
        return self._sched.p_rows[self.slot]

    def _yaw(self) -> float:
        return self._sched.att_rows[self.slot][2]

    # ------------------------------------------------------------------------------------------
    # input
    def _on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        self._rx_datagrams += 1
        self._rx_bytes += len(data)
        if self.dead is not None:
            self._rx_dropped += 1
            return
        f = self.faults
        if f.loss_pct > 0.0 and self._rng.random() * 100.0 < f.loss_pct:
            self._rx_dropped += 1
            return
        if f.latency_s > 0.0:
            self._delay_in.append((self._now() + f.latency_s, data, addr))
            self._sched.delayed.add(self)
            return
        self._process_datagram(data, addr, self._now())

    def _process_datagram(self, data: bytes, addr: tuple[str, int], now: float,
                          link: GcsLink | None = None) -> None:
        if self.stage < len(_STAGES) and self.dead is None:  # boot state is current for commands
            self._boot_stages(now, now - self.t0)
        packets, malformed, unknown = self._parser.parse(data)
        if malformed:
            self._rx_malformed += 1
        self._rx_unknown += unknown
        if not packets:
            return
        if link is None:
            self._remote = addr  # answers whoever last sent to it
        else:
            link.remote = addr
            link.rx_packets += len(packets)
        self._reply = link
        try:
            self._handle_packets(packets, now)
        finally:
            self._reply = None

    def _handle_packets(self, packets: list, now: float) -> None:
        for pk in packets:
            self._rx_packets += 1
            if pk.src_system == self.sysid:
                self._rx_ignored += 1
                continue
            handler = _HANDLERS.get(pk.msgid)
            if handler is None:
                self._rx_ignored += 1
                self.ignored_msgids[pk.msgid] += 1
                continue
            try:
                handler(self, pk.msg, pk.src_system, pk.src_component, now)
            except Exception:  # a pathological value must not break the link: count, log
                self._rx_errors += 1
                if self._rx_errors <= 3:
                    src = f"{pk.src_system}/{pk.src_component}"
                    log.exception(
                        "sim_stub vehicle %d: msgid %d from %s failed", self.instance, pk.msgid, src
                    )

    def _for_me(self, tsys: int, tcomp: int) -> bool:
        return (tsys == self.sysid or tsys == 0) and (tcomp == self.compid or tcomp == 0)

    def _h_heartbeat(self, msg: dict, ssys: int, scomp: int, now: float) -> None:
        self._last_gcs_heartbeat = now

    def _h_command(self, msg: object, ssys: int, scomp: int, now: float) -> None:
        m = msg
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        is_int = m.get_msgId() == 75  # type: ignore[attr-defined]
        p = [m.param1, m.param2, m.param3, m.param4]  # type: ignore[attr-defined]
        if is_int:
            p += [m.x / 1e7, m.y / 1e7, m.z]  # type: ignore[attr-defined]
        else:
            p += [m.param5, m.param6, m.param7]  # type: ignore[attr-defined]
        cmd = m.command  # type: ignore[attr-defined]
        handler = _COMMANDS.get(cmd)
        self.commands[cmd] += 1
        if handler is None:
            result = MAV_RESULT_UNSUPPORTED
        else:
            result = handler(self, p, ssys, scomp, now, is_int)
        self.command_log.append((now - self.t0, cmd, tuple(p), result))
        self._ack(cmd, result, ssys, scomp)

    def _h_setpoint_local(self, m: dict, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m["target_system"], m["target_component"]):  # type: ignore[arg-type]
            self._rx_ignored += 1
            return
        frame = m["coordinate_frame"]
        if frame not in (1, 7, 8, 9):  # LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED
            self._rx_ignored += 1
            return
        mask = int(m["type_mask"])  # type: ignore[call-overload]
        x, y, z = m["x"], m["y"], m["z"]
        vx, vy, vz = m["vx"], m["vy"], m["vz"]
        body = frame in (8, 9)
        if body:
            yaw = self._yaw()
            c, s = math.cos(yaw), math.sin(yaw)
            x, y = c * x - s * y, s * x + c * y  # type: ignore[operator]
            vx, vy = c * vx - s * vy, s * vx + c * vy  # type: ignore[operator]
        p = self._pos()
        offset = frame != 1
        sp = _Setpoint()
        for i, (val, base) in enumerate(((x, p[0]), (y, p[1]), (z, p[2]))):
            if not mask & (1 << i) and math.isfinite(val):  # type: ignore[arg-type]
                sp.pos[i] = val + base if offset else val  # type: ignore[operator]
        for i, val in enumerate((vx, vy, vz)):
            if not mask & (8 << i) and math.isfinite(val):  # type: ignore[arg-type]
                sp.vel[i] = val  # type: ignore[assignment]
        yaw_sp, yaw_rate = m["yaw"], m["yaw_rate"]
        if not mask & 0x400 and math.isfinite(yaw_sp):  # type: ignore[arg-type]
            sp.yaw = yaw_sp  # type: ignore[assignment]
        if not mask & 0x800 and math.isfinite(yaw_rate):  # type: ignore[arg-type]
            sp.yaw_rate = yaw_rate  # type: ignore[assignment]
        self._accept_setpoint(sp, now)

    def _h_setpoint_global(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        mask = int(m.type_mask)  # type: ignore[attr-defined]
        sp = _Setpoint()
        if not mask & 0x3:
            x, y = project(self.origin[0], self.origin[1], m.lat_int / 1e7, m.lon_int / 1e7)  # type: ignore[attr-defined]
            sp.pos[0], sp.pos[1] = x, y
        if not mask & 0x4:
            alt = m.alt  # type: ignore[attr-defined]
            frame = m.coordinate_frame  # type: ignore[attr-defined]
            if frame in (3, 6):  # relative to home
                alt += self.home[2] if self.home else self.origin[2]
            sp.pos[2] = self.origin[2] - alt
        for i, name in enumerate(("vx", "vy", "vz")):
            if not mask & (8 << i):
                sp.vel[i] = getattr(m, name)
        if not mask & 0x400 and math.isfinite(m.yaw):  # type: ignore[attr-defined]
            sp.yaw = m.yaw  # type: ignore[attr-defined]
        if not mask & 0x800 and math.isfinite(m.yaw_rate):  # type: ignore[attr-defined]
            sp.yaw_rate = m.yaw_rate  # type: ignore[attr-defined]
        self._accept_setpoint(sp, now)

    def _accept_setpoint(self, sp: _Setpoint, now: float) -> None:
        self.sp = sp
        self.sp_time = now
        self.sp_ever = True
        if not self.sp_fresh:
            self.sp_fresh = True
            if self.ready:
                self._events(px4.HEALTH_BURST_READY)
        # a velocity setpoint acts at once in offboard (no wait for the 50 Hz logic)
        if self.armed and self.mode.name == "OFFBOARD" and self.phase == "flying":
            self._command_offboard()

    def _h_param_request_read(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        idx = m.param_index  # type: ignore[attr-defined]
        if idx >= 0:
            names = list(self.params)
            if idx < len(names):
                self._param_value(names[idx])
            return
        name = _param_name(m.param_id)  # type: ignore[attr-defined]
        if name in self.params:
            self._param_value(name)
        # capture: a nonexistent name gets no reply at all

    def _h_param_request_list(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        for name in self.params:
            self._param_value(name)

    def _h_param_set(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        name = _param_name(m.param_id)  # type: ignore[attr-defined]
        p = self.params.get(name)
        if p is None:
            self._text(px4.SEV_INFO, f"[pm] unknown param: {name}")
            return
        value = px4.param_from_wire(m.param_value, p.type)  # type: ignore[attr-defined]
        if not math.isfinite(value):
            return
        self.params[name] = px4.Param(name, value, p.type)
        self._param_value(name)

    def _h_timesync(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if m.tc1 == 0:  # type: ignore[attr-defined]
            self._send_named("TIMESYNC", _S["TIMESYNC"].pack(self._tboot_us(now) * 1000, m.ts1))  # type: ignore[attr-defined]

    def _h_ping(self, m: object, ssys: int, scomp: int, now: float) -> None:
        # PX4: a PING with target 0/0 is a request; answer it to the sender with the same fields
        if m.target_system == 0 and m.target_component == 0:  # type: ignore[attr-defined]
            self._send_named("PING", _S["PING"].pack(m.time_usec, m.seq, ssys, scomp))  # type: ignore[attr-defined]

    def _h_mission_request_list(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        mtype = getattr(m, "mission_type", 0)
        self._send_named("MISSION_COUNT", _S["MISSION_COUNT"].pack(0, ssys, scomp, mtype))

    # ------------------------------------------------------------------------------------------
    # commands (return a MAV_RESULT; messages they produce are sent before the ACK)
    def _c_arm_disarm(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        action = round(p[0]) if math.isfinite(p[0]) else -1
        forced = math.isfinite(p[1]) and round(p[1]) == 21196
        if action == 1:
            return self._arm(now, forced)
        if action == 0:
            return self._disarm(now, "external command", forced)
        self._text(px4.SEV_CRITICAL, f"Unsupported ARM_DISARM param: {p[0]:.3f}")
        return MAV_RESULT_UNSUPPORTED

    def _arm(self, now: float, forced: bool) -> int:
        if self.armed:
            return MAV_RESULT_ACCEPTED
        if not forced and not self._prearm_ok():
            self._text(px4.SEV_CRITICAL, "Arming denied: Resolve system health failures first")
            self._event(px4.EVENTS["arming_denied"])
            return MAV_RESULT_TEMPORARILY_REJECTED
        self.armed = True
        self.arm_time = now
        self._sched.est.start(self.slot)  # the estimate starts to wander (reported 0,0,0 before)
        self.took_off = False
        self.phase = "spoolup"
        self.phase_t = now
        self.failsafe = None
        self.hold = list(self._pos())
        self._text(px4.SEV_INFO, "Armed by external command")
        self._event(px4.EVENTS["armed"])
        self._set_home(now)  # capture: home is re-set at arming
        self._log_mode(now, self.mode_name)
        return MAV_RESULT_ACCEPTED

    def _disarm(self, now: float, reason: str, forced: bool = False) -> int:
        if not self.armed:
            return MAV_RESULT_ACCEPTED  # capture: DISARM while disarmed is ACCEPTED, no text
        if not forced and self.landed_state != LANDED_ON_GROUND and self.phase == "flying":
            self._text(px4.SEV_CRITICAL, "Disarming denied: not landed")
            return MAV_RESULT_TEMPORARILY_REJECTED
        self.armed = False
        self._text(px4.SEV_INFO, f"Disarmed by {reason}")
        self._event(px4.EVENTS["disarmed"], bytes((px4.ARM_REASON.get(reason, 4),)))
        if self.phase in ("flying", "landed") and self.took_off:
            self._set_home(now)  # capture: home re-set to the landing point at disarm
        self.failsafe = None  # PX4: the user intention returns to the mode set before
        self.phase = "ground"
        self.took_off = False
        self.landed_state = LANDED_ON_GROUND
        self._sched.airborne[self.slot] = False
        self._sched.u[self.slot] = 0.0
        self._log_mode(now, self.mode_name)
        return MAV_RESULT_ACCEPTED

    def _c_set_mode(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        base = int(p[0]) if math.isfinite(p[0]) else 0
        if not base & px4.FLAG_CUSTOM:
            return MAV_RESULT_DENIED  # base-mode-only requests are not modelled
        main = int(p[1]) if math.isfinite(p[1]) else 0
        sub = int(p[2]) if math.isfinite(p[2]) else 0
        mode = px4.mode_from_set_mode(main, sub)
        if mode is None:
            if main == 4:
                self._text(px4.SEV_CRITICAL, "Unsupported auto mode")
                return MAV_RESULT_TEMPORARILY_REJECTED
            return MAV_RESULT_ACCEPTED  # PX4: an unknown main mode changes nothing
        return self._change_mode(mode, now, scomp)

    def _change_mode(self, mode: Mode, now: float, scomp: int = 190) -> int:
        """PX4's UserModeIntention: any mode while disarmed, only runnable modes while armed."""
        if self.armed and not self._can_run(mode):
            if scomp == 190:
                self._text(
                    px4.SEV_CRITICAL, f"Switching to {mode.label} is currently not available"
                )
            return MAV_RESULT_TEMPORARILY_REJECTED
        self._enter_mode(mode, now)
        return MAV_RESULT_ACCEPTED

    def _enter_mode(self, mode: Mode, now: float) -> None:
        self.intended = mode
        self.failsafe = None
        p = self._pos()
        self.hold = list(p)
        if mode.name == "AUTO.TAKEOFF":
            self._set_takeoff_target(_NAN)
        elif mode.name == "AUTO.RTL":
            self.rtl_phase = "climb"
        self._log_mode(now, mode.name)

    def _set_takeoff_target(self, alt_amsl: float) -> None:
        home_alt = self.home[2] if self.home else self.origin[2]
        if not math.isfinite(alt_amsl):
            alt_amsl = home_alt + self._param("MIS_TAKEOFF_ALT")
        z = self.origin[2] - alt_amsl
        self.takeoff_z = min(z, self._pos()[2] - 0.5) if self.phase == "flying" else z

    def _c_takeoff(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        mode = MODE_BY_NAME["AUTO.TAKEOFF"]
        res = self._change_mode(mode, now, scomp)
        if res == MAV_RESULT_ACCEPTED:
            self._set_takeoff_target(p[6])  # param7: altitude AMSL, NaN → MIS_TAKEOFF_ALT
        return res

    def _c_land(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        res = self._change_mode(MODE_BY_NAME["AUTO.LAND"], now, scomp)
        if res == MAV_RESULT_ACCEPTED:
            self._text(px4.SEV_INFO, "Landing at current position")
        return res

    def _c_rtl(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        res = self._change_mode(MODE_BY_NAME["AUTO.RTL"], now, scomp)
        if res == MAV_RESULT_ACCEPTED:
            self._text(px4.SEV_INFO, "Returning to launch")
        return res

    def _c_reposition(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        flags = int(p[1]) if math.isfinite(p[1]) else 0
        if not flags & 1 or flags & ~1:
            return MAV_RESULT_UNSUPPORTED  # PX4: mode switch flag required
        res = self._change_mode(MODE_BY_NAME["AUTO.LOITER"], now, scomp)
        if res == MAV_RESULT_ACCEPTED:
            pos = self._pos()
            target = list(pos)
            if math.isfinite(p[4]) and math.isfinite(p[5]):
                target[0], target[1] = project(self.origin[0], self.origin[1], p[4], p[5])
            if math.isfinite(p[6]):
                target[2] = self.origin[2] - p[6]
            self.hold = target
            if math.isfinite(p[0]) and p[0] > 0:
                self.cruise_speed = p[0]
        return res

    def _c_change_speed(
        self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool
    ) -> int:
        if math.isfinite(p[1]) and p[1] > 0:
            self.cruise_speed = p[1]
        return MAV_RESULT_ACCEPTED

    def _c_set_home(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        if math.isfinite(p[0]) and p[0] > 0.5:
            self._set_home(now)
            return MAV_RESULT_ACCEPTED
        if (
            all(math.isfinite(v) for v in p[4:7])
            and abs(p[4]) < 90.0
            and abs(p[5]) <= 180.0
            and -500.0 <= p[6] <= 9000.0
        ):
            x, y = project(self.origin[0], self.origin[1], p[4], p[5])
            self.home = (p[4], p[5], p[6])
            self.home_ned = (x, y, self.origin[2] - p[6])
            self.home_time_us = self._tboot_us(now)
            return MAV_RESULT_ACCEPTED
        return MAV_RESULT_DENIED

    def _c_set_message_interval(
        self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool
    ) -> int:
        msgid = int(p[0]) if math.isfinite(p[0]) else -1
        interval_us = p[1]
        if msgid == 49:  # GPS_GLOBAL_ORIGIN: PX4 sends it only when it changes or on request
            return MAV_RESULT_ACCEPTED
        if msgid == 0:  # HEARTBEAT stays at 1 Hz, in cadence (mock: never disabled)
            return MAV_RESULT_ACCEPTED
        sd = _STREAM_BY_ID.get(msgid)
        if sd is None or not math.isfinite(interval_us):
            return MAV_RESULT_DENIED
        hz = 0.0 if interval_us < 0 else (None if interval_us == 0 else 1e6 / interval_us)
        first_due = None
        if msgid == 242 and self.home is not None:  # capture: one HOME_POSITION before the ACK
            self._send_named("HOME_POSITION", self._b_home_position(now) or b"")
            first_due = now + (1e6 / interval_us if interval_us > 0 else 2.0)
        self.set_stream_rate(sd.name, hz, first_due, self._reply)
        return MAV_RESULT_ACCEPTED

    def _c_get_message_interval(
        self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool
    ) -> int:
        msgid = int(p[0]) if math.isfinite(p[0]) else -1
        if not 0 <= msgid <= 0xFFFF:
            return MAV_RESULT_DENIED
        sd = _STREAM_BY_ID.get(msgid)
        if sd is None:
            interval = 0
        else:
            st = (self._streams if self._reply is None else self._reply.streams)[sd.name]
            interval = min(int(st.interval * 1e6), 2**31 - 1) if st.interval > 0 else -1
        self._send_named("MESSAGE_INTERVAL", _S["MESSAGE_INTERVAL"].pack(interval, msgid))
        return MAV_RESULT_ACCEPTED

    def _c_request_message(
        self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool
    ) -> int:
        msgid = int(p[0]) if math.isfinite(p[0]) else -1
        if msgid == 244:  # MESSAGE_INTERVAL
            return self._c_get_message_interval([p[1], 0, 0, 0, 0, 0, 0], ssys, scomp, now, is_int)
        name = _REQUESTABLE_EXTRA.get(msgid)
        if name is None:
            sd = _STREAM_BY_ID.get(msgid)
            name = sd.name if sd else None
        if name is None:
            return MAV_RESULT_DENIED
        payload = getattr(self, "_b_" + name.lower())(now)
        if payload is None:
            return MAV_RESULT_DENIED
        self._send_named(name, payload)  # capture: the message arrives 1-3 ms before the ACK
        return MAV_RESULT_ACCEPTED

    def _c_autopilot_capabilities(
        self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool
    ) -> int:
        self._send_named("AUTOPILOT_VERSION", self._b_autopilot_version(now))
        return MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------------------------------
    # the PX4 logic, 50 Hz
    def _control(self, now: float) -> None:
        if not self.started:
            return
        up = now - self.t0
        f = self.faults
        if f.die_at_s is not None and self.dead is None and up >= f.die_at_s:
            self.kill(f.die_how)
        if self.dead == "freeze":
            return
        if f.push_at_s is not None:
            on = f.push_at_s <= up < f.push_at_s + f.push_for_s
            self._sched.push[self.slot] = (f.push_north_m_s, f.push_east_m_s, 0.0) if on \
                else (0.0, 0.0, 0.0)
        elif self._push_until is not None:
            if now >= self._push_until:
                self._push_until = None
                self._sched.push[self.slot] = 0.0
        if self.stage < len(_STAGES):
            self._boot_stages(now, up)
        # offboard signal (COM_OF_LOSS_T)
        fresh = self.sp_time is not None and now - self.sp_time <= self._param("COM_OF_LOSS_T")
        if self.sp_fresh and not fresh:
            self.sp_fresh = False
            if self.ready:
                self._events(px4.HEALTH_BURST_NO_OFFBOARD)
        if self.armed:
            self._armed_logic(now)
        else:
            self._sched.airborne[self.slot] = False

    def _boot_stages(self, now: float, up: float) -> None:
        while self.stage < len(_STAGES) and up >= self._boot_at(_STAGES[self.stage]):
            key = _STAGES[self.stage]
            self.stage += 1
            if key == "event_boot":
                self._event(px4.EVENTS["boot"])
            elif key == "origin":
                self.origin_time_us = self._tboot_us(now)
                self._set_home(now)
                self._send_named("GPS_GLOBAL_ORIGIN", self._b_gps_global_origin(now))
            elif key == "health_report":
                self._events(px4.HEALTH_BURST_NOT_READY)
            elif key == "logger":
                stamp = time.strftime("%Y-%m-%d/%H_%M_%S", time.gmtime(self.wall_t0 + 1.3))
                self._text(px4.SEV_INFO, f"[logger] ./log/{stamp}.ulg")
            elif key == "ready":
                self.ready = True
                self._events(
                    px4.HEALTH_BURST_READY if self.sp_fresh else px4.HEALTH_BURST_NO_OFFBOARD
                )
            elif key == "cal_baro":
                for name in ("CAL_BARO0_ID", "CAL_BARO0_OFF", "CAL_BARO0_PRIO"):
                    self._param_value(name)

    def _armed_logic(self, now: float) -> None:
        sched = self._sched
        slot = self.slot
        mode = self.mode
        # offboard loss failsafe (capture 1c): COM_OF_LOSS_T after the last setpoint
        if self.intended.name == "OFFBOARD":
            if self.failsafe is None and not self.sp_fresh:
                self._trigger_offboard_failsafe(now)
                mode = self.mode
            elif self.failsafe is not None and self.sp_fresh:
                self.failsafe = None  # PX4: mode fallback clears when the condition clears
                mode = self.mode
                self.hold = list(self._pos())
                self._log_mode(now, mode.name)
        phase = self.phase
        if phase == "spoolup":
            if now - self.phase_t >= self._param("COM_SPOOLUP_TIME"):
                self.phase = phase = "idle"
                self.phase_t = now
        if phase in ("idle", "landed"):
            if self._wants_climb(mode):
                self.phase = phase = "ramp"
                self.phase_t = now
        if phase == "ramp":
            el = now - self.phase_t
            if el >= TAKEOFF_DETECT_S and self.landed_state == LANDED_ON_GROUND:
                self.landed_state = LANDED_IN_AIR
                self.took_off = True
                self._text(px4.SEV_INFO, "Takeoff detected")
                self._event(px4.EVENTS["takeoff"])
            if el >= LIFTOFF_S:
                self.phase = phase = "flying"
                self.touchdown_t = None
        if phase == "flying":
            sched.airborne[slot] = True
            self._command(mode, now)
            contact = sched.contact_rows[slot]
            descending = sched.u[slot, 2] >= -0.05
            if contact and descending:
                if self.touchdown_t is None:
                    self.touchdown_t = now
                elif now - self.touchdown_t >= LAND_DETECT_S:
                    self.phase = "landed"
                    self.landed_t = now
                    self.landed_state = LANDED_ON_GROUND
                    sched.airborne[slot] = False
                    sched.u[slot] = 0.0
                    self._text(px4.SEV_INFO, "Landing detected")
                    self._event(px4.EVENTS["landing"])
            else:
                self.touchdown_t = None
            if mode.name == "AUTO.TAKEOFF" and self.failsafe is None:
                if self._pos()[2] <= self.takeoff_z + TAKEOFF_ACCEPT_M:
                    hold = list(self._pos())
                    hold[2] = self.takeoff_z
                    self._enter_mode(MODE_BY_NAME["AUTO.LOITER"], now)
                    self.hold = hold
        else:
            sched.airborne[slot] = False
            sched.u[slot] = 0.0
        # auto-disarm
        if self.phase == "landed" and self.landed_t is not None:
            if now - self.landed_t >= self._param("COM_DISARM_LAND"):
                self._disarm(now, "landing", forced=True)
                return
        if not self.took_off and self.phase in ("spoolup", "idle"):
            limit = self._param("COM_SPOOLUP_TIME") + self._param("COM_DISARM_PRFLT")
            if self._param("COM_DISARM_PRFLT") > 0 and now - self.arm_time >= limit:
                self._disarm(now, "auto preflight disarming", forced=True)

    def _trigger_offboard_failsafe(self, now: float) -> None:
        action = int(self._param("COM_OBL_RC_ACT"))
        # 0 Position, 1 Altitude, 2 Stabilized (no RC: they descend), 3 Return, 4 Land, 5 Hold
        name = {
            0: "POSCTL",
            1: "ALTCTL",
            2: "STABILIZED",
            3: "AUTO.RTL",
            4: "AUTO.LAND",
            5: "AUTO.LOITER",
        }
        self.failsafe = MODE_BY_NAME[name.get(action, "AUTO.LAND")]
        self.hold = list(self._pos())
        if self.failsafe.name == "AUTO.RTL":
            self.rtl_phase = "climb"
        self._text(px4.SEV_CRITICAL, "Failsafe activated")
        self._events(px4.HEALTH_BURST_NO_OFFBOARD)
        self._event(px4.EVENTS["failsafe"])
        self._log_mode(now, self.failsafe.name)

    def _wants_climb(self, mode: Mode) -> bool:
        if self.failsafe is not None:
            return False
        if mode.name == "AUTO.TAKEOFF":
            return True
        if mode.name == "OFFBOARD" and self.sp_fresh:
            sp = self.sp
            if sp.vel[2] is not None and sp.vel[2] < -0.1:
                return True
            if sp.pos[2] is not None and sp.pos[2] < self._pos()[2] - 0.2:
                return True
        return False

    def _command_offboard(self) -> None:
        u = self._sched.u
        slot = self.slot
        sp = self.sp
        p = self._pos()
        kp_xy = self._param("MPC_XY_P")
        kp_z = self._param("MPC_Z_P")
        out = [0.0, 0.0, 0.0]
        hold = self.hold or p
        for i in range(3):
            pos, vel = sp.pos[i], sp.vel[i]
            k = kp_z if i == 2 else kp_xy
            if pos is not None:
                out[i] = k * (pos - p[i]) + (vel or 0.0)
            elif vel is not None:
                out[i] = vel
            else:
                out[i] = k * (hold[i] - p[i])
        self._limit(out, self._param("MPC_XY_VEL_MAX"))
        u[slot, 0], u[slot, 1], u[slot, 2] = out
        ysp = self._sched.yaw_sp
        if sp.yaw is not None:
            ysp[slot] = sp.yaw
            self._sched.yaw_rate_sp[slot] = 0.0
        else:
            ysp[slot] = _NAN
            self._sched.yaw_rate_sp[slot] = sp.yaw_rate or 0.0

    def _limit(self, out: list[float], xy_max: float) -> None:
        xy_max = min(xy_max, XY_SPEED_CAP)
        n = math.hypot(out[0], out[1])
        if n > xy_max > 0:
            out[0] *= xy_max / n
            out[1] *= xy_max / n
        up = min(self._param("MPC_Z_VEL_MAX_UP"), UP_SPEED_CAP)
        out[2] = min(max(out[2], -up), min(self._param("MPC_Z_VEL_MAX_DN"), DOWN_SPEED_CAP))

    def _goto(self, target: list[float], xy_max: float, z_up: float, z_dn: float) -> list[float]:
        xy_max = min(xy_max, XY_SPEED_CAP)
        z_up, z_dn = min(z_up, UP_SPEED_CAP), min(z_dn, DOWN_SPEED_CAP)
        p = self._pos()
        kp_xy = self._param("MPC_XY_P")
        out = [kp_xy * (target[0] - p[0]), kp_xy * (target[1] - p[1]), 0.0]
        out[2] = min(max(self._param("MPC_Z_P") * (target[2] - p[2]), -z_up), z_dn)
        n = math.hypot(out[0], out[1])
        if n > xy_max > 0:
            out[0] *= xy_max / n
            out[1] *= xy_max / n
        return out

    def _command(self, mode: Mode, now: float) -> None:
        sched = self._sched
        slot = self.slot
        name = mode.name
        if name == "OFFBOARD":
            self._command_offboard()
            return
        sched.yaw_sp[slot] = _NAN
        sched.yaw_rate_sp[slot] = 0.0
        p = self._pos()
        hold = self.hold or list(p)
        cruise = self.cruise_speed or self._param("MPC_XY_CRUISE")
        z_up = self._param("MPC_Z_VEL_MAX_UP")
        z_dn = self._param("MPC_Z_VEL_MAX_DN")
        if name == "AUTO.TAKEOFF":
            target = [hold[0], hold[1], self.takeoff_z]
            out = self._goto(target, cruise, self._param("MPC_TKO_SPEED"), z_dn)
        elif name == "AUTO.LOITER":
            out = self._goto(hold, cruise, z_up, z_dn)
        elif name == "AUTO.LAND":
            out = self._goto([hold[0], hold[1], p[2]], cruise, z_up, z_dn)
            out[2] = self._land_speed(-p[2])
        elif name == "AUTO.RTL":
            out = self._rtl(p, cruise, z_up, z_dn)
        else:  # POSCTL/ALTCTL/STABILIZED as failsafe without RC: hold x/y, descend (capture 1c)
            out = self._goto([hold[0], hold[1], p[2]], cruise, z_up, z_dn)
            out[2] = self._param("MPC_LAND_SPEED")
        sched.u[slot, 0], sched.u[slot, 1], sched.u[slot, 2] = out

    def _land_speed(self, height: float) -> float:
        slow = self._param("MPC_LAND_SPEED")
        fast = self._param("MPC_Z_VEL_MAX_DN")
        alt1, alt2 = 10.0, 5.0  # MPC_LAND_ALT1/ALT2 defaults
        if height <= alt2:
            return slow
        if height >= alt1:
            return fast
        return slow + (fast - slow) * (height - alt2) / (alt1 - alt2)

    def _rtl(self, p: list[float], cruise: float, z_up: float, z_dn: float) -> list[float]:
        hx, hy, hz = self.home_ned
        return_z = hz - self._param("RTL_RETURN_ALT")
        if self.rtl_phase == "climb":
            if p[2] <= return_z + 0.5 or p[2] <= return_z:
                self.rtl_phase = "return"
            return (
                self._goto([p[0], p[1], min(return_z, p[2])], 0.0, z_up, z_dn)
                if p[2] > return_z
                else self._goto([p[0], p[1], p[2]], 0.0, z_up, z_dn)
            )
        if self.rtl_phase == "return":
            if math.hypot(hx - p[0], hy - p[1]) < 1.0:
                self.rtl_phase = "land"
            return self._goto([hx, hy, min(return_z, p[2])], cruise, z_up, z_dn)
        out = self._goto([hx, hy, p[2]], cruise, z_up, z_dn)
        out[2] = self._land_speed(hz - p[2])
        return out

    def _set_home(self, now: float) -> None:
        x, y, z = self._pos()
        lat, lon = reproject(self.origin[0], self.origin[1], x, y)
        self.home = (lat, lon, self.origin[2] - z)
        self.home_ned = (x, y, z)
        r, pch, yaw = self._sched.att_rows[self.slot][:3]
        self.home_q = _quat(r, pch, yaw) if self.armed or self.took_off else (1.0, 0.0, 0.0, 0.0)
        self.home_time_us = self._tboot_us(now)

    # ------------------------------------------------------------------------------------------
    # message builders: return the full payload, or None to skip this time
    def _b_heartbeat(self, now: float) -> bytes:
        if self.stage < len(_STAGES) and self.dead is None:
            self._boot_stages(now, now - self.t0)  # (home/origin valid by the first heartbeat)
        return _S["HEARTBEAT"].pack(self.custom_mode, 2, 12, self.base_mode, self.system_status, 3)

    def _b_sys_status(self, now: float) -> bytes:
        up = now - self.t0
        if up < self._boot_at("sensors"):
            present, enabled, health = px4.SENSORS_BOOT
        elif not self.ready:
            present, enabled, health = px4.SENSORS_NO_GPS
        else:
            present, enabled, health = px4.SENSORS_READY
            if self._prearm_ok():
                health |= px4.SENSOR_PREARM
        errors = self._rx_malformed & 0xFFFF
        return _S["SYS_STATUS"].pack(
            present, enabled, health, 100, 16200, -100, 0, errors, 0, 0, 0, 0, 99, 0, 0, 1
        )

    def _b_extended_sys_state(self, now: float) -> bytes:
        return _S["EXTENDED_SYS_STATE"].pack(0, self.landed_state)

    def _b_attitude(self, now: float) -> bytes:
        a = self._sched.att_rows[self.slot]
        return _S["ATTITUDE"].pack(self._tboot_ms(now), a[0], a[1], a[2], a[3], a[4], a[5])

    def _b_attitude_quaternion(self, now: float) -> bytes:
        s = self._sched
        a = s.att_rows[self.slot]
        q = s.q_rows[self.slot]
        return _S["ATTITUDE_QUATERNION"].pack(
            self._tboot_ms(now), q[0], q[1], q[2], q[3], a[3], a[4], a[5], 0.0, 0.0, 0.0, 0.0
        )

    def _b_highres_imu(self, now: float) -> bytes:
        s = self._sched
        a = s.att_rows[self.slot]
        fx, fy, fz, mx, my, mz = s.imu_rows[self.slot]
        alt = self.origin[2] - s.p_true_rows[self.slot][2]
        return _S["HIGHRES_IMU"].pack(
            self._tboot_us(now), fx, fy, fz, a[3], a[4], a[5], mx, my, mz,
            _pressure_pa(alt), 0.0, alt, 15.0, 511, 0,
        )  # fmt: skip

    def _b_local_position_ned(self, now: float) -> bytes:
        s = self._sched
        p = s.p_rows[self.slot]
        v = s.v_rows[self.slot]
        return _S["LOCAL_POSITION_NED"].pack(
            self._tboot_ms(now), p[0], p[1], p[2], v[0], v[1], v[2]
        )

    def _b_odometry(self, now: float) -> bytes:
        s = self._sched
        p = s.p_rows[self.slot]
        v = s.v_rows[self.slot]
        a = s.att_rows[self.slot]
        q = s.q_rows[self.slot]
        head = _ODO_HEAD.pack(
            self._tboot_us(now), p[0], p[1], p[2], q[0], q[1], q[2], q[3],
            v[0], v[1], v[2], a[3], a[4], a[5],
        )  # fmt: skip
        return head + _ODO_TAIL

    def _b_global_position_int(self, now: float) -> bytes | None:
        if now - self.t0 < self._boot_at("global_position"):
            return None
        s = self._sched
        p = s.p_rows[self.slot]
        v = s.v_rows[self.slot]
        lat, lon = reproject(self.origin[0], self.origin[1], p[0], p[1])
        alt = self.origin[2] - p[2]
        home_alt = self.home[2] if self.home else self.origin[2]
        hdg = int(math.degrees(s.att_rows[self.slot][2]) * 100.0) % 36000
        return _S["GLOBAL_POSITION_INT"].pack(
            self._tboot_ms(now), round(lat * 1e7), round(lon * 1e7), round(alt * 1000.0),
            round((alt - home_alt) * 1000.0), _i16(v[0] * 100.0), _i16(v[1] * 100.0),
            _i16(v[2] * 100.0), hdg,
        )  # fmt: skip

    def _b_gps_raw_int(self, now: float) -> bytes:
        """The GNSS receiver (truth + its own error), with the profile's reported accuracy."""
        s = self._sched
        p = s.gnss_p_rows[self.slot]
        v = s.gnss_v_rows[self.slot]
        e = self.estimator
        lat, lon = reproject(self.origin[0], self.origin[1], p[0], p[1])
        alt_mm = round((self.origin[2] - p[2]) * 1000.0)
        gs = math.hypot(v[0], v[1])
        cog = int(math.degrees(math.atan2(v[1], v[0])) * 100.0) % 36000 if gs > 0.05 else 0
        return _S["GPS_RAW_INT"].pack(
            self._tboot_us(now), round(lat * 1e7), round(lon * 1e7), alt_mm, e.eph_cm, e.epv_cm,
            min(int(gs * 100.0), 65534), cog, e.fix_type, e.satellites, alt_mm, e.h_acc_mm,
            e.v_acc_mm, e.vel_acc_mm_s, 0, 0,
        )  # fmt: skip

    def _b_hil_state_quaternion(self, now: float) -> bytes:
        """SITL ground truth as PX4 SITL sends it: lat/lon 1e-7 deg, alt mm AMSL, vx/vy/vz cm/s
        NED, accelerations in mG, ``time_usec`` always 0 (fleet-truth captures)."""
        s = self._sched
        x, y, z = s.p_true_rows[self.slot]
        vx, vy, vz = s.v_true_rows[self.slot]
        a = s.att_rows[self.slot]
        q = s.q_rows[self.slot]
        ax, ay, az = s.acc_rows[self.slot]
        lat, lon = reproject(self.origin[0], self.origin[1], x, y)
        gs = _u16(math.hypot(vx, vy) * 100.0)
        mg = 1000.0 / 9.80665
        return _S["HIL_STATE_QUATERNION"].pack(
            0, q[0], q[1], q[2], q[3], a[3], a[4], a[5], round(lat * 1e7), round(lon * 1e7),
            round((self.origin[2] - z) * 1000.0), _i16(vx * 100.0), _i16(vy * 100.0),
            _i16(vz * 100.0), gs, gs, _i16(ax * mg), _i16(ay * mg), _i16((az - 9.80665) * mg),
        )  # fmt: skip

    def _b_timesync(self, now: float) -> bytes:
        return _S["TIMESYNC"].pack(0, self._tboot_us(now) * 1000)

    def _b_altitude(self, now: float) -> bytes:
        z = self._sched.p_rows[self.slot][2]
        alt = self.origin[2] - z
        home_alt = self.home[2] if self.home else self.origin[2]
        return _S["ALTITUDE"].pack(
            self._tboot_us(now), alt, alt, -z, alt - home_alt, self.origin[2], -z
        )

    def _b_distance_sensor(self, now: float) -> bytes:
        h = -self._sched.p_true_rows[self.slot][2]
        cm = min(max(int(h * 100.0), 0), 10000)
        return _S["DISTANCE_SENSOR"].pack(
            self._tboot_ms(now), 0, 10000, cm, 0, 0, 25, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0
        )

    def _thrust(self) -> float:
        if not self.armed:
            return 0.0
        if self.phase in ("spoolup", "idle", "landed", "ground"):
            return 0.1
        if self.phase == "ramp":
            return 0.1 + 0.38 * min(1.0, (self._now() - self.phase_t) / LIFTOFF_S)
        acc_z = self._sched.acc_rows[self.slot][2]
        return min(1.0, max(0.05, 0.48 * (1.0 - acc_z / 9.80665)))

    def _paused(self) -> bool:
        # capture 1d: ATTITUDE_TARGET, POSITION_TARGET_LOCAL_NED and SERVO_OUTPUT_RAW stop while
        # OFFBOARD is selected without any setpoint (no controller runs)
        return self.mode.name == "OFFBOARD" and not self.sp_ever

    def _b_servo_output_raw(self, now: float) -> bytes | None:
        if self._paused():
            return None
        pwm = 900 if not self.armed else int(1000 + 1000 * self._thrust())
        return _S["SERVO_OUTPUT_RAW"].pack(
            self._tboot_us(now) & 0xFFFFFFFF, pwm, pwm, pwm, pwm, 900, 900, 900, 900, 0,
            900, 900, 900, 900, 900, 900, 900, 900,
        )  # fmt: skip

    def _b_attitude_target(self, now: float) -> bytes | None:
        if self._paused():
            return None
        a = self._sched.att_rows[self.slot]
        q = self._sched.q_rows[self.slot]
        thrust = self._thrust() if self.armed else 0.001
        return _S["ATTITUDE_TARGET"].pack(
            self._tboot_ms(now), q[0], q[1], q[2], q[3], a[3], a[4], a[5], thrust, 0
        )

    def _b_position_target_local_ned(self, now: float) -> bytes | None:
        if self._paused():
            return None
        s = self._sched
        yaw = s.att_rows[self.slot][2]
        acc = s.acc_rows[self.slot]
        nan = _NAN
        if not self.armed or self.phase in ("spoolup", "idle", "landed", "ground"):
            return _S["POSITION_TARGET_LOCAL_NED"].pack(
                self._tboot_ms(now), nan, nan, nan, nan, nan, nan, 0.0, 0.0, 100.0, yaw, 0.0, 63, 1
            )
        mode = self.mode
        u = s.u[self.slot]
        if self.failsafe is not None and mode.needs == "manual":
            # capture 1c: type_mask 31, vz = descent speed, vx/vy NaN
            return _S["POSITION_TARGET_LOCAL_NED"].pack(
                self._tboot_ms(now), nan, nan, nan, nan, nan, float(u[2]),
                acc[0], acc[1], acc[2], yaw, 0.0, 31, 1,
            )  # fmt: skip
        if mode.name == "OFFBOARD":
            sp = self.sp
            mask = 0
            pos = []
            for i in range(3):
                if sp.pos[i] is None:
                    mask |= 1 << i
                    pos.append(nan)
                else:
                    pos.append(sp.pos[i])
            vel = (
                [float(u[0]), float(u[1]), float(u[2])]
                if any(x is not None for x in sp.vel)
                else [nan, nan, nan]
            )
            if vel[0] != vel[0]:
                mask |= 0x38
            return _S["POSITION_TARGET_LOCAL_NED"].pack(
                self._tboot_ms(now), pos[0], pos[1], pos[2], vel[0], vel[1], vel[2],
                acc[0], acc[1], acc[2], yaw, 0.0, mask, 1,
            )  # fmt: skip
        hold = self.hold or self._pos()
        return _S["POSITION_TARGET_LOCAL_NED"].pack(
            self._tboot_ms(now), hold[0], hold[1], hold[2], float(u[0]), float(u[1]), float(u[2]),
            acc[0], acc[1], acc[2], yaw, 0.0, 0, 1,
        )  # fmt: skip

    def _b_vfr_hud(self, now: float) -> bytes:
        s = self._sched
        v = s.v_rows[self.slot]
        z = s.p_rows[self.slot][2]
        heading = int(math.degrees(s.att_rows[self.slot][2])) % 360
        return _S["VFR_HUD"].pack(
            _NAN,
            math.hypot(v[0], v[1]),
            self.origin[2] - z,
            -v[2],
            heading,
            int(self._thrust() * 100),
        )

    def _b_home_position(self, now: float) -> bytes | None:
        if self.home is None:
            return None
        lat, lon, alt = self.home
        x, y, z = self.home_ned
        q = self.home_q
        return _S["HOME_POSITION"].pack(
            round(lat * 1e7), round(lon * 1e7), round(alt * 1000.0), x, y, z,
            q[0], q[1], q[2], q[3], 0.0, 0.0, 0.0, self.home_time_us,
        )  # fmt: skip

    def _b_gps_global_origin(self, now: float) -> bytes | None:
        if now - self.t0 < self._boot_at("origin"):
            return None
        lat, lon, alt = self.origin
        return _S["GPS_GLOBAL_ORIGIN"].pack(
            round(lat * 1e7), round(lon * 1e7), round(alt * 1000.0), self.origin_time_us
        )

    def _b_mission_current(self, now: float) -> bytes:
        return _S["MISSION_CURRENT"].pack(0, 65535, 1, 2)

    def _b_estimator_status(self, now: float) -> bytes:
        """Accuracy as PX4 SIH reported it (fleet-truth captures): 14.1 m before a global
        position, then 2.0 → 0.6 (1 s later) → 0.33 (3 s) → the profile's value (0.29 m)."""
        t_gp = self._boot_at("global_position")
        up = now - self.t0
        if up < t_gp:
            return _S["ESTIMATOR_STATUS"].pack(
                self._tboot_us(now), _NAN, _NAN, 0.01, _NAN, 0.002, _NAN, 14.14, 0.19, 229
            )
        e = self.estimator
        tau = 0.7 * self.boot_time_scale
        acc = e.pos_horiz_accuracy_m + (2.0 - e.pos_horiz_accuracy_m) * math.exp(
            -(up - t_gp) / tau)
        return _S["ESTIMATOR_STATUS"].pack(
            self._tboot_us(now), 0.14, 0.03, 0.02, 0.10, 0.01, _NAN, acc,
            e.pos_vert_accuracy_m, 895
        )

    def _b_open_drone_id_location(self, now: float) -> bytes:
        s = self._sched
        p = s.p_rows[self.slot]
        v = s.v_rows[self.slot]
        lat, lon = reproject(self.origin[0], self.origin[1], p[0], p[1])
        alt = self.origin[2] - p[2]
        gs = math.hypot(v[0], v[1])
        direction = int(math.degrees(math.atan2(v[1], v[0])) * 100) % 36000 if gs > 0.05 else 36100
        status = 2 if self.landed_state == LANDED_IN_AIR else 1
        home_alt = self.home[2] if self.home else self.origin[2]
        return _S["OPEN_DRONE_ID_LOCATION"].pack(
            round(lat * 1e7), round(lon * 1e7), alt, float(round(alt)), alt - home_alt, 65535.0,
            direction, min(int(gs * 100), 25425), _i16(-v[2] * 100), 0, 0, *_ZERO20,
            status, 0, 12, 5, 0, 3, 0,
        )  # fmt: skip

    def _b_open_drone_id_system(self, now: float) -> bytes:
        lat, lon, alt = self.home or self.origin
        ts = max(0, int(time.time()) - 1546300800)  # seconds since 2019-01-01 (ODID epoch)
        return _S["OPEN_DRONE_ID_SYSTEM"].pack(
            round(lat * 1e7), round(lon * 1e7), -1000.0, -1000.0, alt, ts, 1, 0, 0, 0, *_ZERO20,
            0, 0, 0, 0,
        )  # fmt: skip

    def _b_ping(self, now: float) -> bytes:
        seq = self._ping_seq
        self._ping_seq = (seq + 1) & 0xFFFFFFFF
        return _S["PING"].pack(self._tboot_us(now), seq, 0, 0)

    def _b_scaled_pressure(self, now: float) -> bytes:
        alt = self.origin[2] - self._sched.p_true_rows[self.slot][2]
        return _S["SCALED_PRESSURE"].pack(
            self._tboot_ms(now), _pressure_pa(alt) / 100.0, 0.0, 1182, 0
        )

    def _b_system_time(self, now: float) -> bytes:
        return _S["SYSTEM_TIME"].pack(int(time.time() * 1e6), self._tboot_ms(now))

    def _b_link_node_status(self, now: float) -> bytes:
        t_prev, tx_prev, rx_prev = self._link_stat
        dt = now - t_prev if t_prev else 1.0
        tx_rate = int((self._tx_bytes - tx_prev) / dt) if dt > 0 else 0
        rx_rate = int((self._rx_bytes - rx_prev) / dt) if dt > 0 else 0
        self._link_stat = (now, self._tx_bytes, self._rx_bytes)
        return _S["LINK_NODE_STATUS"].pack(
            self._tboot_us(now), tx_rate, rx_rate, self._tx_packets & 0xFFFFFFFF,
            self._rx_packets & 0xFFFFFFFF, 0, self._rx_malformed & 0xFFFF, 0, 0, 0, 0,
        )  # fmt: skip

    def _b_time_estimate_to_target(self, now: float) -> bytes:
        if self.landed_state != LANDED_IN_AIR:
            safe = 0
        else:
            p = self._pos()
            h = -p[2]
            ret = self._param("RTL_RETURN_ALT")
            dist = math.hypot(p[0] - self.home_ned[0], p[1] - self.home_ned[1])
            safe = int(
                max(0.0, ret - h) / self._param("MPC_Z_VEL_MAX_UP")
                + dist / self._param("MPC_XY_CRUISE")
                + max(h, ret) / (self._param("MPC_LAND_SPEED") + 0.1)
            )
        return _S["TIME_ESTIMATE_TO_TARGET"].pack(safe, -1, -1, -1, -1)

    def _b_battery_status(self, now: float) -> bytes:
        return _S["BATTERY_STATUS"].pack(
            0, -1, 32767, 16200, *_V9, -100, 0, 1, 1, 99, 0, 1, 0, 0, 0, 0, 0, 0
        )

    def _b_vibration(self, now: float) -> bytes:
        return _S["VIBRATION"].pack(self._tboot_us(now), 0.0, 0.011, 0.117, 0, 0, 0)

    def _b_current_mode(self, now: float) -> bytes:
        m = self.mode
        return _S["CURRENT_MODE"].pack(m.custom_mode, self.intended.custom_mode, m.standard_mode)

    def _b_current_event_sequence(self, now: float) -> bytes:
        return _S["CURRENT_EVENT_SEQUENCE"].pack((self._event_seq - 1) & 0xFFFF, 0)

    def _b_autopilot_version(self, now: float) -> bytes:
        uid = 0x2D0000 + self.sysid
        return _S["AUTOPILOT_VERSION"].pack(
            _CAPABILITIES, uid, _FLIGHT_SW_VERSION, _FLIGHT_SW_VERSION, 0, 0, 0, 0,
            *b"752ecd3d", *bytes(8), *bytes(8), *bytes(18),
        )  # fmt: skip


_STAGES = ("event_boot", "origin", "health_report", "logger", "ready", "cal_baro")

_HANDLERS: dict[int, Callable[..., None]] = {
    0: MockVehicle._h_heartbeat,
    75: MockVehicle._h_command,
    76: MockVehicle._h_command,
    84: MockVehicle._h_setpoint_local,
    86: MockVehicle._h_setpoint_global,
    20: MockVehicle._h_param_request_read,
    21: MockVehicle._h_param_request_list,
    23: MockVehicle._h_param_set,
    111: MockVehicle._h_timesync,
    4: MockVehicle._h_ping,
    43: MockVehicle._h_mission_request_list,
}
_COMMANDS: dict[int, Callable[..., int]] = {
    CMD_COMPONENT_ARM_DISARM: MockVehicle._c_arm_disarm,
    CMD_DO_SET_MODE: MockVehicle._c_set_mode,
    CMD_NAV_TAKEOFF: MockVehicle._c_takeoff,
    CMD_NAV_LAND: MockVehicle._c_land,
    CMD_NAV_RETURN_TO_LAUNCH: MockVehicle._c_rtl,
    CMD_DO_REPOSITION: MockVehicle._c_reposition,
    CMD_DO_CHANGE_SPEED: MockVehicle._c_change_speed,
    CMD_DO_SET_HOME: MockVehicle._c_set_home,
    CMD_SET_MESSAGE_INTERVAL: MockVehicle._c_set_message_interval,
    CMD_GET_MESSAGE_INTERVAL: MockVehicle._c_get_message_interval,
    CMD_REQUEST_MESSAGE: MockVehicle._c_request_message,
    CMD_REQUEST_AUTOPILOT_CAPABILITIES: MockVehicle._c_autopilot_capabilities,
}

_ODO_HEAD = struct.Struct("<Qfff4fffffff")
# ODOMETRY covariances and trailing fields as captured (upper triangle, NaN = unknown),
# frame_id/child_frame_id LOCAL_NED, reset_counter 4, estimator_type 8 (AUTOPILOT), quality 0
_POSE_COV = [100.0] + [_NAN] * 5 + [100.0] + [_NAN] * 4 + [100.0] + [_NAN] * 3
_POSE_COV += [0.01, _NAN, _NAN, 0.01, _NAN, 1e-6]
_VEL_COV = [25.0] + [_NAN] * 5 + [25.0] + [_NAN] * 4 + [10.0] + [_NAN] * 9
_ODO_TAIL = struct.pack("<21f21fBBBBb", *_POSE_COV, *_VEL_COV, 1, 1, 4, 8, 0)
_ZERO20 = (0,) * 20
_V9 = (65535,) * 9


def _param_name(raw: bytes | str) -> str:
    if isinstance(raw, bytes):
        raw = raw.split(b"\x00", 1)[0].decode("ascii", "replace")
    return raw.split("\x00", 1)[0]


def _u16(x: float) -> int:
    return min(max(int(x), 0), 0xFFFF)


def _i16(x: float) -> int:
    return max(-32768, min(32767, int(round(x))))


def _quat(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(roll * 0.5), math.sin(roll * 0.5)
    cp, sp = math.cos(pitch * 0.5), math.sin(pitch * 0.5)
    cy, sy = math.cos(yaw * 0.5), math.sin(yaw * 0.5)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def _body(
    n: float, e: float, d: float, roll: float, pitch: float, yaw: float
) -> tuple[float, float, float]:
    """Rotate an NED vector into the body frame (ZYX Euler)."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    x1, y1 = cy * n + sy * e, -sy * n + cy * e
    cp, sp = math.cos(pitch), math.sin(pitch)
    x2, z2 = cp * x1 - sp * d, sp * x1 + cp * d
    cr, sr = math.cos(roll), math.sin(roll)
    return x2, cr * y1 + sr * z2, -sr * y1 + cr * z2


def _pressure_pa(alt_m: float) -> float:
    return 101325.0 * (1.0 - 2.25577e-5 * alt_m) ** 5.25588
