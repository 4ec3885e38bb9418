"""An in-memory fleet for the supervisor's tick: point vehicles behind :class:`MemoryLink`s.

:func:`memory_fleet` builds a :class:`~vtube_fleet.fleet.supervisor.Supervisor` whose vehicles
hover at their slots at the mission altitude, every one in the tube (or taking off), with no
network; :func:`fly_telemetry` moves each vehicle by its last velocity setpoint and writes the
new local position and velocity into its link state, as a telemetry sample would. Used by the
tick's equivalence tests (``tests/test_fleet_tick.py``) and ``bench/bench_tick.py``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from missions import grid_mission

from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.link.base import GeoPoint, VehicleLink
from vtube_fleet.state import Phase


class MemoryLink(VehicleLink):
    """A link whose vehicle is a point that flies its last velocity setpoint (no I/O)."""

    def __init__(self, url: str, sysid: int) -> None:
        super().__init__(url, sysid)
        self.v_ned = (0.0, 0.0, 0.0)
        self.sent = 0

    def send_velocity_ned(self, north_m_s: float, east_m_s: float, down_m_s: float,
                          yaw_deg: float | None = None) -> None:
        self.v_ned = (north_m_s, east_m_s, down_m_s)
        self.sent += 1

    @property
    def latency_s(self) -> float | None:
        return 0.002

    async def connect(self, timeout_s: float = 10.0) -> None: ...
    async def arm(self, timeout_s: float = 10.0) -> None: ...
    async def disarm(self) -> None: ...
    async def takeoff(self, altitude_m: float) -> None: ...
    async def land(self) -> None: ...
    async def hold(self) -> None: ...
    async def start_offboard(self) -> None: ...
    async def stop_offboard(self) -> None: ...
    async def close(self) -> None: ...


def memory_fleet(count: int, phase: str = "tube", spacing_m: float = 5.0,
                 now_s: float | None = None, text: str | None = None, mission_keys: str = ""
                 ) -> tuple[Supervisor, list[MemoryLink]]:
    """``count`` vehicles on :func:`~missions.grid_mission`'s grid (or in the slots of the
    mission ``text``, its ``[mission]`` table last), armed in OFFBOARD at the mission
    altitude, phase IN_TUBE (``"tube"``) or TAKEOFF (``"takeoff"``); their positions stamped
    ``now_s`` (default: now); ``mission_keys``: lines added to the ``[mission]`` table."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "tick.toml"
        body = grid_mission(count, 20.0, 60.0, spacing_m) if text is None else text
        path.write_text(body  # [mission] last: L, σ fixed
                        + "latency_s = 0.25\nposition_accuracy_m = 0.29\n" + mission_keys)
        mission = load_mission(path)
    links = [MemoryLink(f"udpin://127.0.0.1:{30000 + i}", i % 255 + 1) for i in range(count)]
    f = mission.frame
    lat0, lon0, alt0 = f.lat0_deg, f.lon0_deg, f.alt0_m  # every vehicle's origin: the tube's
    slots = mission.slots
    n, e, d = f.tube_to_local_ned(slots[:, 0], slots[:, 1],
                                  np.full(count, mission.config.altitude_m), lat0, lon0, alt0)
    now = time.monotonic() if now_s is None else now_s
    for i, link in enumerate(links):
        s = link.state
        s.origin = GeoPoint(lat0, lon0, alt0)
        s.north_m, s.east_m, s.down_m = float(n[i]), float(e[i]), float(d[i])
        s.vn_m_s = s.ve_m_s = s.vd_m_s = 0.0
        s.armed, s.flight_mode, s.landed_state = True, "OFFBOARD", "IN_AIR"
        s.last_position_s = s.last_heartbeat_s = s.last_packet_s = now
        s.pos_accuracy_m = 0.29
    sup = Supervisor(mission, links, fence=False)
    # re-partitions in the tick itself, as a test ticking by hand expects them (the runtime
    # plans them in a worker thread: tests/test_fleet_tick.py has that case)
    sup.ticker.replan_worker = None
    for p in sup.pilots:
        p.set_phase(Phase.TAKEOFF if phase == "takeoff" else Phase.IN_TUBE)
    sup.table.takeoff_xy[:] = slots[: count]
    sup.stage = phase
    if phase == "tube":
        sup.tube_start_s = sup.t_s()
    return sup, links


def fly_telemetry(links: list[MemoryLink], dt_s: float, now_s: float) -> None:
    """Each vehicle flies its last setpoint for ``dt_s``; a new sample stamped ``now_s``."""
    for link in links:
        s = link.state
        vn, ve, vd = link.v_ned
        s.north_m += dt_s * vn
        s.east_m += dt_s * ve
        s.down_m += dt_s * vd
        s.vn_m_s, s.ve_m_s, s.vd_m_s = vn, ve, vd
        s.last_position_s = now_s
