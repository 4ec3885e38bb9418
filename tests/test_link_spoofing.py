"""End-to-end: the unsigned attack of issue 33 on a flying mock mission, and a port that carries
other vehicles (issue 33's 14550 clash), at the level a user runs them (``launch.fly``, an agent).

The mission is ``configs/px4_sitl_3.toml`` on sim_stub vehicles with PX4 SITL's estimate errors.
When the fleet enters the tube, a spoofer (``tests/spoofer.py``, pymavlink, its own UDP socket)
sends every vehicle's controller port unsigned LOCAL_POSITION_NED, ATTITUDE and HEARTBEATs,
50 Hz for 10 s, claiming each vehicle sits beside the obstacle moving across the tube at
3 m/s. Judged from the mock's ground truth (``truth.py``) and from what the links counted:

* defended (both backends): the truth stays clean, the controller's positions stay within the
  estimate's error of the truth, the refusals are counted (mavlink: at the door, by address;
  mavsdk: MAVSDK takes them, the hub sees a second address and the plausibility checks refuse
  the positions);
* the plausibility checks alone (the spoofer forges the vehicle's address: here, source
  pinning off, and it sniffs the vehicle's clock): every fake refused, a telemetry fault
  "telemetry from two sources";
* undefended (the test switch: no checks, no source pinning): the positions the controller
  used jump to the fakes, metres from the truth.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np
import pytest
from fleet_ports import free_ports
from missions import PX4_SITL_3
from spoofer import Spoofer, SpoofTarget
from truth import TruthLog, assert_true_clearance, true_clearance

from sim_stub import MockFleet, PortScheme
from vtube_fleet.config.mission import Mission, load_mission
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.link.endpoints import parse_endpoint

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

ATTACK_S = 10.0


def fake_near_obstacle(mission: Mission, vehicle: object, k: int
                       ) -> Callable[[float], tuple[float, float, float, float, float, float]]:
    """Vehicle ``k`` claimed 1 m before the obstacle (1.2 m apart across the tube), at
    altitude, moving across the tube at 3 m/s, in its own local frame."""
    ob = mission.scenario.obstacles[0]
    x, y = float(ob.center[0]) - 1.0, float(ob.center[1]) + 1.2 * (k - 1)
    n, e, d = (float(v) for v in mission.frame.tube_to_local_ned(
        x, y, mission.config.altitude_m, *vehicle.origin))  # type: ignore[attr-defined]
    return lambda t: (n, e, d, 0.0, 3.0, 0.0)


class SpoofedFlight:
    """One flight of the mission under attack: the result, the supervisor, the truth, the
    spoofer and, per tick of the attack, the largest distance between the position the
    controller used and the truth."""

    def __init__(self) -> None:
        self.sup: Supervisor | None = None
        self.log: TruthLog | None = None
        self.spoofer: Spoofer | None = None
        self.deviation_m: list[float] = []
        self.result = None

    @property
    def links(self) -> list:
        assert self.sup is not None
        return [p.link for p in self.sup.pilots]


async def fly_spoofed(tmp_path: Path, backend: str, seed: int, *, sniff: bool = False,
                      link_options: dict | None = None) -> SpoofedFlight:
    mission = load_mission(PX4_SITL_3)
    n = mission.count
    run = SpoofedFlight()
    boot = {"boot_time_scale": 0.3, "port_scheme": free_ports(n), "seed": seed}
    async with mock_fleet(mission, **boot) as fleet:
        log = run.log = TruthLog(fleet, mission)
        targets = []
        for k, (url, v) in enumerate(zip(fleet.endpoints, fleet.vehicles, strict=True)):
            ep = parse_endpoint(url)
            clock = (lambda v=v: v._tboot_ms(v._sched.now()) + 1) if sniff else None
            targets.append(SpoofTarget((ep.host, ep.port), v.sysid,
                                       fake_near_obstacle(mission, v, k), clock))
        spoofer = run.spoofer = Spoofer(targets, duration_s=ATTACK_S)

        def hook(tick: int, sup: Supervisor) -> None:
            run.sup = sup
            log(tick, sup)
            if sup.tube_start_s is not None and not spoofer.started:
                spoofer.start()
            if spoofer.started and not spoofer.done.is_set() and sup.trace:
                d = np.hypot(*(sup.trace[-1].pos - log.xy[-1]).T)
                if np.isfinite(d).any():
                    run.deviation_m.append(float(np.nanmax(d)))

        try:
            run.result = await fly(mission, backend=backend, endpoints=fleet.endpoints,
                                   out_dir=tmp_path, keep_trace=True, tick_hook=hook,
                                   link_options=link_options)
        finally:
            spoofer.stop()
    assert spoofer.sent > 3 * 50 * 3 * 2, spoofer.sent  # at least 2 s of the attack
    return run


def report(name: str, run: SpoofedFlight) -> dict[str, float]:
    assert run.log is not None and run.result is not None
    truth = true_clearance(run.log)
    refused = [dict(lk.state.telemetry_refused) for lk in run.links]
    print(f"\n{name}: {run.result.outcome}; spoofer sent {run.spoofer.sent}; TRUE clearance: "
          f"pair {truth['pair']:.2f} m, legs {truth['left_leg']:.2f} / {truth['right_leg']:.2f}"
          f" m, obstacle {truth['obstacle']:.2f} m; controller vs truth during the attack: max "
          f"{max(run.deviation_m):.2f} m; refused {refused}; faults "
          f"{[lk.state.telemetry_fault for lk in run.links]}")
    return truth


@pytest.mark.parametrize(("backend", "seed"), [("mavlink", 5), ("mavsdk", 6)],
                         ids=["mavlink", "mavsdk"])
async def test_the_unsigned_attack_is_refused_and_the_fleet_flies_true(
        tmp_path: Path, backend: str, seed: int) -> None:
    run = await fly_spoofed(tmp_path, backend, seed)
    report(f"spoofed, defended ({backend})", run)
    assert_true_clearance(run.log)  # type: ignore[arg-type]
    assert run.deviation_m and max(run.deviation_m) < 1.5  # the estimate's error, no fake
    refused = [lk.state.telemetry_refused for lk in run.links]
    if backend == "mavlink":
        # refused at the door: the vehicle's id from another address, datagram by datagram
        assert all(r["other_source"] > 300 for r in refused), refused
        assert all(lk.state.telemetry_fault is None for lk in run.links)
        assert run.result.outcome == "completed", run.result.reason
        # the run says what happened: the refusals counted in its summary and its reason
        told = run.result.summary["telemetry"]
        assert told["refused"]["other_source"] == sum(r["other_source"] for r in refused)
        assert told["faults"] == []
        assert run.result.reason.startswith("telemetry refused (not the vehicles'): "
                                            "other_source "), run.result.reason
    else:
        # MAVSDK takes the fakes: the hub sees the second address (a fault: nothing can
        # refuse them), the plausibility checks refuse the positions
        assert all(r["other_source"] == 1 for r in refused), refused
        assert all(r["position_jump"] + r["speed"] > 50 for r in refused), refused
        for lk in run.links:
            assert (lk.state.telemetry_fault or "").startswith(
                f"telemetry from two sources: system {lk.sysid} speaks from "), lk.name
        _held_and_said(run)


async def test_a_spoofer_with_the_vehicles_address_meets_the_plausibility_checks(
        tmp_path: Path) -> None:
    """An attacker who forges the vehicle's address on the LAN and sniffs its clock (source
    pinning off stands in for the forged address): every fake is refused as a jump, the
    controller flies the truth, and the link says its telemetry comes from two sources."""
    run = await fly_spoofed(tmp_path, "mavlink", 8, sniff=True,
                            link_options={"pin_source": False})
    report("spoofed with the vehicle's address, plausibility checks", run)
    assert_true_clearance(run.log)  # type: ignore[arg-type]
    assert max(run.deviation_m) < 1.5
    for lk in run.links:
        r = lk.state.telemetry_refused
        assert r["position_jump"] > 300 and r["other_source"] == 0, (lk.name, dict(r))
        fault = lk.state.telemetry_fault or ""
        assert fault.startswith("telemetry from two sources: position jumped"), (lk.name, fault)
    _held_and_said(run)


def _held_and_said(run: SpoofedFlight) -> None:
    """Telemetry in conflict beyond the window: the vehicle held (an obstacle for the others,
    its event names why), and the run is not `completed`: exit 3, the vehicles and the reason
    in its reason and its summary."""
    assert run.result is not None and run.sup is not None
    assert run.result.outcome in ("incomplete", "aborted"), run.result.reason
    assert run.result.exit_code == 3
    assert "telemetry not trustworthy: " in run.result.reason, run.result.reason
    faults = run.result.summary["telemetry"]["faults"]
    assert {f["vehicle"] for f in faults} == {p.vehicle_id for p in run.sup.pilots}
    held = [e for e in run.result.summary["events"]
            if "→ holding (telemetry not trustworthy: " in e["text"]]
    assert held, [e["text"] for e in run.result.summary["events"]][-20:]


async def test_without_the_defences_the_same_attack_moves_the_fleet(tmp_path: Path) -> None:
    """The test switch (no plausibility checks, no source pinning): the positions the
    controller flies on are the fakes, metres from the truth, jumping at 50 Hz."""
    run = await fly_spoofed(tmp_path, "mavlink", 5,
                            link_options={"telemetry": None, "pin_source": False})
    report("spoofed, undefended", run)
    assert max(run.deviation_m) > 5.0
    assert all(not lk.state.telemetry_refused for lk in run.links)


# -- a port that carries other vehicles ---------------------------------------------------------
@contextlib.asynccontextmanager
async def clashing_fleet(mission: Mission, n: int) -> AsyncIterator[MockFleet]:
    """``n`` mock vehicles in the mission's slots whose vehicles 0..n-2 send their GCS link to
    vehicle n-1's API port, as PX4 SITL instances 0-9 send theirs to 14550, the API port of
    instance 10 (whose own GCS link goes elsewhere). The built-in mock (``launch.mock_fleet``)
    moves such a GCS link; PX4 SITL does not."""
    free = free_ports(2 * n)  # API ports gcs_base + i; its upper half for the GCS links
    api_last = free.gcs_base + n - 1
    scheme = PortScheme("clash", vehicle_base=free.vehicle_base, gcs_base=free.gcs_base,
                        gcs_link_base=free.gcs_base + n,
                        gcs_link_remotes=((0, api_last), (n - 1, free.vehicle_base + n)))
    homes = [tuple(float(x) for x in g) for g in mission.slot_geodetic()[:n]]
    async with MockFleet(n, homes=homes, port_scheme=scheme, boot_time_scale=0.3) as fleet:
        yield fleet


@pytest.mark.parametrize("backend", ["mavlink", "mavsdk"])
async def test_a_port_that_hears_other_vehicles_is_refused_before_arming(
        tmp_path: Path, backend: str) -> None:
    mission = load_mission(PX4_SITL_3)
    async with clashing_fleet(mission, 3) as fleet:
        result = await fly(mission, backend=backend, endpoints=fleet.endpoints,
                           out_dir=tmp_path)
        armed = [any(a for _, _, a in v.mode_log) for v in fleet.vehicles]
    print(f"\n{backend}: {result.outcome}: {result.reason}")
    assert result.outcome == "failed" and armed == [False, False, False]
    reason = result.reason
    assert "not ready" in reason and "\n" not in reason
    if backend == "mavlink":
        assert ("vehicle 3 (" in reason and "its port hears 3 vehicles, "
                "systems 1, 2 and 3 (this link flies system 3" in reason)
    else:  # one MAVSDK for the fleet: it merges systems 1 and 2 from both addresses
        assert "system 1 speaks from 2 addresses" in reason
        assert "system 2 speaks from 2 addresses" in reason


async def test_an_agent_on_a_port_with_other_vehicles_is_refused_before_arming(
        tmp_path: Path) -> None:
    """Issue 33's second finding: agent 10 on udpin 14550 heard eleven vehicles and took the
    first. Here agent 2 of three, on the port vehicles 0 and 1 send their GCS link to: it
    refuses the run naming the vehicles, the coordinator says so, nothing arms."""
    from broker import LocalBroker

    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess
    from vtube_fleet.link import LinkConflict

    mission = load_mission(PX4_SITL_3)
    with LocalBroker() as broker:
        async with clashing_fleet(mission, 3) as fleet:
            agent = AgentProcess(PX4_SITL_3, 2, broker=broker.url, join_timeout_s=60,
                                 endpoint=fleet.endpoints[2])
            coordinator = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "vtube_fleet", "mission", "start", str(PX4_SITL_3),
                "--broker", broker.url, "--vehicles", "3", "--ready-timeout", "60",
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            try:
                with pytest.raises(LinkConflict) as err:
                    async with asyncio.timeout(120):  # (refused within seconds)
                        await agent.run()
                _, errb = await asyncio.wait_for(coordinator.communicate(), 60)
            finally:
                if coordinator.returncode is None:
                    coordinator.kill()
                    await coordinator.wait()
            armed = [any(a for _, _, a in v.mode_log) for v in fleet.vehicles]
    msg = str(err.value)
    print(f"\nagent: {msg}")
    assert "its port hears 3 vehicles, systems 1, 2 and 3" in msg, msg
    assert "speaks from" not in msg  # its own vehicle's GCS link goes elsewhere, as PX4's
    assert armed == [False, False, False]
    text = errb.decode()
    assert coordinator.returncode == 2 and "refused" in text and "vehicle 2" in text, text
    assert "its port hears 3 vehicles" in text, text


# -- signing first --------------------------------------------------------------------------
async def test_with_a_key_the_unsigned_spoof_is_refused_by_signing_before_any_of_this(
        tmp_path: Path) -> None:
    """A vehicle holding the key (PX4 ≥ 1.18 after sign-setup) and a signing link: the
    spoofer's unsigned datagrams never reach the identity, source or plausibility rules; they
    are all signing's refusals, and the link's position stays the vehicle's."""
    from sim_stub import MockVehicle
    from sim_stub.ports import free_port_scheme
    from vtube_fleet.link import MavlinkLink
    from vtube_fleet.link.signing import LinkSigning, TimestampStore

    key = bytes(range(1, 33))
    ports = free_port_scheme(1)
    async with MockVehicle(0, ports=ports, signing=key, boot_time_scale=0.3) as v:
        link = MavlinkLink(ports.endpoint(0), sysid=v.sysid,
                           signing=LinkSigning(key, TimestampStore(tmp_path / "k.timestamp")))
        try:
            await link.connect(15.0)
            await link.wait_ready(20.0)
            target = SpoofTarget(v.gcs_address, v.sysid, lambda t: (20.0, 0.5, -5.0, 3, 0, 0))
            spoofer = Spoofer([target], duration_s=2.0)
            with spoofer:
                await asyncio.get_running_loop().run_in_executor(None, spoofer.done.wait, 10)
            # the vehicle's own (signed) stream goes on: its next positions come after the fakes
            fakes = spoofer.sent
            await link.wait_until(lambda s: link.signing_refused["unsigned"] >= fakes, 5.0,
                                  "every fake refused by signing")
            north, east, _ = v.position_ned
            st = link.state
        finally:
            await link.close()
    assert fakes > 150 and link.signing_refused["unsigned"] == fakes
    assert not st.telemetry_refused and st.telemetry_fault is None
    assert abs(st.north_m - north) < 1.0 and abs(st.east_m - east) < 1.0
