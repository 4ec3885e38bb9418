"""The agent's recording (fleet/distributed/vehicle_agent.AgentRecording): a failure of the safety
evaluation is not swallowed with the recording's problems (issue #10); the interim summary
(``complete: false``, every ``SUMMARY_EVERY_S`` during the flight) and the final one
(``complete: true``) (issue #12)."""

from __future__ import annotations

import itertools
import json
import math
from types import SimpleNamespace

import pytest
from missions import compact_12

from vtube_fleet.fleet.distributed.vehicle_agent import AgentControl, AgentRecording
from vtube_fleet.recording.api import NullRecorder
from vtube_fleet.state import Phase


def _pilot():
    return SimpleNamespace(last_state=None, mqtt=SimpleNamespace(latest=dict), cmd_xy=None,
                           cmd_in_tube=False, phase=Phase.IN_TUBE, reason="", bus_holds=0,
                           tick_gaps_s=[], watch=None, response=None)


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


def test_the_agent_aborts_its_tube_run_when_the_evaluation_fails() -> None:
    calls: list[str] = []
    recording = SimpleNamespace(failure="safety monitor failed: X: y")

    def sample(_control, _now):
        raise RuntimeError("y")

    recording.sample = sample
    recording.after_tick = lambda _control, mono, wall: calls.append(f"after_tick {mono:g}")

    def tick(*_a):
        raise RuntimeError("the tick itself")

    fake = SimpleNamespace(tick=tick, recording=recording, abort_for=calls.append)
    try:
        AgentControl.step(fake, 0.0, 0.0, None)  # type: ignore[arg-type]
    except RuntimeError:
        pass  # the clock's guard takes a failed tick
    assert calls == ["safety monitor failed: X: y", "after_tick 0"]  # the checkpoint too

    events: list[tuple[str, str]] = []
    holds: list[str] = []
    pilot = SimpleNamespace(reason="", phase=Phase.IN_TUBE,
                            event=lambda text, level="info": events.append((text, level)),
                            begin_hold=holds.append)
    control = SimpleNamespace(_aborted=False, pilot=pilot)
    control.stop_for = lambda why: AgentControl.stop_for(control, why)  # type: ignore
    for _ in range(3):
        AgentControl.abort_for(control, "safety monitor failed: X: y")  # type: ignore[arg-type]
    assert events == [("ABORT: safety monitor failed: X: y", "error")]
    assert pilot.reason == "safety monitor failed: X: y"
    assert holds == ["mission aborted"] * 3


def test_the_teammate_wait_returns_who_is_missing() -> None:
    """The altitude and exit barriers' one wait (AgentProcess._wait_teammates)."""
    import asyncio

    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess

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


def test_the_interim_summary_is_rewritten_during_the_flight_and_the_final_is_complete(
        tmp_path) -> None:
    """Issue #12: a SIGKILLed agent leaves its last summary. After a tick (``after_tick``, as
    :meth:`AgentControl.step` calls it) the summary is written at once, then again only once
    ``SUMMARY_EVERY_S`` passed, atomically, ``complete: false``; ``finish`` writes
    ``complete: true``."""
    from vtube_fleet.artifacts import SUMMARY_EVERY_S
    from vtube_fleet.state import NeighbourState

    meta = {"mission_id": "m", "run_id": "r1", "config_hash": "h", "broker": "mqtt://b"}
    # each write takes 5 ms of the work clock: the pacer does not stretch (a real clock would
    # on a loaded machine: a write > 20 ms postpones the next beyond SUMMARY_EVERY_S)
    work = itertools.count(0.0, 0.005)
    rec = AgentRecording(compact_12(), 3, 0, NullRecorder(), t0_s=100.0, out=tmp_path,
                         meta=meta, work_clock=lambda: next(work))
    path = tmp_path / "summary.json"
    pilot = _pilot()

    def hear(k: int) -> None:
        for v in (1, 2):
            rec.on_neighbour(NeighbourState(v, 5.0, 2.5 * v, 1.0, 0.0, Phase.IN_TUBE,
                                            100.0 + 0.05 * k - 0.02, k), 100.0 + 0.05 * k)

    hear(0)
    rec.sample(pilot, 100.0)
    rec.after_tick(pilot, 50.0, 100.0)  # the first tick: written at once
    first = json.loads(path.read_text())
    assert first["complete"] is False and first["outcome"] == "running"
    assert "still flying (phase in_tube, 0.0 s after start)" in first["reason"]
    assert "without writing its own" in first["reason"]
    assert first["kind"] == "agent" and first["vehicle"] == 0 and first["run_id"] == "r1"
    assert first["states_received"] == 2 and first["wall_s"] == 0.0
    assert first["tick_gap_max_s"] is None  # no second tick yet
    pilot.tick_gaps_s.extend([0.05] * 98 + [0.06, 0.4])  # one stall of 400 ms
    for k in range(1, 10):  # not due yet: not rewritten
        hear(k)
        rec.sample(pilot, 100.0 + 0.05 * k)
        rec.after_tick(pilot, 50.0 + 0.05 * k, 100.0 + 0.05 * k)
    assert json.loads(path.read_text()) == first
    rec.after_tick(pilot, 50.0 + SUMMARY_EVERY_S + 0.01, 102.5)  # due: rewritten
    later = json.loads(path.read_text())
    assert later["complete"] is False and later["states_received"] == 20
    assert later["wall_s"] == 2.5 and later["steps"] == 10
    assert not list(tmp_path.glob("*.tmp"))
    final = json.loads(rec.finish(tmp_path, pilot, outcome="completed").read_text())
    assert final["complete"] is True and final["outcome"] == "completed"
    assert final["run_id"] == "r1" and final["states_received"] == 20
    assert final["tick_gap_max_s"] == 0.4 and 0.05 < final["tick_gap_p99_s"] < 0.4
    assert final["tick_gap_max_in_tube_s"] is None  # this fake pilot has no budget watch


def test_no_interim_summary_without_an_out_folder_and_a_bad_one_never_raises(
        tmp_path, caplog) -> None:
    rec = AgentRecording(compact_12(), 3, 0, NullRecorder(), t0_s=0.0)
    rec.after_tick(_pilot(), 0.0, 1.0)  # no out: nothing, no error
    blocker = tmp_path / "file"
    blocker.write_text("")
    rec = AgentRecording(compact_12(), 3, 0, NullRecorder(), t0_s=0.0, out=blocker / "sub")
    rec.after_tick(_pilot(), 0.0, 1.0)  # cannot write: a warning, the flight goes on
    assert "cannot write the interim summary.json" in caplog.text


async def test_a_bug_of_ours_in_the_agents_flight_still_lands_its_vehicle() -> None:
    """The agent's flight ends with an exception nobody expected (a bug, not a UserError): the
    vehicle is brought down (the same landing as an abort's) and the agent aborts, naming it."""
    import asyncio

    from vtube_fleet.fleet.distributed.vehicle_agent import AgentAborted, AgentProcess

    landed: list[str] = []

    async def fly(**_kw):
        raise RuntimeError("injected bug")

    async def land_now(_control, why: str) -> None:
        landed.append(why)

    fake = SimpleNamespace(
        vehicle=3, _abort=asyncio.Event(), _interrupt=asyncio.Event(),
        _altitude_barrier=None, _exit_barrier=None, _land_now=land_now)
    control = SimpleNamespace(pilot=SimpleNamespace(fly=fly))
    with pytest.raises(AgentAborted, match="vehicle 3: internal error: RuntimeError: injected"):
        await AgentProcess._fly_started(fake, control)  # type: ignore[arg-type]
    assert landed == ["internal error: RuntimeError: injected bug (a bug: the traceback is in "
                      "the log)"]


def test_the_summary_pacer_stretches_its_period_when_writing_is_slow() -> None:
    """Writing an interim summary takes at most ~1 % of the time: a 5 ms write keeps the
    period at ``SUMMARY_EVERY_S``; a 50 ms write postpones the next by 100 × 50 ms."""
    from vtube_fleet.artifacts import SUMMARY_EVERY_S, SummaryPacer

    pacer = SummaryPacer(-math.inf)
    assert pacer.due(0.0)
    pacer.written(10.0, 10.005)
    assert not pacer.due(10.005 + SUMMARY_EVERY_S - 0.001)
    assert pacer.due(10.005 + SUMMARY_EVERY_S + 0.001)
    pacer.written(20.0, 20.05)
    assert not pacer.due(20.05 + SUMMARY_EVERY_S + 2.9)
    assert pacer.due(20.05 + 5.001)
