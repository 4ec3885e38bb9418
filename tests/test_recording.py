"""The rerun recorder and the read-back: what goes in comes out, on every exit path."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vtube_fleet.cli._args import add_recording_args, recorder_from_args
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.errors import UserError
from vtube_fleet.recording.api import NullRecorder, Recorder, RecordingError
from vtube_fleet.recording.layout import DEFAULT_CONNECT_URL, E_VEHICLES
from vtube_fleet.recording.reader import load_recording
from vtube_fleet.recording.writer import (
    RerunRecorder,
    default_blueprint,
    normalize_connect_url,
    open_recorder,
)

REPO = Path(__file__).resolve().parents[1]


# A minimal stand-in with the attributes log_scene reads from a Scenario (duck-typed on purpose:
# the recorder must not need the simulator). The end-to-end tests in test_review.py use the real
# Scenario.
@dataclass(frozen=True)
class _Params:
    r_s: float = 0.25
    r_a: float = 0.5
    v_min: float = 0.5
    v_max: float = 3.5
    eps_0: float = 0.01


@dataclass(frozen=True)
class _Robots:
    count: int
    v_min: float = 0.5
    v_max: float = 3.5
    model: str = "single_integrator"
    nid_distance: float | None = None


@dataclass(frozen=True)
class _Sim:
    dt: float = 0.05
    duration: float = 5.0


@dataclass(frozen=True)
class _Scenario:
    tube: Trapezoid
    obstacles: tuple[Obstacle, ...]
    robots: _Robots
    controller: _Params
    sim: _Sim
    source: str = "test.toml"


def scenario(m: int = 5) -> _Scenario:
    tube = Trapezoid(np.array([0.0, 0.0]), np.array([30.0, 2.0]), np.array([0.0, 10.0]),
                     np.array([30.0, 8.0]), name="T")
    return _Scenario(tube, (Obstacle(np.array([15.0, 5.0]), 1.0),), _Robots(m), _Params(), _Sim())


def motion(k: int, m: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    pos = np.stack([np.full(m, 0.1 * k), 1.0 + 1.5 * np.arange(m)], axis=-1)
    pos = pos + rng.normal(scale=1e-3, size=pos.shape)  # full float64 precision matters
    vel = np.tile([2.0, 0.1], (m, 1)) + rng.normal(scale=1e-3, size=pos.shape)
    return pos, vel


def test_round_trip_is_exact_with_absent_rows(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    sent = []
    with open_recorder(path, kind="sim") as rec:
        assert isinstance(rec, RerunRecorder)
        rec.log_scene(scenario(), None, meta={"dt_s": 0.05})
        for k in range(40):
            pos, vel = motion(k)
            if k >= 30:
                pos[2] = np.nan  # robot 2 has left
            rec.log_tick(t_s=0.05 * k, tick=k, ids=np.arange(5), pos=pos, vel=vel,
                         metrics={"min_pair_distance_m": 1.5 - 0.01 * k})
            sent.append((pos, vel))
    d = load_recording(path)
    assert d.kind == "sim"
    assert d.meta["robots"] == 5 and d.meta["r_s"] == 0.25 and d.meta["dt_s"] == 0.05
    assert d.meta["tube"]["p_h1"] == [30.0, 2.0]
    assert d.meta["obstacles"] == [{"center": [15.0, 5.0], "radius": 1.0, "apex_distance": None}]
    np.testing.assert_array_equal(d.tick, np.arange(40))
    np.testing.assert_allclose(d.t_s, 0.05 * np.arange(40), atol=1e-9)
    np.testing.assert_array_equal(d.ids, np.arange(5))
    # float64 state is stored exactly (the Points2D positions are float32, for display only)
    np.testing.assert_array_equal(d.pos, np.stack([p for p, _ in sent]))
    vel_exp = np.stack([v for _, v in sent])
    vel_exp[30:, 2] = np.nan
    np.testing.assert_array_equal(d.vel, vel_exp)
    for ent in ("world/vehicles", "metrics/min_pair_distance_m"):
        assert d.entity_rows[ent] == 40, ent
    for ent in ("meta/scenario", "world/tube", "world/obstacles", "world/obstacles/extended"):
        assert d.static_rows[ent] >= 1, ent
    np.testing.assert_allclose(d.metrics["min_pair_distance_m"], 1.5 - 0.01 * np.arange(40))
    assert d.exits == {2: pytest.approx(1.5)}
    assert d.summary is None


def test_decimation_keeps_extrema_and_the_last_tick(tmp_path: Path) -> None:
    path = tmp_path / "dec.rrd"
    rec = open_recorder(path, decimate=3)
    rec.log_scene(scenario())
    for k in range(11):
        pos, vel = motion(k)
        rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(5), pos=pos, vel=vel,
                     metrics={"min_pair_distance_m": 10.0 - (k % 3), "max_speed_m_s": float(k),
                              "tick_duration_s": 0.001 * (k % 4)})
    rec.close()
    d = load_recording(path)
    # calls 0, 3, 6, 9 are recorded, and the last call (10) at close
    np.testing.assert_array_equal(d.tick, [0, 3, 6, 9, 10])
    assert d.entity_rows[E_VEHICLES] == 5
    assert d.meta["decimate"] == 3
    # each recorded tick carries the extreme of the calls since the previous recorded one
    np.testing.assert_allclose(d.metrics["min_pair_distance_m"], [10, 8, 8, 8, 9])
    np.testing.assert_allclose(d.metrics["max_speed_m_s"], [0, 3, 6, 9, 10])
    np.testing.assert_allclose(d.metrics["tick_duration_s"], [0, 0.003, 0.002, 0.003, 0.002])
    np.testing.assert_array_equal(d.pos[-1], motion(10)[0])


def test_fleet_ids_phases_commands_and_events(tmp_path: Path) -> None:
    path = tmp_path / "fleet.rrd"
    rec = open_recorder(path, kind="fleet")
    rec.log_scene(scenario(3), meta={"rate_hz": 20.0})
    phases_seen = []
    for k in range(12):
        ids = np.array([1, 2, 3]) if k < 4 else np.array([1, 2, 3, 7])  # vehicle 7 joins late
        m = len(ids)
        pos, vel = motion(k, m)
        cmd = vel * 1.01
        phases = ["in_tube"] * m
        if k >= 8:
            phases[1] = "exited"
            pos[1] = np.nan  # exited vehicles may keep reporting or not: phases decide
        phases_seen.append(phases)
        p_tube = pos.copy()
        p_tube[0] = np.nan  # vehicle 1 not counted by the safety metrics (e.g. still climbing)
        safety = {"": (p_tube, cmd)} if k % 2 == 0 else None
        rec.log_tick(t_s=0.05 * k, tick=100 + k, ids=ids, pos=pos, vel=vel, phases=phases,
                     cmd=cmd, metrics={"link_latency_s": 0.002, "tick_duration_s": 0.0004},
                     safety=safety)
    rec.log_event(0.3, "slow to answer", vehicle_id=3, level="warning")
    rec.log_event(0.4, "mission complete")
    rec.log_summary({"robots": 4, "exited": 1, "violations": 0})
    rec.close()
    d = load_recording(path)
    assert d.kind == "fleet" and d.meta["rate_hz"] == 20.0
    np.testing.assert_array_equal(d.ids, [0, 1, 2, 3, 7])  # scenario ids first, then new ones
    assert d.summary == {"robots": 4, "exited": 1, "violations": 0}
    col = {int(v): c for c, v in enumerate(d.ids)}
    assert np.isnan(d.pos[:4, col[7]]).all() and not np.isnan(d.pos[4:, col[7]]).any()
    assert d.phases is not None
    assert d.phases[9, col[2]] is None  # absent rows are not stored
    assert d.phases[9, col[1]] == "in_tube" and d.phases[0, col[3]] == "in_tube"
    assert d.cmd is not None
    np.testing.assert_array_equal(d.cmd[5, col[1]], motion(5, 4)[1][0] * 1.01)
    assert d.exits == {2: pytest.approx(0.4)}
    sp, sv = d.safety[""]
    assert np.isnan(sp[:, col[1]]).all() and np.isnan(sp[1::2]).all()  # odd ticks: not given
    np.testing.assert_array_equal(sp[6, col[2]], motion(6, 4)[0][1])
    np.testing.assert_array_equal(sv[6, col[7]], motion(6, 4)[1][3] * 1.01)
    assert d.entity_rows["safety/main"] == 6
    texts = [(e[1], e[2], e[3]) for e in d.events]
    assert ("events/vehicles", "WARN", "vehicle 3: slow to answer") in texts
    assert ("events", "INFO", "mission complete") in texts
    assert ("events/vehicles", "INFO", "vehicle 2: in_tube → exited") in texts
    assert ("events/vehicles", "INFO", "vehicle 7: in_tube") in texts
    assert d.entity_rows["world/commands"] == 12
    assert d.entity_rows["metrics/link_latency_s"] == 12


@pytest.mark.parametrize("detect", [True, False])
def test_exit_detection_can_be_left_to_the_owner(tmp_path: Path, detect: bool) -> None:
    """``detect_exits=False``: the recording's exits are exactly the explicit ones (the MQTT
    coordinator and agents decide exits from every state heard, also between ticks)."""
    rec = open_recorder(tmp_path / "x.rrd", kind="fleet", detect_exits=detect)
    rec.log_scene(scenario(3))
    for k in range(6):
        phases = ["in_tube", "exited" if k >= 2 else "in_tube", "exited" if k >= 4 else "in_tube"]
        if k == 3:
            rec.log_exits(0.12, 3, [2])  # its own time for vehicle 2, before the tick shows it
        pos, vel = motion(k, 3)
        rec.log_tick(t_s=0.05 * k, tick=k, ids=np.arange(3), pos=pos, vel=vel, phases=phases)
    rec.close()
    d = load_recording(tmp_path / "x.rrd")
    if detect:
        assert d.exits == {1: pytest.approx(0.10), 2: pytest.approx(0.12)}
    else:
        assert d.exits == {2: pytest.approx(0.12)}
    texts = [e[3] for e in d.events]
    assert "vehicle 1: in_tube → exited" in texts  # the phase events stay either way


def test_two_recorders_in_one_process_stay_apart(tmp_path: Path) -> None:
    a = open_recorder(tmp_path / "a.rrd", app_id="a")
    b = open_recorder(tmp_path / "b.rrd", app_id="b", kind="fleet")
    for rec, n in ((a, 3), (b, 4)):
        rec.log_scene(scenario(n))
    for k in range(20):
        a.log_tick(t_s=k * 0.1, tick=k, ids=np.arange(3), pos=motion(k, 3)[0],
                   vel=motion(k, 3)[1])
        if k % 2 == 0:
            b.log_tick(t_s=k * 0.1, tick=k, ids=np.arange(4), pos=motion(k, 4)[0] + 100,
                       vel=motion(k, 4)[1])
    a.close()
    b.close()
    da, db = load_recording(tmp_path / "a.rrd"), load_recording(tmp_path / "b.rrd")
    assert (da.application_id, len(da.tick), da.pos.shape[1]) == ("a", 20, 3)
    assert (db.application_id, len(db.tick), db.pos.shape[1]) == ("b", 10, 4)
    assert da.recording_id != db.recording_id
    assert np.nanmax(da.pos[..., 0]) < 50 < np.nanmin(db.pos[..., 0])


def test_close_is_idempotent_and_later_calls_are_ignored(tmp_path: Path) -> None:
    rec = open_recorder(tmp_path / "c.rrd")
    rec.log_scene(scenario())
    rec.log_tick(t_s=0.0, tick=0, ids=np.arange(5), pos=motion(0)[0], vel=motion(0)[1])
    rec.close()
    rec.close()
    rec.log_tick(t_s=0.1, tick=1, ids=np.arange(5), pos=motion(1)[0], vel=motion(1)[1])
    rec.log_event(0.1, "late")
    rec.close()
    d = load_recording(tmp_path / "c.rrd")
    assert list(d.tick) == [0] and not d.events


def test_null_recorder_and_protocol(tmp_path: Path) -> None:
    rec = open_recorder(None)
    assert isinstance(rec, NullRecorder) and isinstance(rec, Recorder)
    with rec:
        rec.log_scene(scenario())
        rec.log_tick(t_s=0.0, tick=0, ids=np.arange(5), pos=motion(0)[0], vel=motion(0)[1])
        rec.log_event(0.0, "x")
        rec.log_summary({})
    assert rec.closed
    real = open_recorder(tmp_path / "p.rrd")
    assert isinstance(real, Recorder)
    real.close()
    assert default_blueprint() is not None


def _child(tmp_path: Path, body: str) -> subprocess.Popen[str]:
    script = tmp_path / "child.py"
    script.write_text(textwrap.dedent("""
        import signal, sys, time
        # Ctrl-C as a terminal gives it: a process started with SIGINT ignored (a test
        # worker that ignores it) would keep that, and Python would never raise
        # KeyboardInterrupt (CI saw this test hang for 60 s so)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        import numpy as np
        sys.path.insert(0, {tests!r})
        from test_recording import scenario, motion
        from vtube_fleet.recording.writer import open_recorder
        path = sys.argv[1]
    """).format(tests=str(Path(__file__).parent)) + textwrap.dedent(body))
    return subprocess.Popen([sys.executable, str(script), str(tmp_path / "child.rrd")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO)


def test_unclosed_recorder_is_flushed_at_interpreter_exit(tmp_path: Path) -> None:
    child = _child(tmp_path, """
        rec = open_recorder(path, batch_ticks=1000, max_delay_s=1000.0)
        rec.log_scene(scenario())
        for k in range(37):
            rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(5), pos=motion(k)[0],
                         vel=motion(k)[1])
        # no close(): the atexit hook must send the buffered ticks and flush
    """)
    out, err = child.communicate(timeout=60)
    assert child.returncode == 0, err
    d = load_recording(tmp_path / "child.rrd")
    np.testing.assert_array_equal(d.tick, np.arange(37))


def test_ctrl_c_leaves_a_complete_recording(tmp_path: Path) -> None:
    child = _child(tmp_path, """
        rec = open_recorder(path, batch_ticks=1000, max_delay_s=1000.0)
        k = 0
        try:
            with rec:
                rec.log_scene(scenario())
                while True:
                    rec.log_tick(t_s=0.01 * k, tick=k, ids=np.arange(5), pos=motion(k)[0],
                                 vel=motion(k)[1])
                    k += 1
                    if k == 50:
                        print("ready", flush=True)
                    time.sleep(0.001)  # pacing like a control loop
        except KeyboardInterrupt:
            print(f"calls {rec.calls}", flush=True)
            sys.exit(130)
    """)
    assert child.stdout is not None
    line = child.stdout.readline()
    assert line.strip() == "ready", child.stderr.read() if child.stderr else ""
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=60)
    assert child.returncode == 130, err
    calls = int(out.split()[-1])
    d = load_recording(tmp_path / "child.rrd")
    assert calls >= 50
    np.testing.assert_array_equal(d.tick, np.arange(calls))


def test_bad_paths_are_user_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="is a directory"):
        open_recorder(tmp_path)
    with pytest.raises(RecordingError, match="no such file"):
        load_recording(tmp_path / "missing.rrd")
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"this is not a recording" * 10)
    with pytest.raises(RecordingError, match="not a readable rerun recording|no recording"):
        load_recording(junk)
    import rerun as rr

    other = tmp_path / "other.rrd"
    stream = rr.RecordingStream("someone_else", recording_id="x")
    stream.save(other)
    stream.set_time("t", sequence=0)
    stream.log("a", rr.Scalars(1.0))
    stream.flush()
    stream.disconnect()
    with pytest.raises(RecordingError, match="not a vtube_fleet recording"):
        load_recording(other)
    assert issubclass(RecordingError, UserError)
    with pytest.raises(RecordingError, match="decimation"):
        open_recorder(tmp_path / "x.rrd", decimate=0)


def test_normalize_connect_url() -> None:
    assert normalize_connect_url(None) == DEFAULT_CONNECT_URL
    assert normalize_connect_url("9877") == "rerun+http://127.0.0.1:9877/proxy"
    assert normalize_connect_url(":9877") == "rerun+http://127.0.0.1:9877/proxy"
    assert normalize_connect_url("10.0.0.5:9876") == "rerun+http://10.0.0.5:9876/proxy"
    assert normalize_connect_url("rerun+http://h:1/proxy") == "rerun+http://h:1/proxy"
    assert normalize_connect_url("rerun+http://h:1") == "rerun+http://h:1/proxy"
    with pytest.raises(RecordingError, match="scheme"):
        normalize_connect_url("http://h:1/proxy")
    with pytest.raises(RecordingError, match="HOST:PORT"):
        normalize_connect_url("h:notaport")


def _parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_recording_args(p)
    return p.parse_args(argv)


def test_cli_args(tmp_path: Path) -> None:
    args = _parse([])
    assert args.rerun_connect is None and args.rerun_save is None
    assert _parse(["--rerun-connect"]).rerun_connect == DEFAULT_CONNECT_URL
    assert _parse(["--rerun-connect", "9000"]).rerun_connect == "9000"
    rec = recorder_from_args(args, tmp_path / "out", kind="fleet", decimate=4)
    assert isinstance(rec, RerunRecorder)
    assert rec.path == tmp_path / "out" / "recording.rrd" and rec.decimate == 4
    assert rec.kind == "fleet"
    rec.close()
    rec = recorder_from_args(_parse(["--rerun-save", str(tmp_path / "x.rrd"),
                                     "--rerun-decimate", "2"]), tmp_path / "out", decimate=4)
    assert isinstance(rec, RerunRecorder)
    assert rec.path == tmp_path / "x.rrd" and rec.decimate == 2
    rec.close()
    assert isinstance(recorder_from_args(_parse(["--no-rerun"]), tmp_path), NullRecorder)
    rec = recorder_from_args(args, tmp_path / "out", kind="sim")  # the simulator's default
    assert isinstance(rec, RerunRecorder) and rec.min_period_s == 0.04 and rec.decimate == 1
    rec.close()
    rec = recorder_from_args(_parse(["--rerun-decimate", "1"]), tmp_path / "out", kind="sim")
    assert isinstance(rec, RerunRecorder) and rec.min_period_s == 0.0  # explicit: every frame
    rec.close()
    assert isinstance(recorder_from_args(args, None), NullRecorder)
    with pytest.raises(SystemExit) as exit_:  # refused while parsing, by its declared bound
        _parse(["--rerun-decimate", "0"])
    assert exit_.value.code == 2
    args.rerun_decimate = 0  # a library caller that bypasses the parser
    with pytest.raises(RecordingError, match="--rerun-decimate"):
        recorder_from_args(args, tmp_path)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_viewer_warns_and_still_saves(tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    port = _free_port()
    with caplog.at_level(logging.WARNING, logger="vtube_fleet.recording"):
        rec = open_recorder(tmp_path / "w.rrd", connect=str(port))
    assert isinstance(rec, RerunRecorder) and rec.connect_url is None
    assert f"no rerun viewer answers at rerun+http://127.0.0.1:{port}/proxy" in caplog.text
    rec.log_scene(scenario())
    rec.log_tick(t_s=0.0, tick=0, ids=np.arange(5), pos=motion(0)[0], vel=motion(0)[1])
    rec.close()
    assert len(load_recording(tmp_path / "w.rrd").tick) == 1


def _wait_port(port: int, proc: subprocess.Popen[Any], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, "rerun server exited"
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"rerun server did not listen on {port} within {timeout_s} s")


def _wait_rows(path: Path, rows: int, timeout_s: float) -> Any:
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        try:
            last = load_recording(path)
            if len(last.tick) >= rows and last.summary is not None:
                return last
        except RecordingError:
            pass
        time.sleep(0.1)
    raise AssertionError(f"{path}: expected {rows} ticks, got "
                         f"{None if last is None else len(last.tick)}")


def test_live_viewer_receives_the_stream(tmp_path: Path) -> None:
    """A real rerun server process (``rerun --port P --save FILE``) gets every tick."""
    port = _free_port()
    live = tmp_path / "live.rrd"
    env = dict(os.environ, CI="1")  # no usage analytics from the test's server
    server = subprocess.Popen(["rerun", "--port", str(port), "--save", str(live)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        _wait_port(port, server, 30.0)
        rec = open_recorder(tmp_path / "local.rrd", connect=f"127.0.0.1:{port}")
        assert isinstance(rec, RerunRecorder)
        assert rec.connect_url == f"rerun+http://127.0.0.1:{port}/proxy"
        rec.log_scene(scenario())
        for k in range(25):
            rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(5), pos=motion(k)[0],
                         vel=motion(k)[1])
        rec.log_summary({"exited": 0})
        rec.close()
        d = _wait_rows(live, 25, 30.0)
        np.testing.assert_array_equal(d.tick, np.arange(25))
        np.testing.assert_array_equal(d.pos, load_recording(tmp_path / "local.rrd").pos)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def test_recording_holds_the_default_blueprint(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    rec = open_recorder(tmp_path / "bp.rrd")
    rec.log_event(0.0, "only an event, no scene")
    rec.close()
    assert RrdReader(tmp_path / "bp.rrd").blueprints(), "no blueprint in the file"
    with pytest.raises(RecordingError, match="no meta/scenario"):
        load_recording(tmp_path / "bp.rrd")


def test_nothing_logged_leaves_no_file_and_no_folder(tmp_path: Path) -> None:
    """A run that fails before recording anything must not leave an output folder behind."""
    rec = open_recorder(tmp_path / "out" / "sub" / "r.rrd")
    assert not (tmp_path / "out").exists()
    rec.close()
    assert not (tmp_path / "out").exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RecordingError, match="is not a directory"):
        open_recorder(blocker / "r.rrd")


def test_meta_is_plain_json(tmp_path: Path) -> None:
    rec = open_recorder(tmp_path / "m.rrd")
    rec.log_scene(scenario(), meta={"arr": np.array([1.0, np.inf]), "path": tmp_path})
    rec.close()
    d = load_recording(tmp_path / "m.rrd")
    assert d.meta["arr"] == [1.0, None] and d.meta["path"] == str(tmp_path)
    assert json.loads(json.dumps(d.meta)) == d.meta
    assert d.meta["controller"]["r_a"] == 0.5


def test_bulk_metrics_and_explicit_exits(tmp_path: Path) -> None:
    """The simulator's way: metrics per chunk of steps (reduced per block), exact exits."""
    rec = open_recorder(tmp_path / "s.rrd")
    rec.log_scene(scenario(3))
    ticks = np.arange(20)
    rec.log_metrics(ticks * 0.01, ticks, {
        "min_pair_distance_m": np.where(ticks == 7, np.inf, 1.0 - 0.01 * ticks),
        "max_speed_m_s": 2.0 + 0.1 * (ticks % 5),
    }, every=5)
    for k in (0, 5, 10, 15):
        rec.log_tick(t_s=0.01 * k, tick=k, ids=np.arange(3) if k < 10 else np.array([0, 2]),
                     pos=motion(k, 3)[0] if k < 10 else motion(k, 2)[0],
                     vel=motion(k, 3)[1] if k < 10 else motion(k, 2)[1])
        if k == 5:
            rec.log_exits(0.08, 8, [1])  # between two recorded frames
    rec.close()
    d = load_recording(tmp_path / "s.rrd")
    np.testing.assert_array_equal(d.tick, [0, 5, 10, 15])
    np.testing.assert_allclose(d.metrics["min_pair_distance_m"], [0.96, 0.91, 0.86, 0.81])
    np.testing.assert_allclose(d.metrics["max_speed_m_s"], [2.4] * 4)
    assert d.exits == {1: pytest.approx(0.08)}  # the explicit time, not the next frame's
    assert d.entity_rows["events/exits"] == 1


@pytest.mark.parametrize("policy", ["block", "drop"])
def test_backlog_policy(tmp_path: Path, policy: str) -> None:
    """A stalled sender: "block" waits and loses nothing, "drop" drops ticks and says so.

    Deterministic: the sender is held inside tick 0's job (the queue holds exactly that one
    job then), so ticks 1 and 2 fill the 3 slots and ticks 3..9 find the queue full."""
    import threading

    rec = open_recorder(tmp_path / "q.rrd", batch_ticks=1, max_queued_batches=3,
                        on_backlog=policy, status_period_s=1e9)
    assert isinstance(rec, RerunRecorder)
    rec.log_scene(scenario())
    entered, gate = threading.Event(), threading.Event()
    real = rec._send_rows_now

    def stalled(rows: Any) -> None:
        entered.set()
        gate.wait(timeout=60)
        real(rows)

    rec._send_rows_now = stalled  # type: ignore[method-assign]

    def tick(k: int) -> None:
        rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(5), pos=motion(k)[0],
                     vel=motion(k)[1])

    tick(0)
    assert entered.wait(timeout=30)  # the sender is stuck in tick 0; earlier jobs are done
    with rec._qcond:
        assert rec._queued == 1
    producer = threading.Thread(target=lambda: [tick(k) for k in range(1, 10)])
    producer.start()
    if policy == "drop":
        producer.join(timeout=30)  # never waits for the sender
        assert not producer.is_alive()
        assert rec.dropped_ticks == 7
    else:
        with rec._qcond:  # the producer fills the queue, then waits for the sender
            assert rec._qcond.wait_for(lambda: rec._queued >= 3, timeout=30)
        assert producer.is_alive() and rec.dropped_ticks == 0
    gate.set()
    producer.join(timeout=30)
    assert not producer.is_alive()
    rec.close()
    d = load_recording(tmp_path / "q.rrd")
    if policy == "block":
        assert rec.dropped_ticks == 0
        np.testing.assert_array_equal(d.tick, np.arange(10))
    else:
        assert rec.dropped_ticks == 7
        np.testing.assert_array_equal(d.tick, [0, 1, 2])


def test_min_period_gate(tmp_path: Path) -> None:
    rec = open_recorder(tmp_path / "g.rrd", min_period_s=0.04, decimate=2)
    rec.log_scene(scenario())
    for k in range(31):  # frames every 10 ms
        rec.log_tick(t_s=0.01 * k, tick=10 * k, ids=np.arange(5), pos=motion(k)[0],
                     vel=motion(k)[1])
    rec.close()
    d = load_recording(tmp_path / "g.rrd")
    # every 4th frame passes the 40 ms gate, every 2nd of those is recorded, then the last
    np.testing.assert_array_equal(d.tick, [0, 80, 160, 240, 300])
    assert d.meta["min_period_s"] == 0.04 and d.meta["decimate"] == 2
