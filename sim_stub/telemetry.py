"""The mock vehicle's telemetry: PX4's stream catalogue and one builder per message.

Rates and contents follow the captures in ``tests/data/px4_sitl/`` (see ``docs/sim_stub.md``).
:class:`TelemetryMixin` holds the builders (``_b_<message>``) of
:class:`~sim_stub.vehicle.MockVehicle`.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from . import px4
from .codec import SPECS, MsgSpec
from .geo import reproject
from .px4 import (
    BOOT_STAGES,
    LANDED_IN_AIR,
    LIFTOFF_S,
)

if TYPE_CHECKING:  # pragma: no cover
    from .vehicle import GcsLink

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
STREAM_BY_NAME = {s.name: s for s in STREAM_CATALOG}
STREAM_BY_ID = {SPECS[s.name].msgid: s for s in STREAM_CATALOG}
# messages REQUEST_MESSAGE can produce besides the streams
REQUESTABLE_EXTRA = {148: "AUTOPILOT_VERSION", 49: "GPS_GLOBAL_ORIGIN", 242: "HOME_POSITION"}

#: struct.Struct of every known message payload, by name.
STRUCTS = {name: sp.struct for name, sp in SPECS.items()}
_S = STRUCTS
_CRC = struct.Struct("<H")
__all__ = [
    "GCS_LINK_PROFILES",
    "GCS_LINK_STREAMS",
    "PROFILES",
    "STREAM_BY_ID",
    "STREAM_BY_NAME",
    "STREAM_CATALOG",
    "STRUCTS",
    "StreamDef",
    "StreamState",
    "TelemetryMixin",
    "quat_from_euler",
]

_NAN = float("nan")
_TWO_PI = 2.0 * math.pi

# AUTOPILOT_VERSION.capabilities: MISSION_FLOAT|PARAM_FLOAT|MISSION_INT|COMMAND_INT|
# PARAM_ENCODE_BYTEWISE|SET_ATTITUDE_TARGET|SET_POSITION_TARGET_LOCAL_NED|
# SET_POSITION_TARGET_GLOBAL_INT|MAVLINK2|MISSION_FENCE|MISSION_RALLY (no FTP: not modelled)
_CAPABILITIES = 1 | 2 | 4 | 8 | 16 | 128 | 256 | 512 | 8192 | 16384 | 32768
_FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 0  # 1.16.0 dev (capture era)


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



class TelemetryMixin:
    """The message builders of :class:`~sim_stub.vehicle.MockVehicle`: each returns the full
    payload, or None to skip this time."""

    # message builders: return the full payload, or None to skip this time
    def _b_heartbeat(self, now: float) -> bytes:
        if self.stage < len(BOOT_STAGES) and self.dead is None:
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
        self.battery_pct(now)
        bat = self.battery
        return _S["SYS_STATUS"].pack(
            present, enabled, health, 100, bat.voltage_mv, -100, 0, errors, 0, 0, 0, 0,
            bat.remaining_pct, 0, 0, 1
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
        self.battery_pct(now)
        bat = self.battery
        return _S["BATTERY_STATUS"].pack(
            0, -1, 32767, bat.voltage_mv, *_V9, -100, 0, 1, 1, bat.remaining_pct, 0,
            bat.charge_state, 0, 0, 0, 0, 0, 0
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



_ODO_HEAD = struct.Struct("<Qfff4fffffff")
# ODOMETRY covariances and trailing fields as captured (upper triangle, NaN = unknown),
# frame_id/child_frame_id LOCAL_NED, reset_counter 4, estimator_type 8 (AUTOPILOT), quality 0
_POSE_COV = [100.0] + [_NAN] * 5 + [100.0] + [_NAN] * 4 + [100.0] + [_NAN] * 3
_POSE_COV += [0.01, _NAN, _NAN, 0.01, _NAN, 1e-6]
_VEL_COV = [25.0] + [_NAN] * 5 + [25.0] + [_NAN] * 4 + [10.0] + [_NAN] * 9
_ODO_TAIL = struct.pack("<21f21fBBBBb", *_POSE_COV, *_VEL_COV, 1, 1, 4, 8, 0)
_ZERO20 = (0,) * 20
_V9 = (65535,) * 9


def _u16(x: float) -> int:
    return min(max(int(x), 0), 0xFFFF)


def _i16(x: float) -> int:
    return max(-32768, min(32767, int(round(x))))


def quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
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
