"""A SIGKILLed coordinator (`mission start --wait`) still leaves its summary (issue 12): while it
follows a run, summary.json is rewritten atomically every few seconds with ``complete: false``,
as `run` does. Real broker, the real CLI in a subprocess, scripted agents that stay in the tube
(the run never ends by itself)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
import time
from pathlib import Path

import pytest
from broker import LocalBroker
from missions import COMPACT_12_PATH

from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.distributed.coordinator import default_mission_id
from vtube_fleet.state import NeighbourState, Phase

ROOT = Path(__file__).resolve().parents[1]
MISSION = COMPACT_12_PATH


class HoveringAgent:
    """The agent's side of the protocol, no vehicle: READY at its slot, IN_TUBE (not moving)
    once started, until ``stop`` is set."""

    def __init__(self, url: str, mission_id: str, vid: int, slot: object) -> None:
        self.bus = MqttBus(url, mission_id, vid, config_hash=load_mission(MISSION).config_hash)
        self.vid = vid
        self.x, self.y = float(slot[0]), float(slot[1])  # type: ignore[index]
        self.seq = 0

    def state(self, phase: Phase) -> None:
        self.seq += 1
        self.bus.publish(NeighbourState(self.vid, self.x, self.y, 0.0, 0.0, phase, time.time(),
                                        self.seq))

    async def run(self, stop: asyncio.Event) -> None:
        bus = self.bus
        async with bus:
            await bus.wait_for(lambda: bus.config is not None, 30)
            bus.run_id = bus.config.run_id
            bus.announce("online", stage="joined")
            while not stop.is_set():
                started = bus.command is not None and bus.command.run_id == bus.run_id
                self.state(Phase.IN_TUBE if started else Phase.READY)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 0.05)  # this scripted vehicle's 20 Hz


async def _summary_where(path: Path, cond: object, timeout_s: float) -> dict:
    """The first readable summary.json satisfying ``cond`` (the file is replaced atomically, so
    every read sees a whole one)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            s = json.loads(path.read_text())
            if cond(s):  # type: ignore[operator]
                return s
        await asyncio.sleep(0.1)
    pytest.fail(f"no summary.json satisfying the condition within {timeout_s} s")


async def test_sigkilled_coordinator_leaves_an_interim_summary(tmp_path: Path) -> None:
    mission = load_mission(MISSION)
    mid = default_mission_id(MISSION)
    with LocalBroker() as broker:
        stop = asyncio.Event()
        agents = [HoveringAgent(broker.url, mid, v, mission.slots[v]) for v in range(2)]
        tasks = [asyncio.create_task(a.run(stop)) for a in agents]
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "vtube_fleet", "mission", "start", str(MISSION),
            "--broker", broker.url, "--vehicles", "2", "--wait", "--out", str(tmp_path),
            "--ready-timeout", "30", "--timeout", "120", "--no-rerun",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, cwd=ROOT)
        try:
            path = tmp_path / "summary.json"
            first = await _summary_where(path, lambda s: True, 60)
            assert first["complete"] is False and first["outcome"] == "running"
            # rewritten while following: a later one has seen more states
            later = await _summary_where(
                path, lambda s: s["states_received"] > first["states_received"], 30)
            assert proc.returncode is None, "the coordinator ended by itself"
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            stop.set()
            await asyncio.gather(*tasks, return_exceptions=True)
    assert proc.returncode == -signal.SIGKILL
    s = json.loads(path.read_text())  # what the killed coordinator left
    assert s["complete"] is False and s["outcome"] == "running"
    assert s["states_received"] >= later["states_received"]
    assert "still following the run" in s["reason"] and "without writing its own" in s["reason"]
    assert s["kind"] == "mqtt" and s["vehicles"] == 2 and s["run_id"]
    assert not list(tmp_path.glob("*.tmp"))
