"""Fault tests of the fleet against sim_stub vehicles running in ANOTHER process
(``vtube-fleet mock-fleet``), so that freezing the supervisor's event loop does not freeze the
vehicles:

* the supervisor's control loop is frozen (the fault injected: a tick that does not return
  until the vehicles' reaction shows in their telemetry, or 15 s) → with the ``mavlink`` backend
  the vehicles' own offboard-loss failsafe fires (PX4: COM_OF_LOSS_T = 1 s, "Failsafe
  activated", POSCTL); with ``mavsdk`` (which resends setpoints by itself) the link's watchdog
  thread stops offboard and the vehicles hold; afterwards the supervisor marks them LOST;
* SIGINT to a ``vtube-fleet run`` process in the tube → every vehicle holds, then lands; the
  summary is complete; exit code 130.

Everything is asserted from the vehicles' telemetry (flight modes, status texts, landed state).
"""

from __future__ import annotations

import asyncio
import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from missions import straight_mission
from mock_process import child_env, mock_process, read_line, start_run

from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import fly
from vtube_fleet.fleet.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

MISSION = straight_mission(30.0, [[2.0, 4.5], [2.0, -4.5]], heading_deg=90.0,
                           extra="land_timeout_s = 40.0\n")


def freeze_in_tube(after_s: float, until, log: dict, limit_s: float = 15.0):
    """A tick hook that stalls the control loop once, ``after_s`` into the tube, until
    ``until(supervisor)`` holds (the vehicles' reaction, seen in their telemetry) or
    ``limit_s``; the event loop keeps running, so telemetry is still received meanwhile."""

    async def stall(sup: Supervisor) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            async with asyncio.timeout(limit_s):
                while not until(sup):
                    # wake on any telemetry update of any vehicle
                    tasks = [asyncio.ensure_future(_next_state(p.link)) for p in sup.pilots]
                    try:
                        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        for t in tasks:
                            t.cancel()
        except TimeoutError:
            log["stall_timeout"] = True
        log["stalled_s"] = loop.time() - t0
        log["modes_during"] = [p.link.state.flight_mode for p in sup.pilots]
        log["landed_during"] = [p.link.state.landed_state for p in sup.pilots]

    def hook(tick: int, sup: Supervisor):
        log.setdefault("sup", sup)
        if sup.tube_start_s is None or "frozen" in log:
            return None
        if sup.t_s() - sup.tube_start_s >= after_s:
            log["frozen"] = True
            log["modes_before"] = [p.link.state.flight_mode for p in sup.pilots]
            return stall(sup)  # THE FAULT: the control loop stops sending setpoints
        return None

    return hook


async def _next_state(link) -> None:
    async for _ in link.states():
        return


async def test_frozen_loop_mavlink_px4_failsafe_fires(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    mission = load_mission(path)
    log: dict = {}

    def failsafe_reported(sup: Supervisor) -> bool:
        return all(p.link.state.flight_mode == "POSCTL" for p in sup.pilots)

    with mock_process(path, 2) as (_mock, endpoints):
        result = await fly(mission, backend="mavlink", endpoints=endpoints, sysids=[1, 2],
                           out_dir=tmp_path, tick_hook=freeze_in_tube(1.0, failsafe_reported,
                                                                       log))
    sup: Supervisor = log["sup"]
    assert log.get("frozen"), f"never froze: {result.outcome} {result.reason}"
    assert not log.get("stall_timeout"), log
    assert log["modes_before"] == ["OFFBOARD", "OFFBOARD"]
    assert log["modes_during"] == ["POSCTL", "POSCTL"]  # PX4's offboard-loss failsafe mode
    for p in sup.pilots:
        texts = [t.text for t in p.link.state.statustexts]
        assert any("Failsafe activated" in t for t in texts), texts  # as PX4 reports it (1c)
        assert p.phase.value == "lost"
        assert "left OFFBOARD unexpectedly (mode POSCTL" in (p.reason or "")
    assert result.outcome == "incomplete" and result.exit_code == 3
    print(f"\nfrozen loop (mavlink): failsafe after {log['stalled_s']:.2f} s without setpoints; "
          f"modes {log['modes_during']}; reasons {[p.reason for p in sup.pilots]}")


async def test_frozen_loop_mavsdk_watchdog_holds(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    mission = load_mission(path)
    log: dict = {}

    def holding(sup: Supervisor) -> bool:
        return all(p.link.watchdog_trips >= 1 and p.link.state.flight_mode == "HOLD"
                   for p in sup.pilots)

    with mock_process(path, 2) as (_mock, endpoints):
        result = await fly(mission, backend="mavsdk", endpoints=endpoints, sysids=[1, 2],
                           out_dir=tmp_path, tick_hook=freeze_in_tube(1.0, holding, log))
    sup: Supervisor = log["sup"]
    assert log.get("frozen"), f"never froze: {result.outcome} {result.reason}"
    assert not log.get("stall_timeout"), log
    assert log["modes_during"] == ["HOLD", "HOLD"]
    assert log["landed_during"] == ["IN_AIR", "IN_AIR"]  # held in the air
    for p in sup.pilots:
        assert p.link.watchdog_trips >= 1
        assert p.phase.value == "lost"
        assert "left OFFBOARD unexpectedly (mode HOLD" in (p.reason or "")
    assert result.exit_code == 3
    print(f"\nfrozen loop (mavsdk): watchdog held after {log['stalled_s']:.2f} s; trips "
          f"{[p.link.watchdog_trips for p in sup.pilots]}; modes {log['modes_during']}")


def test_sigint_lands_everyone_and_leaves_a_complete_summary(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text(MISSION.replace("[[2.0, 4.5], [2.0, -4.5]]",
                                    "[[2.0, 4.5], [2.0, 0.0], [2.0, -4.5]]"))
    out = tmp_path / "run"
    with mock_process(path, 3) as (_mock, endpoints):
        proc = start_run(path, endpoints, out)
        try:
            read_line(proc, "stderr", lambda s: "stage: tube" in s, 90)
            # the status line (every 5 s when stderr is not a terminal) shows them in the tube
            read_line(proc, "stderr", lambda s: ": 3 in tube" in s, 30)
            proc.send_signal(signal.SIGINT)
            tail = proc.stderr.read() if proc.stderr else ""
            rc = proc.wait(timeout=90)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert rc == 130, tail[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcome"] == "interrupted"
    assert [v["phase"] for v in summary["vehicle_states"]] == ["landed"] * 3
    for key in ("ticks", "achieved_rate_hz", "tick_duration_p99_s", "safety_budget",
                "min_pair_distance_m", "min_speed_m_s", "max_speed_m_s",
                "min_measured_speed_m_s", "max_measured_speed_m_s", "link_latency_p50_s"):
        assert summary.get(key) is not None, key
    assert summary["ticks"] > 0 and summary["tube_start_s"] is not None
    assert any("SIGINT" in e["text"] for e in summary["events"])
    assert "interrupted" in tail
    rec = out / "recording.rrd"
    assert rec.is_file() and rec.stat().st_size > 0
    from vtube_fleet.recording.reader import load_recording

    data = load_recording(rec)
    assert len(data.t_s) > 0
    # the recording runs to the end: its last tick is within a second of the summary's end
    assert float(data.t_s[-1]) >= summary["wall_s"] - 1.0
    print(f"\nSIGINT: rc {rc}; phases {[v['phase'] for v in summary['vehicle_states']]}; "
          f"recorded ticks {len(data.t_s)}, summary ticks {summary['ticks']}")


def _read_pty_until(master: int, proc: subprocess.Popen[bytes], text: bytes,
                    timeout_s: float) -> bytes:
    """Read the terminal's output (the pty's master side) until ``text`` appears."""
    seen = b""
    deadline = time.monotonic() + timeout_s
    while text not in seen:
        assert time.monotonic() < deadline and proc.poll() is None, seen[-2000:]
        ready, _, _ = select.select([master], [], [], 1.0)
        if ready:
            seen += os.read(master, 65536)
    return seen


def test_a_closed_terminal_lands_everyone_like_ctrl_c(tmp_path: Path) -> None:
    """The operator's terminal (an SSH session) goes away mid-tube: SIGHUP, and writes to the
    terminal (the live table, the log lines) fail from then on. By default Python would end on
    the spot and leave the vehicles in OFFBOARD to PX4's failsafe; the run brings them down as
    for Ctrl-C and keeps its summary."""
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    out = tmp_path / "run"
    master, slave = pty.openpty()
    with mock_process(path, 2) as (_mock, endpoints):
        proc = subprocess.Popen(
            [sys.executable, "-m", "vtube_fleet", "run", str(path), "--endpoints",
             ",".join(endpoints), "--out", str(out)],
            stdin=slave, stdout=slave, stderr=slave, env=child_env(), cwd=ROOT,
            # SIGHUP as an operator's shell leaves it, also when the suite itself runs under
            # nohup (ignored SIGHUP is inherited, and run rightly flies on then)
            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
        os.close(slave)
        try:
            _read_pty_until(master, proc, b"stage: tube", 90)
            os.close(master)  # the terminal is gone: writes to it fail (EIO)
            master = -1
            proc.send_signal(signal.SIGHUP)
            rc = proc.wait(timeout=90)
        finally:
            if master >= 0:
                os.close(master)
            if proc.poll() is None:
                proc.kill()
    summary = json.loads((out / "summary.json").read_text())
    assert rc == 130, (rc, summary.get("outcome"), summary.get("reason"))
    assert summary["outcome"] == "interrupted"
    assert [v["phase"] for v in summary["vehicle_states"]] == ["landed"] * 2
    assert any("SIGHUP" in e["text"] for e in summary["events"])


def _aborted_and_all_down(result, sup: Supervisor, why: str) -> None:
    """The run aborted (exit 3) naming ``why``, and every vehicle landed and disarmed."""
    assert result.outcome == "aborted" and result.exit_code == 3, result.reason
    assert why in result.reason
    assert [p.phase.value for p in sup.pilots] == ["landed", "landed"]
    assert [p.link.state.armed for p in sup.pilots] == [False, False]


async def test_a_bug_of_ours_in_flight_still_lands_everyone(tmp_path: Path) -> None:
    """An exception nobody expected (here from the tick hook, outside the guarded tick) one
    second into the tube: the run does not end with the vehicles in OFFBOARD; it aborts, every
    vehicle lands, and the reason names the error."""
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    mission = load_mission(path)
    log: dict = {}

    def hook(tick: int, sup: Supervisor) -> None:
        log.setdefault("sup", sup)
        if sup.tube_start_s is not None and sup.t_s() - sup.tube_start_s >= 1.0:
            log["raised"] = True
            raise RuntimeError("injected bug")

    with mock_process(path, 2) as (_mock, endpoints):
        result = await fly(mission, endpoints=endpoints, sysids=[1, 2], out_dir=tmp_path,
                           tick_hook=hook)
    assert log.get("raised")
    _aborted_and_all_down(result, log["sup"], "RuntimeError: injected bug")


async def test_a_control_clock_that_dies_in_flight_still_lands_everyone(tmp_path: Path) -> None:
    """The clock itself ends with an exception (here its stall callback raises after a stall
    one second into the tube): the mission aborts, the clock runs again to see the vehicles
    down, and every vehicle lands."""
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    mission = load_mission(path)
    log: dict = {}

    def broken_on_stall(gap_s: float) -> None:
        log["raised"] = True
        raise RuntimeError("injected bug in the clock")

    def hook(tick: int, sup: Supervisor):
        log.setdefault("sup", sup)
        if sup.tube_start_s is None or "stalled" in log:
            return None
        if sup.t_s() - sup.tube_start_s >= 1.0:
            log["stalled"] = True
            sup.clock.on_stall = broken_on_stall
            return asyncio.sleep(0.5)  # a stall of our own loop: the callback runs next tick
        return None

    with mock_process(path, 2) as (_mock, endpoints):
        result = await fly(mission, endpoints=endpoints, sysids=[1, 2], out_dir=tmp_path,
                           tick_hook=hook)
    assert log.get("raised")
    _aborted_and_all_down(result, log["sup"],
                          "the control loop ended: RuntimeError: injected bug in the clock")


async def test_a_bug_of_ours_after_the_tube_still_lands_everyone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception nobody expected in the procedure itself (here the finish after the tube,
    the vehicles still in the air): the run aborts and brings every vehicle down instead of
    ending with them airborne."""
    path = tmp_path / "m.toml"
    path.write_text(MISSION)
    mission = load_mission(path)
    log: dict = {}

    async def broken_finish(self: Supervisor, how: str) -> None:
        log["sup"] = self
        raise RuntimeError("injected bug in the finish")

    monkeypatch.setattr(Supervisor, "_finish", broken_finish)
    with mock_process(path, 2) as (_mock, endpoints):
        result = await fly(mission, endpoints=endpoints, sysids=[1, 2], out_dir=tmp_path)
    _aborted_and_all_down(result, log["sup"],
                          "internal error: RuntimeError: injected bug in the finish")
