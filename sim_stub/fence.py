"""PX4's geofence on the mock vehicle: the MAVLink mission protocol for ``mission_type`` FENCE
(upload, download, clear) and the breach check on the *estimated* position with GF_ACTION.

What follows PX4 source (``mavlink_mission.cpp``, ``navigator/geofence``,
``commander/failsafe``) and what could not be confirmed is listed in ``docs/sim_stub.md``
("Geofence"). In short:

* upload: MISSION_COUNT → MISSION_REQUEST_INT(seq) … MISSION_ITEM_INT(seq) → MISSION_ACK;
  count 0 clears; too many items → NO_SPACE; a polygon vertex with param1 < 3 vertices → ERROR;
  an item of an unknown frame → UNSUPPORTED_FRAME; the wrong mission_type → ERROR; an
  unexpected seq is ignored (PX4 re-requests the expected one every 0.25 s); a duplicate of the
  last item after the final ACK is ACKed again; 5 s of silence aborts ("Operation timeout");
* download: MISSION_REQUEST_LIST → MISSION_COUNT, MISSION_REQUEST_INT(seq) → MISSION_ITEM_INT
  (frame GLOBAL_INT, param1 = vertex count or radius), MISSION_ACK from the client ends it;
* the breach check runs at 50 Hz while armed, on the estimate (GF_SOURCE 0 = global position
  estimate); GF_ACTION 0 none, 1 warn, 2 hold (AUTO.LOITER at once), 3 return / 5 land (Hold
  for COM_FAIL_ACT_T first, then the action), 4 terminate (not modelled: land). The text is
  commander's "Failsafe activated" (or "Failsafe activated, entering Hold for N seconds"). The
  hold is cleared only by a mode change or disarm, never by fresh offboard setpoints.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

from . import px4
from .codec import SPECS
from .geo import project

__all__ = [
    "FENCE_MAX_ITEMS",
    "FenceItem",
    "FenceMixin",
    "FENCE_HANDLERS",
    "MAV_MISSION_TYPE_FENCE",
    "MISSION_RESULT",
    "fence_clearance",
    "point_in_fence",
]

MAV_MISSION_TYPE_FENCE = 1
MAV_MISSION_TYPE_ALL = 255

CMD_FENCE_RETURN_POINT = 5000
CMD_POLYGON_INCLUSION = 5001
CMD_POLYGON_EXCLUSION = 5002
CMD_CIRCLE_INCLUSION = 5003
CMD_CIRCLE_EXCLUSION = 5004
_FENCE_COMMANDS = (CMD_FENCE_RETURN_POINT, CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION,
                   CMD_CIRCLE_INCLUSION, CMD_CIRCLE_EXCLUSION)
_GLOBAL_FRAMES = (0, 3, 5, 6)  # GLOBAL, GLOBAL_RELATIVE_ALT, GLOBAL_INT, GLOBAL_RELATIVE_ALT_INT
FRAME_GLOBAL_INT = 5

#: MAV_MISSION_RESULT values PX4 answers with
MISSION_RESULT = {"ACCEPTED": 0, "ERROR": 1, "UNSUPPORTED_FRAME": 2, "UNSUPPORTED": 3,
                  "NO_SPACE": 4, "INVALID": 5, "OPERATION_CANCELLED": 15}
_ACCEPTED, _ERROR = 0, 1

#: PX4: MAX_COUNT[FENCE] = DM_KEY_FENCE_POINTS_MAX - 1 (GEOFENCE_MAX_VERTICES; 64 assumed)
FENCE_MAX_ITEMS = 63
RETRY_S = 0.25  # MAVLINK_MISSION_RETRY_TIMEOUT_DEFAULT (assumed 250 ms)
PROTOCOL_TIMEOUT_S = 5.0  # MAVLINK_MISSION_PROTOCOL_TIMEOUT_DEFAULT (assumed 5 s)
_COMPID_MISSIONPLANNER = 190

#: GF_ACTION values (geofence_params.yaml)
GF_NONE, GF_WARN, GF_HOLD, GF_RTL, GF_TERMINATE, GF_LAND = range(6)


@dataclass(frozen=True)
class FenceItem:
    """One stored fence item as PX4's dataman keeps it (lat/lon in 1e-7 degrees)."""

    command: int
    lat_e7: int
    lon_e7: int
    alt_m: float
    param1: float  # vertex count (polygons) or radius (circles)
    frame: int


def point_in_fence(north_m: float, east_m: float, polygons: list[list[tuple[float, float]]],
                   exclusions: list[list[tuple[float, float]]],
                   circles_in: list[tuple[float, float, float]],
                   circles_out: list[tuple[float, float, float]]) -> bool:
    """PX4's rule: inside at least one inclusion (if any) and inside no exclusion. Polygons
    are crossing-number tests in the local north/east plane."""

    def in_poly(poly: list[tuple[float, float]]) -> bool:
        inside = False
        n = len(poly)
        for i in range(n):
            (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % n]
            if (y1 > east_m) != (y2 > east_m):
                xc = (x2 - x1) * (east_m - y1) / (y2 - y1) + x1
                if north_m < xc:
                    inside = not inside
        return inside

    def in_circle(c: tuple[float, float, float]) -> bool:
        return math.hypot(north_m - c[0], east_m - c[1]) < c[2]

    if any(in_poly(p) for p in exclusions) or any(in_circle(c) for c in circles_out):
        return False
    if not polygons and not circles_in:
        return True
    return any(in_poly(p) for p in polygons) or any(in_circle(c) for c in circles_in)


#: the breach check's shortcut keeps this much of the clearance back (float rounding)
_CLEARANCE_MARGIN_M = 1e-6


def fence_clearance(north_m: float, east_m: float,
                    polygons: list[list[tuple[float, float]]],
                    exclusions: list[list[tuple[float, float]]],
                    circles_in: list[tuple[float, float, float]],
                    circles_out: list[tuple[float, float, float]]) -> float:
    """Distance (m) from the point to the nearest fence boundary (polygon edge or circle).

    :func:`point_in_fence` is the same for every point closer to this one than that: its result
    can only change where a path crosses a boundary. The 50 Hz breach check repeats the full
    test only once the estimate has left that disc."""
    best = math.inf
    for poly in (*polygons, *exclusions):
        n = len(poly)
        for i in range(n):
            (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % n]
            dx, dy = x2 - x1, y2 - y1
            ll = dx * dx + dy * dy
            t = 0.0 if ll <= 0.0 else min(1.0, max(0.0, ((north_m - x1) * dx
                                                         + (east_m - y1) * dy) / ll))
            best = min(best, math.hypot(north_m - (x1 + t * dx), east_m - (y1 + t * dy)))
    for cn, ce, r in (*circles_in, *circles_out):
        best = min(best, abs(math.hypot(north_m - cn, east_m - ce) - r))
    return best


class FenceMixin:
    """The fence part of :class:`~sim_stub.vehicle.MockVehicle` (module docstring)."""

    def _fence_init(self) -> None:
        self.fence_items: list[FenceItem] = []
        self.fence_log: list[tuple[float, str]] = []  # (uptime, what) for tests/diagnostics
        self.fence_breached = False  # the estimate is outside the fence now (armed or not)
        self.fence_failsafe = False  # a geofence action is in control
        self._fence_latched = False  # breach seen; re-armed once back inside
        self._fence_delayed: tuple[float, str] | None = None  # (due, mode) after the Hold delay
        self._fence_shapes: tuple = ([], [], [], [])
        # (north, east, r², inside): no fence boundary within r of that point (fence_clearance)
        self._fence_clear: tuple[float, float, float, bool] | None = None
        self._mt_state = "idle"  # idle | getlist (upload) | sendlist (download)
        self._mt_partner = (0, 0)
        self._mt_seq = 0
        self._mt_count = 0
        self._mt_staging: list[FenceItem] = []
        self._mt_last_sent = 0.0
        self._mt_last_recv = 0.0
        self._mt_crc = 0

    # -- helpers ------------------------------------------------------------------------------
    def _mt_for_me(self, tsys: int, tcomp: int) -> bool:
        # PX4 CHECK_SYSID_COMPID_MISSION: target_system must be ours (not broadcast)
        return tsys == self.sysid and tcomp in (self.compid, _COMPID_MISSIONPLANNER, 0)

    def _mt_ack(self, result: int, tsys: int, tcomp: int, mtype: int = MAV_MISSION_TYPE_FENCE
                ) -> None:
        self._send_named("MISSION_ACK", SPECS["MISSION_ACK"].pack(
            target_system=tsys, target_component=tcomp, type=result, mission_type=mtype))

    def _mt_request(self, now: float) -> None:
        self._mt_last_sent = now
        self._send_named("MISSION_REQUEST_INT", SPECS["MISSION_REQUEST_INT"].pack(
            seq=self._mt_seq, target_system=self._mt_partner[0],
            target_component=self._mt_partner[1], mission_type=MAV_MISSION_TYPE_FENCE))

    def _fence_store(self, items: list[FenceItem], now: float) -> None:
        self.fence_items = list(items)
        crc = 0
        for it in items:
            crc = zlib.crc32(f"{it.command},{it.lat_e7},{it.lon_e7},{it.param1:.6g}".encode(), crc)
        self._mt_crc = crc
        lat0, lon0 = self.origin[0], self.origin[1]
        polys: list[list[tuple[float, float]]] = []
        excl: list[list[tuple[float, float]]] = []
        c_in: list[tuple[float, float, float]] = []
        c_out: list[tuple[float, float, float]] = []
        i = 0
        while i < len(items):
            it = items[i]
            ne = project(lat0, lon0, it.lat_e7 * 1e-7, it.lon_e7 * 1e-7)
            if it.command in (CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION):
                n = int(it.param1 + 0.5)
                group = items[i:i + n]
                if len(group) == n and all(g.command == it.command for g in group):
                    pts = [project(lat0, lon0, g.lat_e7 * 1e-7, g.lon_e7 * 1e-7) for g in group]
                    (polys if it.command == CMD_POLYGON_INCLUSION else excl).append(pts)
                    i += n
                    continue
                self.fence_log.append((self.uptime, f"malformed polygon at item {i} ignored"))
            elif it.command == CMD_CIRCLE_INCLUSION:
                c_in.append((ne[0], ne[1], it.param1))
            elif it.command == CMD_CIRCLE_EXCLUSION:
                c_out.append((ne[0], ne[1], it.param1))
            i += 1
        self._fence_shapes = (polys, excl, c_in, c_out)
        self._fence_clear = None
        self._fence_latched = False
        self.fence_log.append((self.uptime, f"stored {len(items)} items"))

    # -- upload ---------------------------------------------------------------------------------
    def _h_mission_count(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._mt_for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        mtype = m.mission_type  # type: ignore[attr-defined]
        count = m.count  # type: ignore[attr-defined]
        if mtype != MAV_MISSION_TYPE_FENCE:
            self._mt_ack(MISSION_RESULT["UNSUPPORTED"], ssys, scomp, mtype)  # mock: no missions
            return
        if self._mt_state == "idle":
            self._mt_last_recv = now
            if count > FENCE_MAX_ITEMS:
                self._mt_ack(MISSION_RESULT["NO_SPACE"], ssys, scomp)
                return
            if count == 0:
                self._fence_store([], now)
                self._mt_ack(_ACCEPTED, ssys, scomp)
                return
            self._mt_state = "getlist"
            self._mt_partner = (ssys, scomp)
            self._mt_seq = 0
            self._mt_count = count
            self._mt_staging = []
        elif self._mt_state == "getlist":
            self._mt_last_recv = now
            if (ssys, scomp) != self._mt_partner:
                self._mt_ack(_ERROR, ssys, scomp)
                return
            if self._mt_seq != 0:
                self._text(px4.SEV_CRITICAL, "WPM: REJ. CMD: Busy", now)
                self._mt_ack(_ERROR, ssys, scomp)
                return
        else:
            self._text(px4.SEV_CRITICAL, "WPM: IGN MISSION_COUNT: Busy", now)
            self._mt_ack(_ERROR, ssys, scomp)
            return
        self._mt_request(now)

    def _h_mission_item_int(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._mt_for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        if (ssys, scomp) != self._mt_partner:
            self._text(px4.SEV_CRITICAL, "REJ. MIS ITEM: partner id mismatch", now)
            return
        seq = m.seq  # type: ignore[attr-defined]
        if m.mission_type != MAV_MISSION_TYPE_FENCE:  # type: ignore[attr-defined]
            self._mt_ack(_ERROR, ssys, scomp)
            return
        if self._mt_state == "idle":
            if self._mt_seq == seq + 1:  # the GCS missed our final ACK
                self._mt_ack(_ACCEPTED, ssys, scomp)
            else:
                self._text(px4.SEV_CRITICAL, "IGN MISSION_ITEM: No transfer", now)
                self._mt_ack(_ERROR, ssys, scomp)
            return
        if self._mt_state != "getlist":
            self._text(px4.SEV_CRITICAL, "IGN MISSION_ITEM: Busy", now)
            self._mt_ack(_ERROR, ssys, scomp)
            return
        self._mt_last_recv = now
        if seq != self._mt_seq:
            return  # PX4: unexpected sequence, ignored (it re-requests the expected one)
        frame, cmd = m.frame, m.command  # type: ignore[attr-defined]
        result = _ACCEPTED
        if frame not in _GLOBAL_FRAMES:
            result = MISSION_RESULT["UNSUPPORTED_FRAME"]
        elif cmd not in _FENCE_COMMANDS:
            result = MISSION_RESULT["UNSUPPORTED"]  # mock: only fence items in a fence upload
        if result != _ACCEPTED:
            self._text(px4.SEV_CRITICAL, "IGN MISSION_ITEM: Invalid item", now)
            self._mt_ack(result, ssys, scomp)
            self._mt_state = "idle"
            return
        p1 = float(m.param1)  # type: ignore[attr-defined]
        if cmd in (CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION) and int(p1 + 0.5) < 3:
            self._mt_ack(_ERROR, ssys, scomp)  # PX4: "Fence: too few vertices" (console only)
            self._mt_state = "idle"
            return
        # MISSION_ITEM_INT: x, y are degrees * 1e7 in every global frame (PX4's int mode),
        # also for frame GLOBAL (0), which MAVSDK's geofence plugin sends
        lat_e7, lon_e7 = int(m.x), int(m.y)  # type: ignore[attr-defined]
        self._mt_staging.append(FenceItem(cmd, lat_e7, lon_e7, float(m.z), p1, frame))  # type: ignore[attr-defined]
        self._mt_seq = seq + 1
        if self._mt_seq == self._mt_count:
            self._mt_state = "idle"
            self._fence_store(self._mt_staging, now)
            self._mt_ack(_ACCEPTED, ssys, scomp)
        else:
            self._mt_request(now)

    # -- download -------------------------------------------------------------------------------
    def _fence_request_list(self, m: object, ssys: int, scomp: int, now: float) -> None:
        """MISSION_REQUEST_LIST for the fence (the commander routes mission_type 1 here)."""
        if self._mt_seq == len(self.fence_items) and self._mt_state == "sendlist":
            self._mt_state = "idle"  # PX4: all sent, the ACK was lost: start over
        if self._mt_state == "idle" or (self._mt_state == "sendlist"
                                        and (ssys, scomp) == self._mt_partner):
            self._mt_last_recv = now
            self._mt_state = "sendlist"
            self._mt_seq = 0
            self._mt_count = len(self.fence_items)
            self._mt_partner = (ssys, scomp)
            self._mt_last_sent = now
            self._send_named("MISSION_COUNT", SPECS["MISSION_COUNT"].pack(
                count=self._mt_count, target_system=ssys, target_component=scomp,
                mission_type=MAV_MISSION_TYPE_FENCE))
        else:
            self._text(px4.SEV_INFO, "Mission download request ignored, already active", now)

    def _h_mission_request_int(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._mt_for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            self._rx_ignored += 1
            return
        if (ssys, scomp) != self._mt_partner:
            self._text(px4.SEV_CRITICAL, "WPM: REJ. CMD: partner id mismatch", now)
            return
        if self._mt_state == "idle":
            return  # PX4: silently ignored
        if self._mt_state != "sendlist":
            self._text(px4.SEV_CRITICAL, "WPM: REJ. CMD: Busy", now)
            return
        if m.mission_type != MAV_MISSION_TYPE_FENCE:  # type: ignore[attr-defined]
            return
        self._mt_last_recv = now
        seq = m.seq  # type: ignore[attr-defined]
        if seq == self._mt_seq and seq < self._mt_count:
            self._mt_seq += 1
        elif seq != self._mt_seq - 1:
            self._mt_state = "idle"
            self._mt_ack(_ERROR, ssys, scomp)
            self._text(px4.SEV_CRITICAL, "WPM: REJ. CMD: Req. WP was unexpected", now)
            return
        it = self.fence_items[seq]
        self._mt_last_sent = now
        self._send_named("MISSION_ITEM_INT", SPECS["MISSION_ITEM_INT"].pack(
            param1=it.param1, x=it.lat_e7, y=it.lon_e7, z=it.alt_m, seq=seq,
            command=it.command, target_system=ssys, target_component=scomp,
            frame=FRAME_GLOBAL_INT, current=0, autocontinue=0,
            mission_type=MAV_MISSION_TYPE_FENCE))

    def _h_mission_ack(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._mt_for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            return
        if (ssys, scomp) != self._mt_partner:
            self._text(px4.SEV_CRITICAL, "REJ. WP CMD: partner id mismatch", now)
            return
        if self._mt_state == "sendlist" and m.mission_type == MAV_MISSION_TYPE_FENCE:  # type: ignore[attr-defined]
            self._mt_state = "idle"

    def _h_mission_clear_all(self, m: object, ssys: int, scomp: int, now: float) -> None:
        if not self._mt_for_me(m.target_system, m.target_component):  # type: ignore[attr-defined]
            return
        mtype = m.mission_type  # type: ignore[attr-defined]
        if self._mt_state != "idle":
            self._text(px4.SEV_CRITICAL, "WPM: IGN CLEAR CMD: Busy", now)
            return
        if mtype in (MAV_MISSION_TYPE_FENCE, MAV_MISSION_TYPE_ALL):
            self._fence_store([], now)
        self._mt_ack(_ACCEPTED, ssys, scomp, mtype)

    # -- the 50 Hz part -------------------------------------------------------------------------
    def _fence_tick(self, now: float) -> None:
        """Transfer retries/timeouts and the breach check (called from ``control``)."""
        if self._mt_state != "idle":
            if now - self._mt_last_recv > PROTOCOL_TIMEOUT_S:
                self._text(px4.SEV_CRITICAL, "Operation timeout", now)
                self._mt_state = "idle"
            elif self._mt_state == "getlist" and now - self._mt_last_sent > RETRY_S:
                self._mt_request(now)
        if self.fence_failsafe and self.failsafe is None:
            self.fence_failsafe = False  # a mode change or disarm took over
            self._fence_delayed = None
        if not self.fence_items or not self.armed:
            self.fence_breached = False
            return
        north, east = self._pos()[:2]  # PX4's estimate (GF_SOURCE 0)
        c = self._fence_clear
        if c is not None and (north - c[0]) ** 2 + (east - c[1]) ** 2 < c[2]:
            inside = c[3]  # still within the boundary-free disc of the last full check
        else:
            polys, excl, c_in, c_out = self._fence_shapes
            inside = point_in_fence(north, east, polys, excl, c_in, c_out)
            r = fence_clearance(north, east, polys, excl, c_in, c_out) - _CLEARANCE_MARGIN_M
            self._fence_clear = (north, east, r * r, inside) if r > 0.0 else None
        self.fence_breached = not inside
        if inside:
            self._fence_latched = False
        elif not self._fence_latched:
            self._fence_latched = True
            self._fence_breach(now)
        due = self._fence_delayed
        if due is not None and self.fence_failsafe and now >= due[0]:
            mode = px4.MODE_BY_NAME[self._fence_delayed[1]]
            self._fence_delayed = None
            self.failsafe = mode
            if mode.name == "AUTO.RTL":
                self.rtl_phase = "climb"
            self.hold = list(self._pos())
            self._log_mode(now, mode.name)

    def _fence_breach(self, now: float) -> None:
        action = int(self._param("GF_ACTION"))
        p = self._pos()
        self.fence_log.append((self.uptime, f"breach at ({p[0]:.2f}, {p[1]:.2f}) GF_ACTION "
                                            f"{action}"))
        if action == GF_NONE:
            return
        if action == GF_WARN or self.phase != "flying":
            self._text(px4.SEV_CRITICAL, "Failsafe activated", now)
            return
        self.fence_failsafe = True
        self.failsafe = px4.MODE_BY_NAME["AUTO.LOITER"]
        self.hold = list(p)
        self._log_mode(now, "AUTO.LOITER")
        delay = self._param("COM_FAIL_ACT_T")
        if action == GF_HOLD or delay <= 0.1:
            if action != GF_HOLD:
                self._fence_delayed = (now, "AUTO.RTL" if action == GF_RTL else "AUTO.LAND")
            self._text(px4.SEV_CRITICAL, "Failsafe activated", now)
            return
        self._fence_delayed = (now + delay, "AUTO.RTL" if action == GF_RTL else "AUTO.LAND")
        self._text(px4.SEV_CRITICAL,
                   f"Failsafe activated, entering Hold for {int(delay + 0.5)} seconds", now)


#: msgid → handler, merged into the commander's table
FENCE_HANDLERS = {
    44: FenceMixin._h_mission_count,
    73: FenceMixin._h_mission_item_int,
    51: FenceMixin._h_mission_request_int,
    47: FenceMixin._h_mission_ack,
    45: FenceMixin._h_mission_clear_all,
}
