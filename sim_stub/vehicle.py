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
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as _mav

from . import px4
from .battery import Battery
from .codec import SPECS, DatagramParser, Encoder, MsgSpec, fast_decoder, mcrf4xx
from .commander import CommanderMixin, Setpoint
from .errors import SimStubError
from .estimator import EstimatorProfile, estimator_profile
from .faults import Faults
from .fence import FenceMixin
from .geo import reproject
from .ports import PortScheme, resolve_port_scheme
from .px4 import (
    BOOT,
    BOOT_STAGES,
    LANDED_ON_GROUND,
    MAX_STREAM_HZ,
    MODE_BY_NAME,
    Mode,
)
from .scheduler import Scheduler
from .signing import SigningState
from .telemetry import (
    GCS_LINK_PROFILES,
    GCS_LINK_STREAMS,
    PROFILES,
    STREAM_BY_NAME,
    STREAM_CATALOG,
    StreamState,
    TelemetryMixin,
)
from .telemetry import (
    STRUCTS as _S,
)

__all__ = [
    "DEFAULT_HOME",
    "GcsLink",
    "MockVehicle",
    "VehicleCounters",
    "validate_home",
]

log = logging.getLogger("sim_stub")

_CRC = struct.Struct("<H")
# MAVLink 2 header after the magic: length, flags 0/0, seq, sysid, compid, msgid (3 bytes)
_HDR = struct.Struct("<B2xBBB3s")
_NAN = float("nan")
_N_BOOT_STAGES = len(BOOT_STAGES)
_MAX_DATAGRAM = 65535
# the setpoint fast path (MockVehicle._on_datagram): SET_POSITION_TARGET_LOCAL_NED's wire format
_SP_MSG = _mav.MAVLink_set_position_target_local_ned_message
assert tuple(_SP_MSG.ordered_fieldnames) == (
    "time_boot_ms", "x", "y", "z", "vx", "vy", "vz", "afx", "afy", "afz", "yaw", "yaw_rate",
    "type_mask", "target_system", "target_component", "coordinate_frame")  # fmt: skip
_SP_STRUCT = struct.Struct(_SP_MSG.unpacker.format)
_SP_UNPACK = _SP_STRUCT.unpack
_SP_SIZE = _SP_STRUCT.size
_SP_CRC_EXTRA = bytes((_SP_MSG.crc_extra,))

DEFAULT_HOME = (47.397742, 8.545594, 489.4)  # PX4 SIH default SIH_LOC_LAT0/LON0/H0

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


class MockVehicle(CommanderMixin, FenceMixin, TelemetryMixin):
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
    ``signing``: MAVLink 2 signing as PX4 >= 1.18 (:mod:`sim_stub.signing`): ``False`` = an
    older PX4 that ignores SETUP_SIGNING, ``True`` = no key yet (SETUP_SIGNING sets one), 32
    bytes = the key already on the SD card.

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
        signing: bool | bytes = False,
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
        try:
            self.signing: SigningState | None = (
                None if signing is False
                else SigningState(None if signing is True else bytes(signing)))
        except ValueError as exc:
            raise SimStubError(f"signing: {exc}") from None
        if self.signing is not None:
            self._signing_changed()
        self._sock: socket.socket | None = None
        self._link_plain = False  # no fault, not dead: the fast send path
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
        self.sp = Setpoint()
        # (velocity setpoint, the three speed-limit Params) while the scheduler's u / yaw_sp /
        # yaw_rate_sp of this slot hold exactly its command: every other writer of them clears
        # it (commander.py _command_offboard)
        self._offboard_cache: tuple | None = None
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
        self.health_rereport_at: float | None = None  # px4.HEALTH_AFTER_LANDING_S
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
        self.battery = Battery(self.faults)
        self._fence_init()  # sim_stub/fence.py

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
        self._sched.add_reader(sock, self._on_readable)
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
        if self._sock is not None:
            self._sched.remove_reader(self._sock)
            self._sock.close()
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

    def slow(self, gain: float) -> None:
        """From now on the vehicle follows only ``gain`` (0, 1] of every horizontal velocity it
        is commanded: fault injection on demand, like :class:`~sim_stub.faults.Faults`
        ``slow_*``."""
        if not 0.0 < gain <= 1.0:
            raise SimStubError(f"slow needs a gain in (0, 1], got {gain}")
        self._sched.slow(self.slot, gain)

    def set_battery(self, pct: float) -> None:
        """The battery holds at most ``pct`` % from now on (also after disarming): the
        ``battery_low`` fault on demand (:mod:`sim_stub.battery`)."""
        try:
            self.battery.drop_to(float(pct))
        except ValueError as exc:
            raise SimStubError(str(exc)) from None

    def battery_pct(self, now: float | None = None) -> float:
        """The battery's charge (%) now (:mod:`sim_stub.battery`)."""
        t = self._now() if now is None else now
        return self.battery.update(t, t - self.t0 if self.started else 0.0, self.armed)

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
            sd = STREAM_BY_NAME[name]
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

    def send_stream(self, st: StreamState, payload: bytes) -> None:
        """Send one message of stream ``st`` on its link (the scheduler's path)."""
        if st.link is not None:
            self._send_gcs(st.link, st.spec, payload)
            return
        enc = self._enc
        if not self._link_plain or enc.signer is not None:
            self._send_api(st.spec, payload)
            return
        # _send_api's plain path inlined (~40 stream messages per vehicle and second)
        payload = payload.rstrip(b"\x00") or b"\x00"
        seq = enc.seq
        enc.seq = (seq + 1) & 0xFF
        spec = st.spec
        body = _HDR.pack(len(payload), seq, self.sysid, 1, spec.id3) + payload
        data = b"\xfd" + body + _CRC.pack(mcrf4xx(body + spec.crc_byte))
        self._tx_packets += 1
        self._tx_bytes += len(data)
        try:
            self._sock.sendto(data, self._remote)  # type: ignore[union-attr]
        except OSError:
            self._tx_errors += 1

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
        if enc.signer is None:
            body = _HDR.pack(len(payload), seq, self.sysid, 1, spec.id3) + payload
            data = b"\xfd" + body + _CRC.pack(mcrf4xx(body + spec.crc_byte))
        else:
            data = enc.signer(seq, spec, payload)
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

    def flush_delayed(self, now: float) -> None:
        """Send the datagrams a latency fault held back whose time has come (the scheduler's
        path)."""
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

    def _text(self, severity: int, text: str, now: float) -> None:
        """STATUSTEXT as PX4 formats it: text + TAB, 50-byte chunks sharing an id (capture).

        ``now`` is the clock reading the decision was taken on; the log keeps it, so two texts
        decided ``COM_DISARM_LAND`` apart are logged that far apart, not a clock read later."""
        text = text + "\t"
        self.statustexts.append((now - self.t0, severity, text))
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

    def _signing_changed(self) -> None:
        """Sign (or stop signing) on every link after a key change (sim_stub/signing.py);
        link ids as PX4's MAVLink instances: API link 0, GCS link 1."""
        sg = self.signing
        links = [(self._enc, 0)] + ([(self.gcs_link.enc, 1)] if self.gcs_link else [])
        for enc, link_id in links:
            if sg is None or sg.key is None:
                enc.signer = None
                continue

            def signer(seq: int, spec: MsgSpec, payload: bytes, _enc: Encoder = enc,
                       _lid: int = link_id, _sg: SigningState = sg) -> bytes:
                return _sg.frame(seq, _enc.sysid, _enc.compid, spec.id3, spec.crc_byte,
                                 payload, _lid, mcrf4xx)

            enc.signer = signer
        log.info("sim_stub vehicle %d: MAVLink signing %s", self.instance,
                 "on" if sg is not None and sg.key is not None else "off")

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
    def _on_readable(self) -> None:
        """The API socket has a datagram (the scheduler's reader; one per call, like asyncio's
        datagram transport)."""
        try:
            data, addr = self._sock.recvfrom(_MAX_DATAGRAM)  # type: ignore[union-attr]
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # ICMP errors on loopback (asyncio: error_received)
            self._tx_errors += 1
            return
        self._rx_datagrams += 1
        n = len(data)
        self._rx_bytes += n
        if (self._link_plain and n >= 12 and data[7] == 84 and data[0] == 0xFD
                and n == 12 + data[1] and not data[2] and not data[8] and not data[9]
                and self.signing is None
                and mcrf4xx(_SP_CRC_EXTRA, mcrf4xx(data[1:n - 2], 0xFFFF))
                == data[n - 2] | (data[n - 1] << 8)):  # fmt: skip
            # fast path: a datagram holding exactly one valid unsigned
            # SET_POSITION_TARGET_LOCAL_NED (20 Hz from a fleet controller) gets what
            # _process_datagram would do with it; anything else takes _on_datagram
            now = self._sched.now()
            if self.stage < _N_BOOT_STAGES:
                self._boot_stages(now, now - self.t0)
            self._remote = addr  # answers whoever last sent to it
            self._rx_packets += 1
            if data[5] == self.sysid:
                self._rx_ignored += 1
                return
            payload = data[10:n - 2]
            if len(payload) < _SP_SIZE:
                payload += bytes(_SP_SIZE - len(payload))
            (_, x, y, z, vx, vy, vz, _, _, _, yaw, yaw_rate, mask, tsys, tcomp,
             frame) = _SP_UNPACK(payload)  # fmt: skip
            try:
                self._setpoint_local(tsys, tcomp, frame, mask, x, y, z, vx, vy, vz, yaw,
                                     yaw_rate, now)  # fmt: skip
            except Exception:  # as CommanderMixin._handle_packets: count, log
                self._rx_errors += 1
                if self._rx_errors <= 3:
                    log.exception("sim_stub vehicle %d: msgid 84 from %d/%d failed",
                                  self.instance, data[5], data[6])  # fmt: skip
            return
        self._on_datagram(data, addr)

    def _on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        """A datagram on the API link (counted by the caller): faults, then parsing."""
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
        # the boot state is current for commands
        if self.stage < len(BOOT_STAGES) and self.dead is None:
            self._boot_stages(now, now - self.t0)
        packets, malformed, unknown = self._parser.parse(data)
        if malformed:
            self._rx_malformed += 1
        self._rx_unknown += unknown
        if self.signing is not None and packets:
            packets, changed = self.signing.filter(packets, armed=self.armed, sysid=self.sysid,
                                                   compid=self.compid)
            if changed:
                self._signing_changed()
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

