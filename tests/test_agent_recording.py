"""The agent's recording (fleet/distributed/agent.AgentRecording): a failure of the safety
evaluation is not swallowed with the recording's problems (issue #10)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
from missions import compact_12

from vtube_fleet.fleet.distributed.agent import AgentRecording, BusAwarePilot
from vtube_fleet.recording.api import NullRecorder
from vtube_fleet.state import Phase


def _pilot():
    return SimpleNamespace(last_state=None, mqtt=SimpleNamespace(latest=dict), cmd_xy=None,
                           cmd_in_tube=False, phase=Phase.IN_TUBE, reason="", bus_holds=0)


@pytest.fixture()
def rec():
    mission = compact_12()
    return AgentRecording(mission, 3, 0, NullRecorder(), t0_s=0.0)


def test_a_failing_safety_evaluation_propagates_and_marks_the_summary(rec, tmp_path,
                                                                     monkeypatch) -> None:
    rec.sample(_pilot(), 1.0)  # a working sample: nothing noted
    assert rec.failure is None

    def broken(*_a, **_k):
        raise ValueError("bad geometry")

    monkeypatch.setattr(rec.monitor, "sample", broken)
    for _ in range(2):
        with pytest.raises(ValueError):
            rec.sample(_pilot(), 2.0)
    assert rec.failure == "safety monitor failed: ValueError: bad geometry"
    summary = json.loads(rec.finish(tmp_path, _pilot(), outcome="completed").read_text())
    assert summary["outcome"] == "aborted"
    assert summary["reason"] == rec.failure


def test_the_pilot_aborts_its_tube_run_when_the_evaluation_fails() -> None:
    calls: list[str] = []
    recording = SimpleNamespace(failure="safety monitor failed: X: y")

    def sample(_pilot, _now):
        raise RuntimeError("y")

    recording.sample = sample
    fake = SimpleNamespace(_tick=lambda *_: None, recording=recording,
                           _abort_for=calls.append)
    BusAwarePilot.tick(fake, 0.0, 0.0)  # type: ignore[arg-type]
    assert calls == ["safety monitor failed: X: y"]

    events: list[tuple[str, str]] = []
    holds: list[str] = []
    pilot = SimpleNamespace(_aborted=False, reason="", phase=Phase.IN_TUBE,
                            event=lambda text, level="info": events.append((text, level)),
                            begin_hold=holds.append)
    pilot.stop_for = lambda why: BusAwarePilot.stop_for(pilot, why)  # type: ignore[arg-type]
    for _ in range(3):
        BusAwarePilot._abort_for(pilot, "safety monitor failed: X: y")  # type: ignore[arg-type]
    assert events == [("ABORT: safety monitor failed: X: y", "error")]
    assert pilot.reason == "safety monitor failed: X: y"
    assert holds == ["mission aborted"] * 3


def test_the_teammate_wait_returns_who_is_missing() -> None:
    """The altitude and exit barriers' one wait (AgentProcess._wait_teammates)."""
    import asyncio

    from vtube_fleet.fleet.distributed.agent import AgentProcess

    def status(stage, run="r1"):
        return SimpleNamespace(run_id=run, stage=stage)

    async def wait_for(pred, timeout_s):
        if not pred():
            raise TimeoutError

    bus = SimpleNamespace(run_id="r1", wait_for=wait_for, statuses={
        1: status("at_altitude"), 2: status("exited"), 3: status("exited", run="old"),
        4: status("ready")})
    fake = SimpleNamespace(bus=bus, vehicle=0, _teammates=lambda: range(6),
                           _gone=lambda v: v == 4)  # 4 gone, 5 never heard
    up = ("at_altitude", "in_tube", "exited", "done")
    assert asyncio.run(AgentProcess._wait_teammates(fake, up, 1.0)) == [3, 5]
    assert asyncio.run(AgentProcess._wait_teammates(fake, ("exited", "done"), 1.0)) == [1, 3, 5]
    fake._teammates = lambda: range(3)
    assert asyncio.run(AgentProcess._wait_teammates(fake, up, 1.0)) == []
