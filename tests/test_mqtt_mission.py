"""The coordinator (`vtube-fleet mission start|abort|status`) and the agent's join rules,
against a real broker, with scripted agents standing in for vehicles."""

from __future__ import annotations

import asyncio
import json
import re
import sys
import time
from pathlib import Path

import pytest
from broker import LocalBroker
from missions import COMPACT_12_PATH

from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.distributed.coordinator import default_mission_id
from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess, AgentRefused
from vtube_fleet.state import NeighbourState, Phase

ROOT = Path(__file__).resolve().parents[1]
MISSION = COMPACT_12_PATH  # scripted states: no budget involved (tests/missions.py)


@pytest.fixture
def broker():
    with LocalBroker() as b:
        yield b


class ScriptedAgent:
    """Speaks the agent's side of the protocol and 'flies' straight along the tube at
    ``speed`` (no vehicle): READY at its slot, on start IN_TUBE, EXITED past x = 19, LANDED."""

    def __init__(
        self,
        url: str,
        mission_id: str,
        vid: int,
        slot,
        *,
        speed: float = 6.0,
        hash_: str | None = None,
    ) -> None:
        self.bus = MqttBus(url, mission_id, vid,
                           config_hash=hash_ or load_mission(MISSION).config_hash)
        self.vid = vid
        self.x, self.y = float(slot[0]), float(slot[1])
        self.speed = speed
        self.seq = 0

    def state(self, phase: Phase, vx: float = 0.0) -> None:
        self.seq += 1
        self.bus.publish(
            NeighbourState(self.vid, self.x, self.y, vx, 0.0, phase, time.time(), self.seq)
        )

    async def run(self) -> None:
        bus = self.bus
        async with bus:
            await bus.wait_for(lambda: bus.config is not None, 30)
            bus.run_id = bus.config.run_id
            bus.announce("online", stage="joined")
            while not (bus.command and bus.command.run_id == bus.run_id):
                self.state(Phase.READY)
                await asyncio.sleep(0.05)  # this scripted vehicle's 20 Hz
            if bus.command.command == "abort":
                return
            t0 = time.monotonic()
            x0 = self.x
            while self.x <= 19.0:
                if bus.command.command == "abort":
                    self.state(Phase.LANDED)
                    return
                self.x = x0 + self.speed * (time.monotonic() - t0)
                self.state(Phase.IN_TUBE, self.speed)
                await asyncio.sleep(0.05)
            for phase in (Phase.EXITED, Phase.LANDING, Phase.LANDED):
                for _ in range(3):
                    self.state(phase)
                    await asyncio.sleep(0.05)


async def run_cli(*args: str, timeout: float = 60) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "vtube_fleet",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        cwd=ROOT,
    )
    out, err = await asyncio.wait_for(proc.communicate(), timeout)
    return proc.returncode, out.decode(), err.decode()


async def test_start_wait_writes_the_summary_from_the_agents_states(broker, tmp_path):
    mission = load_mission(MISSION)
    mid = default_mission_id(MISSION)
    agents = [ScriptedAgent(broker.url, mid, v, mission.slots[v]) for v in range(3)]
    tasks = [asyncio.create_task(a.run()) for a in agents]
    code, _, err = await run_cli(
        "mission",
        "start",
        str(MISSION),
        "--broker",
        broker.url,
        "--vehicles",
        "3",
        "--wait",
        "--out",
        str(tmp_path),
        "--ready-timeout",
        "30",
        "--timeout",
        "60",
    )
    await asyncio.gather(*tasks)
    assert code == 0, err
    assert "start published" in err and "completed: 3/3 exited" in err
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["kind"] == "mqtt" and s["outcome"] == "completed"
    assert s["robots"] == 3 and s["exited"] == 3 and s["violations"] == 0
    # Parallel straight lines 2.5 m apart; the pole at (12, 0) passed 1.25 m off centre.
    # Issue 31: the in-tube pair distance was null (pairs searched within the physical
    # r_s + r_a = 1.3 m only); it is searched as `run` searches it, within the flown
    # r_s' + r_a' + 1 m, and printed
    assert s["min_pair_distance_airborne_m"] == pytest.approx(2.5, abs=1e-3)
    assert s["r_s_flown"] + s["r_a_flown"] + 1.0 > 2.6
    assert s["min_pair_distance_airborne_m"] - 1e-9 <= s["min_pair_distance_m"] <= 2.55
    assert re.search(r"completed: 3/3 exited; min pair distance 2\.5\d m \(2 r_s = 0\.60 m\)",
                     err), err
    assert 1.25 - 1e-3 <= s["min_obstacle_center_distance_m"] <= 1.25 + 0.1
    assert s["max_measured_speed_m_s"] == pytest.approx(6.0)
    assert s["state_age_p99_s"] is not None and s["state_age_p99_s"] >= 0
    assert s["lost"] == [] and len(s["vehicle_states"]) == 3
    assert all(v["phase"] == "landed" for v in s["vehicle_states"])
    assert s["config_hash"] == load_mission(MISSION).config_hash
    # the fleet as the agents reported it is also a rerun recording that `review` reads back
    code, out, err = await run_cli("review", str(tmp_path / "recording.rrd"), "--json")
    assert code == 0, err
    r = json.loads(out)
    assert (r["robots"], r["exited"], r["violations"], r["steps"]) == (3, 3, 0, s["steps"])
    assert r["min_pair_distance_m"] == pytest.approx(s["min_pair_distance_m"], abs=1e-9)
    assert r["min_obstacle_center_distance_m"] == pytest.approx(
        s["min_obstacle_center_distance_m"]
    )
    # ... and holds the whole fleet on one map (WGS84): every vehicle, the outline, the fence
    from rerun.chunk import RrdReader

    rd = RrdReader(tmp_path / "recording.rrd")
    geo: dict[str, int] = {}
    for ch in rd.stream(store=rd.recordings()[0]).to_chunks():
        rb = ch.to_record_batch()
        for name in ("GeoPoints:positions", "GeoLineStrings:line_strings"):
            if name in rb.schema.names:
                path = str(ch.entity_path).lstrip("/")
                geo[path] = geo.get(path, 0) + sum(1 for v in rb.column(name).to_pylist() if v)
    assert all(geo.get(f"world/vehicles/{v}", 0) > 10 for v in range(3)), geo
    assert geo.get("map/tube") and geo.get("map/fence") and geo.get("map/slots")


async def test_an_agent_with_another_mission_file_refuses_and_start_fails(broker, tmp_path):
    other = tmp_path / "compact_12.toml"  # same name → same mission id, different content
    other.write_text(MISSION.read_text().replace("v = 1.0 ", "v = 1.1 "))
    assert load_mission(other).config_hash != load_mission(MISSION).config_hash
    proc = AgentProcess(other, 1, broker=broker.url, join_timeout_s=30)
    coordinator = asyncio.create_task(
        run_cli(
            "mission",
            "start",
            str(MISSION),
            "--broker",
            broker.url,
            "--vehicles",
            "2",
            "--ready-timeout",
            "30",
        )
    )
    async with proc.bus:
        with pytest.raises(AgentRefused, match="config hash .* the mission files differ"):
            await proc.join()
    code, _, err = await coordinator
    assert code == 2
    assert "error: 1 agent(s) refused run" in err and "vehicle 1:" in err
    assert err.strip().count("\n") < 5  # a clear error, no traceback


async def test_late_agent_refuses_a_started_run(broker):
    mission = load_mission(MISSION)
    mid = default_mission_id(MISSION)
    agents = [ScriptedAgent(broker.url, mid, v, mission.slots[v], speed=2.0) for v in range(2)]
    tasks = [asyncio.create_task(a.run()) for a in agents]
    code, _, err = await run_cli(
        "mission",
        "start",
        str(MISSION),
        "--broker",
        broker.url,
        "--vehicles",
        "2",
        "--ready-timeout",
        "30",
    )
    assert code == 0, err
    late = AgentProcess(MISSION, 1, broker=broker.url, join_timeout_s=10)
    async with late.bus:
        with pytest.raises(AgentRefused, match="already started .* does not join a fleet"):
            await late.join()
    outside = AgentProcess(MISSION, 5, broker=broker.url, join_timeout_s=10)
    async with outside.bus:
        with pytest.raises(AgentRefused, match="flies vehicles 0..1, not 5"):
            await outside.join()
    # status shows the run, the command and the vehicles' live states
    code, out, err = await run_cli(
        "mission", "status", str(MISSION), "--broker", broker.url, "--json"
    )
    assert code == 0, err
    info = json.loads(out)
    assert info["run"]["hash_matches"] and info["command"]["command"] == "start"
    phases = {v["id"]: v["phase"] for v in info["vehicles"]}
    assert phases[0] in ("in_tube", "exited", "landing", "landed")
    # abort goes to the announced run
    code, _, err = await run_cli("mission", "abort", str(MISSION), "--broker", broker.url)
    assert code == 0 and "abort published" in err
    async with MqttBus(broker.url, mid) as obs:
        await obs.sync()
        assert obs.command.command == "abort"
        assert obs.command.run_id == obs.config.run_id
    await asyncio.gather(*tasks)


async def test_abort_without_a_run_is_a_clear_error(broker):
    code, _, err = await run_cli("mission", "abort", str(MISSION), "--broker", broker.url)
    assert code == 2 and "error: no run of mission compact_12 announced" in err


async def test_unreachable_broker_is_a_clear_error():
    from broker import free_port

    code, _, err = await run_cli(
        "mission",
        "status",
        str(MISSION),
        "--broker",
        f"mqtt://127.0.0.1:{free_port()}",
        "--broker-timeout",
        "1",
    )
    assert code == 2 and "error: cannot reach the MQTT broker" in err and "within 1 s" in err
