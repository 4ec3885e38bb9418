"""The mock vehicle's commander: incoming messages, commands, modes, failsafes, PX4's logic.

:class:`CommanderMixin` is the PX4 state machine of :class:`~sim_stub.vehicle.MockVehicle`:
message handlers (``_h_*``), commands (``_c_*``, each returns a MAV_RESULT) and the 50 Hz
control logic (:meth:`CommanderMixin.control`, driven by the scheduler).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from . import px4
from .fence import FENCE_HANDLERS
from .geo import project, reproject
from .px4 import (
    BOOT_STAGES,
    DOWN_SPEED_CAP,
    LAND_DETECT_S,
    LANDED_IN_AIR,
    LANDED_ON_GROUND,
    LIFTOFF_S,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MAV_RESULT_UNSUPPORTED,
    MODE_BY_NAME,
    TAKEOFF_ACCEPT_M,
    TAKEOFF_DETECT_S,
    UP_SPEED_CAP,
    XY_SPEED_CAP,
    Mode,
)
from .telemetry import REQUESTABLE_EXTRA, STREAM_BY_ID, quat_from_euler
from .telemetry import STRUCTS as _S

__all__ = ["CommanderMixin", "Setpoint"]

_N_BOOT_STAGES = len(BOOT_STAGES)
_OFFBOARD = MODE_BY_NAME["OFFBOARD"]

log = logging.getLogger("sim_stub")

_NAN = float("nan")

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

@dataclass
class Setpoint:
    """The last SET_POSITION_TARGET_*, resolved to NED at reception."""

    pos: list[float | None] = field(default_factory=lambda: [None, None, None])
    vel: list[float | None] = field(default_factory=lambda: [None, None, None])
    yaw: float | None = None
    yaw_rate: float | None = None



class CommanderMixin:
    """PX4's commander of :class:`~sim_stub.vehicle.MockVehicle` (module docstring)."""

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
        fault = self.faults.mode_fault
        if fault and cmd == CMD_DO_SET_MODE and px4.mode_from_set_mode(
                int(p[1]) if math.isfinite(p[1]) else 0,
                int(p[2]) if math.isfinite(p[2]) else 0) is not _OFFBOARD:
            self.command_log.append((now - self.t0, cmd, tuple(p), -1 if fault == "drop"
                                     else MAV_RESULT_DENIED))
            if fault == "deny":
                self._ack(cmd, MAV_RESULT_DENIED, ssys, scomp)
            return  # "drop": no COMMAND_ACK (Faults.mode_fault)
        if handler is None:
            result = MAV_RESULT_UNSUPPORTED
        else:
            result = handler(self, p, ssys, scomp, now, is_int)
        self.command_log.append((now - self.t0, cmd, tuple(p), result))
        self._ack(cmd, result, ssys, scomp)

    def _h_setpoint_local(self, m: dict, ssys: int, scomp: int, now: float) -> None:
        self._setpoint_local(m["target_system"], m["target_component"], m["coordinate_frame"],
                             m["type_mask"], m["x"], m["y"], m["z"], m["vx"], m["vy"], m["vz"],
                             m["yaw"], m["yaw_rate"], now)  # type: ignore[arg-type]

    def _setpoint_local(self, tsys: int, tcomp: int, frame: int, mask: int, x: float, y: float,
                        z: float, vx: float, vy: float, vz: float, yaw_sp: float,
                        yaw_rate: float, now: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED's fields (also the datagram fast path's entry)."""
        if not ((tsys == self.sysid or tsys == 0) and (tcomp == self.compid or tcomp == 0)):
            self._rx_ignored += 1
            return
        if frame not in (1, 7, 8, 9):  # LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED
            self._rx_ignored += 1
            return
        mask = int(mask)
        if frame in (8, 9):  # body frames: rotate by the heading
            yaw = self._yaw()
            c, s = math.cos(yaw), math.sin(yaw)
            x, y = c * x - s * y, s * x + c * y
            vx, vy = c * vx - s * vy, s * vx + c * vy
        isfinite = math.isfinite
        pos: list[float | None] = [None, None, None]
        if mask & 7 != 7:
            p = self._pos()
            offset = frame != 1
            for i, val in enumerate((x, y, z)):
                if not mask & (1 << i) and isfinite(val):
                    pos[i] = val + p[i] if offset else val
        vel: list[float | None] = [
            vx if not mask & 8 and isfinite(vx) else None,
            vy if not mask & 16 and isfinite(vy) else None,
            vz if not mask & 32 and isfinite(vz) else None,
        ]
        self._accept_setpoint(
            Setpoint(pos, vel,
                     yaw_sp if not mask & 0x400 and isfinite(yaw_sp) else None,
                     yaw_rate if not mask & 0x800 and isfinite(yaw_rate) else None),
            now)  # fmt: skip

    def _h_setpoint_global(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        mask = int(m.type_mask)  # type: ignore[attr-defined]
        sp = Setpoint()
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

    def _accept_setpoint(self, sp: Setpoint, now: float) -> None:
        self.sp = sp
        self.sp_time = now
        self.sp_ever = True
        if not self.sp_fresh:
            self.sp_fresh = True
            if self.ready:
                self._events(px4.HEALTH_BURST_READY)
        # a velocity setpoint acts at once in offboard (no wait for the 50 Hz logic)
        if self.armed and self.phase == "flying" and (self.failsafe or self.intended) is _OFFBOARD:
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
            self._text(px4.SEV_INFO, f"[pm] unknown param: {name}", now)
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
        if mtype == 1:  # MAV_MISSION_TYPE_FENCE (sim_stub/fence.py)
            self._fence_request_list(m, ssys, scomp, now)  # type: ignore[attr-defined]
            return
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
        self._text(px4.SEV_CRITICAL, f"Unsupported ARM_DISARM param: {p[0]:.3f}", now)
        return MAV_RESULT_UNSUPPORTED

    def _arm(self, now: float, forced: bool) -> int:
        if self.armed:
            return MAV_RESULT_ACCEPTED
        if not forced and not self._prearm_ok():
            self._text(px4.SEV_CRITICAL, "Arming denied: Resolve system health failures first", now)
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
        self._text(px4.SEV_INFO, "Armed by external command", now)
        self._event(px4.EVENTS["armed"])
        self._set_home(now)  # capture: home is re-set at arming
        self._log_mode(now, self.mode_name)
        return MAV_RESULT_ACCEPTED

    def _disarm(self, now: float, reason: str, forced: bool = False) -> int:
        if not self.armed:
            return MAV_RESULT_ACCEPTED  # capture: DISARM while disarmed is ACCEPTED, no text
        if not forced and self.landed_state != LANDED_ON_GROUND and self.phase == "flying":
            self._text(px4.SEV_CRITICAL, "Disarming denied: not landed", now)
            return MAV_RESULT_TEMPORARILY_REJECTED
        self.armed = False
        self._text(px4.SEV_INFO, f"Disarmed by {reason}", now)
        self._event(px4.EVENTS["disarmed"], bytes((px4.ARM_REASON.get(reason, 4),)))
        if self.phase in ("flying", "landed") and self.took_off:
            self._set_home(now)  # capture: home re-set to the landing point at disarm
        if reason == "landing":
            self.health_rereport_at = now + px4.HEALTH_AFTER_LANDING_S
        self.failsafe = None  # PX4: the user intention returns to the mode set before
        self.phase = "ground"
        self.took_off = False
        self.landed_state = LANDED_ON_GROUND
        self._sched.airborne[self.slot] = False
        self._sched.u[self.slot] = 0.0
        self._offboard_cache = None  # u no longer holds the setpoint's velocity
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
                self._text(px4.SEV_CRITICAL, "Unsupported auto mode", now)
                return MAV_RESULT_TEMPORARILY_REJECTED
            return MAV_RESULT_ACCEPTED  # PX4: an unknown main mode changes nothing
        return self._change_mode(mode, now, scomp)

    def _change_mode(self, mode: Mode, now: float, scomp: int = 190) -> int:
        """PX4's UserModeIntention: any mode while disarmed, only runnable modes while armed."""
        if self.armed and not self._can_run(mode):
            if scomp == 190:
                self._text(
                    px4.SEV_CRITICAL, f"Switching to {mode.label} is currently not available", now
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
            self._text(px4.SEV_INFO, "Landing at current position", now)
        return res

    def _c_rtl(self, p: list[float], ssys: int, scomp: int, now: float, is_int: bool) -> int:
        res = self._change_mode(MODE_BY_NAME["AUTO.RTL"], now, scomp)
        if res == MAV_RESULT_ACCEPTED:
            self._text(px4.SEV_INFO, "Returning to launch", now)
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
        sd = STREAM_BY_ID.get(msgid)
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
        sd = STREAM_BY_ID.get(msgid)
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
        name = REQUESTABLE_EXTRA.get(msgid)
        if name is None:
            sd = STREAM_BY_ID.get(msgid)
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
    def control(self, now: float) -> None:
        """One step of PX4's logic at 50 Hz (boot, arming, modes, failsafes, the commanded
        velocity for the dynamics); called by the scheduler."""
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
        if (f.slow_at_s is not None and up >= f.slow_at_s
                and self._sched.xy_gain[self.slot] != f.slow_gain):
            self._sched.slow(self.slot, f.slow_gain)
        if self.stage < _N_BOOT_STAGES:
            self._boot_stages(now, up)
        # offboard signal (COM_OF_LOSS_T)
        sp_time = self.sp_time
        fresh = sp_time is not None and now - sp_time <= self.params["COM_OF_LOSS_T"].value
        if self.sp_fresh and not fresh:
            self.sp_fresh = False
            if self.ready:
                self._events(px4.HEALTH_BURST_NO_OFFBOARD)
        if self.health_rereport_at is not None and now >= self.health_rereport_at:
            self.health_rereport_at = None
            if not self.armed:
                self._events(
                    px4.HEALTH_BURST_READY if self.sp_fresh else px4.HEALTH_BURST_NO_OFFBOARD
                )
        self._fence_tick(now)  # type: ignore[attr-defined]  # sim_stub/fence.py
        if self.armed:
            self._armed_logic(now)
        else:
            self._sched.airborne[self.slot] = False

    def _boot_stages(self, now: float, up: float) -> None:
        while self.stage < len(BOOT_STAGES) and up >= self._boot_at(BOOT_STAGES[self.stage]):
            key = BOOT_STAGES[self.stage]
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
                self._text(px4.SEV_INFO, f"[logger] ./log/{stamp}.ulg", now)
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
            elif self.failsafe is not None and self.sp_fresh and not self.fence_failsafe:  # type: ignore[attr-defined]
                self.failsafe = None  # PX4: mode fallback clears when the condition clears
                mode = self.mode
                self.hold = list(self._pos())
                self._log_mode(now, mode.name)
        phase = self.phase
        if phase == "spoolup":
            if now - self.phase_t >= self.params["COM_SPOOLUP_TIME"].value:
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
                self._text(px4.SEV_INFO, "Takeoff detected", now)
                self._event(px4.EVENTS["takeoff"])
            if el >= LIFTOFF_S:
                self.phase = phase = "flying"
                self.touchdown_t = None
        if phase == "flying":
            sched.airborne[slot] = True
            if mode.name == "OFFBOARD":
                self._command_offboard()
            else:
                self._command(mode, now)
            if sched.contact_rows[slot] and sched.u[slot, 2] >= -0.05:  # touching, not climbing
                if self.touchdown_t is None:
                    self.touchdown_t = now
                elif now - self.touchdown_t >= LAND_DETECT_S:
                    self.phase = "landed"
                    self.landed_t = now
                    self.landed_state = LANDED_ON_GROUND
                    sched.airborne[slot] = False
                    sched.u[slot] = 0.0
                    self._offboard_cache = None
                    self._text(px4.SEV_INFO, "Landing detected", now)
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
            self._offboard_cache = None
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
        # the health burst went out when the offboard signal was lost (capture 1c: once)
        self._text(px4.SEV_CRITICAL, "Failsafe activated", now)
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
        sched = self._sched
        slot = self.slot
        sp = self.sp
        params = self.params
        pxy, pup, pdn = (params["MPC_XY_VEL_MAX"], params["MPC_Z_VEL_MAX_UP"],
                         params["MPC_Z_VEL_MAX_DN"])  # fmt: skip
        c = self._offboard_cache
        spos, svel = sp.pos, sp.vel
        if c is not None and c[0] is sp and c[1] is pxy and c[2] is pup and c[3] is pdn:
            return  # u and the yaw setpoint still hold this velocity setpoint's command
        if (spos[0] is None and spos[1] is None and spos[2] is None and svel[0] is not None
              and svel[1] is not None and svel[2] is not None):
            # velocity only (a fleet controller's setpoint): the general branch and _limit
            # below, without the state they do not need
            o0, o1, o2 = svel
            xy_max = min(pxy.value, XY_SPEED_CAP)
            nxy = math.hypot(o0, o1)
            if nxy > xy_max > 0:
                o0 *= xy_max / nxy
                o1 *= xy_max / nxy
            up = min(pup.value, UP_SPEED_CAP)
            o2 = min(max(o2, -up), min(pdn.value, DOWN_SPEED_CAP))
            out = [o0, o1, o2]
            cache: tuple | None = (sp, pxy, pup, pdn)
        else:
            p = self._pos()
            kp_xy = params["MPC_XY_P"].value
            kp_z = params["MPC_Z_P"].value
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
            self._limit(out, pxy.value)
            cache = None  # depends on the position: computed again every time
        u = sched.u
        u[slot, 0], u[slot, 1], u[slot, 2] = out
        if sp.yaw is not None:
            sched.yaw_sp[slot] = sp.yaw
            sched.yaw_rate_sp[slot] = 0.0
        else:
            sched.yaw_sp[slot] = _NAN
            sched.yaw_rate_sp[slot] = sp.yaw_rate or 0.0
        self._offboard_cache = cache

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
        self._offboard_cache = None  # this mode writes u and the yaw setpoint
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
        moved = self.armed or self.took_off
        self.home_q = quat_from_euler(r, pch, yaw) if moved else (1.0, 0.0, 0.0, 0.0)
        self.home_time_us = self._tboot_us(now)

    # ------------------------------------------------------------------------------------------


_HANDLERS: dict[int, Callable[..., None]] = {
    0: CommanderMixin._h_heartbeat,
    75: CommanderMixin._h_command,
    76: CommanderMixin._h_command,
    84: CommanderMixin._h_setpoint_local,
    86: CommanderMixin._h_setpoint_global,
    20: CommanderMixin._h_param_request_read,
    21: CommanderMixin._h_param_request_list,
    23: CommanderMixin._h_param_set,
    111: CommanderMixin._h_timesync,
    4: CommanderMixin._h_ping,
    43: CommanderMixin._h_mission_request_list,
}
_HANDLERS.update(FENCE_HANDLERS)  # sim_stub/fence.py: the FENCE mission protocol
_COMMANDS: dict[int, Callable[..., int]] = {
    CMD_COMPONENT_ARM_DISARM: CommanderMixin._c_arm_disarm,
    CMD_DO_SET_MODE: CommanderMixin._c_set_mode,
    CMD_NAV_TAKEOFF: CommanderMixin._c_takeoff,
    CMD_NAV_LAND: CommanderMixin._c_land,
    CMD_NAV_RETURN_TO_LAUNCH: CommanderMixin._c_rtl,
    CMD_DO_REPOSITION: CommanderMixin._c_reposition,
    CMD_DO_CHANGE_SPEED: CommanderMixin._c_change_speed,
    CMD_DO_SET_HOME: CommanderMixin._c_set_home,
    CMD_SET_MESSAGE_INTERVAL: CommanderMixin._c_set_message_interval,
    CMD_GET_MESSAGE_INTERVAL: CommanderMixin._c_get_message_interval,
    CMD_REQUEST_MESSAGE: CommanderMixin._c_request_message,
    CMD_REQUEST_AUTOPILOT_CAPABILITIES: CommanderMixin._c_autopilot_capabilities,
}

def _param_name(raw: bytes | str) -> str:
    if isinstance(raw, bytes):
        raw = raw.split(b"\x00", 1)[0].decode("ascii", "replace")
    return raw.split("\x00", 1)[0]


