"""The operator's live picture: the map in the recording, the served web viewer and the spawned
native viewer — checked with a real gRPC client, a real viewer under Xvfb and a real headless
Chromium; a viewer or browser killed mid-flight changes nothing in the flight.

Without Xvfb, lavapipe (mesa-vulkan-drivers) or chromium these tests skip, and under CI=true
they fail (CI must have them).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.request import urlopen

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import live_view  # noqa: E402
from mock_process import child_env, mock_process  # noqa: E402

from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.fleet.onboard import fence_items  # noqa: E402
from vtube_fleet.recording import RecordingError, load_recording, open_recorder  # noqa: E402
from vtube_fleet.recording.live import rerun_executable  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "configs" / "mock_fleet.toml"
LAVAPIPE = Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")


def require(what: str, present: bool) -> None:
    """A missing component skips the test on a developer's machine and fails it in CI."""
    if present:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"{what} is missing (CI must install it: see tests/live_view.py)")
    pytest.skip(f"{what} is not installed")


def _have(exe: str) -> bool:
    import shutil

    return shutil.which(exe) is not None


def _chunks(path: Path) -> dict[str, list[Any]]:
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    out: dict[str, list[Any]] = {}
    for ch in r.stream(store=r.recordings()[0]).to_chunks():
        out.setdefault(str(ch.entity_path).lstrip("/"), []).append(ch.to_record_batch())
    return out


def _values(batches: list[Any], column: str) -> list[Any]:
    vals: list[Any] = []
    for rb in batches:
        if column in rb.schema.names:
            vals += [v for v in rb.column(column).to_pylist() if v is not None]
    return vals


def _fly_straight(rec: Any, ticks: int = 60, pause_s: float = 0.0) -> np.ndarray:
    """The mock mission's scene and a straight flight along x (what the map must show)."""
    m = load_mission(MISSION)
    rec.log_scene(m.scenario, None, mission=m.config, meta={"rate_hz": 20.0})
    n = m.count
    pos = m.slots.copy()
    for k in range(ticks):
        pos = m.slots + np.array([0.5 * k * 0.05, 0.0])
        rec.log_tick(t_s=k * 0.05, tick=k, ids=np.arange(n), pos=pos,
                     vel=np.tile([0.5, 0.0], (n, 1)), phases=["in_tube"] * n)
        if pause_s:
            time.sleep(pause_s)
    return pos


# ---------------------------------------------------------------------------------------------
# the map in the file (no viewer)
# ---------------------------------------------------------------------------------------------
def test_the_map_is_in_the_recording_from_the_fences_geodesy(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    with open_recorder(path, kind="fleet") as rec:
        last = _fly_straight(rec)
    ents = _chunks(path)
    for e in ("map/tube", "map/obstacles", "map/fence", "map/slots"):
        assert _values(ents[e], "GeoLineStrings:line_strings"), e
    m = load_mission(MISSION)
    # the fence drawn is the fence uploaded: PX4's items, vertex by vertex (same conversion)
    items = fence_items(m)
    poly = np.array(_values(ents["map/fence"], "GeoLineStrings:line_strings")[0][0])
    want = np.array([(i.lat_deg, i.lon_deg) for i in items if i.command == 5001])
    assert np.allclose(poly[:-1], want, rtol=0, atol=1e-12) and np.allclose(poly[-1], want[0])
    # every vehicle on the map where the frame puts its tube-frame position
    geo = _values(ents["world/vehicles/3"], "GeoPoints:positions")
    assert len(geo) == 60
    lat, lon, _ = m.frame.tube_to_geodetic(last[3, 0], last[3, 1], 0.0)
    assert np.allclose(geo[-1][0], [float(lat), float(lon)], rtol=0, atol=1e-12)
    assert set(_values(ents["world/vehicles/3"], "GeoPoints:class_ids")[0]) == {5}  # in tube
    assert _values(ents["world/vehicles/3"], "GeoLineStrings:line_strings")  # its trail
    assert _values(ents["world/vehicles/3/path"], "GeoLineStrings:line_strings")  # whole flight
    # the review still reads the same recording
    assert load_recording(path).pos.shape == (60, 12, 2)


def test_no_fence_uploaded_no_fence_on_the_map(tmp_path: Path) -> None:
    m = load_mission(MISSION)
    path = tmp_path / "run.rrd"
    with open_recorder(path, kind="fleet") as rec:
        rec.log_scene(m.scenario, None, mission=m.config, meta={"fence": False})
        rec.log_tick(t_s=0.0, tick=0, ids=np.arange(m.count), pos=m.slots,
                     vel=np.zeros((m.count, 2)), phases=["ready"] * m.count)
    ents = _chunks(path)
    assert "map/tube" in ents and "map/fence" not in ents


def test_no_geodetic_anchor_no_map(tmp_path: Path) -> None:
    from vtube_fleet.config.scenario import load_scenario

    sc = load_scenario(ROOT / "configs" / "paper.toml")
    path = tmp_path / "sim.rrd"
    with open_recorder(path, kind="sim") as rec:
        rec.log_scene(sc, None)
        rec.log_tick(t_s=0.0, tick=0, ids=np.arange(sc.robots.count), pos=sc.robots.positions,
                     vel=np.zeros((sc.robots.count, 2)))
    ents = _chunks(path)
    assert not any(e.startswith("map") for e in ents)
    assert not _values(ents["world/vehicles/0"], "GeoPoints:positions")


# ---------------------------------------------------------------------------------------------
# the served web viewer: the page over HTTP, the stream to a real gRPC client
# ---------------------------------------------------------------------------------------------
def test_served_page_and_a_real_client_gets_the_stream(tmp_path: Path) -> None:
    port = live_view.free_port(2)
    rec = open_recorder(tmp_path / "run.rrd", kind="fleet", serve_web=port)
    client = None
    try:
        web = rec.web  # type: ignore[attr-defined]
        assert web.url == (f"http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A"
                           f"{port + 1}%2Fproxy")
        page = urlopen(f"http://127.0.0.1:{port}/", timeout=10).read().decode()
        assert "<html" in page.lower() and "rerun" in page.lower()
        listening = subprocess.run(["ss", "-ltnH"], capture_output=True, text=True).stdout
        for p in (port, port + 1):  # loopback only by default
            assert re.search(rf"127\.0\.0\.1:{p}\b", listening), listening
            assert not re.search(rf"(0\.0\.0\.0|\*|\[::\]):{p}\b", listening), listening
        # the rerun CLI as a gRPC client of the server: it saves what it receives
        client = subprocess.Popen(
            [rerun_executable(), web.grpc_url, "--save", str(tmp_path / "client.rrd"),
             "--port", str(live_view.free_port()), "--bind", "127.0.0.1"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "RERUN_APP_ONLY": "true"})
        _fly_straight(rec, ticks=60, pause_s=0.02)
    finally:
        rec.close()
    assert client.wait(timeout=30) == 0  # the server stopped with the recording: it ends
    got = _chunks(tmp_path / "client.rrd")
    assert _values(got["map/fence"], "GeoLineStrings:line_strings")
    assert len(_values(got["world/vehicles/0"], "GeoPoints:positions")) == 60
    assert load_recording(tmp_path / "run.rrd").pos.shape == (60, 12, 2)  # the file as always
    with pytest.raises(OSError):  # the server is gone with the recording
        urlopen(f"http://127.0.0.1:{port}/", timeout=2)


def test_every_interface_when_asked(tmp_path: Path) -> None:
    """``--rerun-bind 0.0.0.0``: both ports on every interface, the URL names this machine, and
    the page's origin may read the data port (CORS)."""
    import socket

    port = live_view.free_port(2)
    with open_recorder(None, kind="fleet", serve_web=port, serve_bind="0.0.0.0") as rec:
        web = rec.web  # type: ignore[attr-defined]
        host = socket.gethostname()
        assert web.url.startswith(f"http://{host}:{port}/?url=rerun%2Bhttp%3A%2F%2F{host}%3A")
        listening = subprocess.run(["ss", "-ltnH"], capture_output=True, text=True).stdout
        for p in (port, port + 1):
            assert re.search(rf"(0\.0\.0\.0|\*):{p}\b", listening), listening
        args = Path(f"/proc/{web.pid}/cmdline").read_bytes().split(b"\0")
        assert b"--cors-allow-origin" in args and f"http://*:{port}".encode() in args


def test_a_port_in_use_is_one_error_before_the_run(tmp_path: Path) -> None:
    import socket

    port = live_view.free_port(2)
    with socket.socket() as s:
        s.bind(("127.0.0.1", port + 1))
        s.listen()
        with pytest.raises(RecordingError, match=rf"data \(gRPC\) port {port + 1} is in use"):
            open_recorder(tmp_path / "run.rrd", kind="fleet", serve_web=port)
    assert not (tmp_path / "run.rrd").exists()


def test_no_display_no_viewer_and_the_run_records_anyway(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch,
                                                         caplog: pytest.LogCaptureFixture
                                                         ) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    rec = open_recorder(tmp_path / "run.rrd", kind="fleet", viewer=True,
                        viewer_port=live_view.free_port())
    with rec:
        assert rec.viewer_url is None  # type: ignore[attr-defined]
        _fly_straight(rec, ticks=5)
    assert "no rerun viewer could be started: no display" in caplog.text
    assert load_recording(tmp_path / "run.rrd").pos.shape == (5, 12, 2)


# ---------------------------------------------------------------------------------------------
# real viewers during a real (mock) flight; killing them changes nothing
# ---------------------------------------------------------------------------------------------
def _start_run(out: Path, endpoints: list[str], *extra: str,
               env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``vtube-fleet run`` of the mock mission on a mock fleet of free ports (tests/
    mock_process.py), with the ground truth."""
    return subprocess.Popen(
        [sys.executable, "-m", "vtube_fleet", "run", str(MISSION), "--out", str(out),
         "--endpoints", ",".join(endpoints), "--truth", *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**child_env(), **(env or {})})


def _wait_for_line(proc: subprocess.Popen[str], pattern: str, lines: list[str],
                   timeout_s: float = 120.0) -> re.Match[str]:
    """Read the run's stderr until a line matches (the lines read are kept in ``lines``)."""
    assert proc.stderr is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        m = re.search(pattern, line)
        if m:
            return m
    raise AssertionError(f"no line matching {pattern!r}:\n{''.join(lines[-30:])}")


def _finish(proc: subprocess.Popen[str], lines: list[str]) -> int:
    _out, err = proc.communicate(timeout=300)
    lines.append(err)
    return proc.returncode


def _assert_flight_unaffected(out: Path, rc: int, lines: list[str]) -> dict[str, Any]:
    """The flight as without a viewer: a clean exit, every vehicle through, a complete summary,
    and the recording's review equal to it."""
    assert rc == 0, "".join(lines)[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True and summary["outcome"] == "completed"
    assert summary["exited"] == summary["robots"] == 12 and summary["violations"] == 0
    rev = subprocess.run([sys.executable, "-m", "vtube_fleet", "review",
                          str(out / "recording.rrd"), "--json", "--no-plots"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert rev.returncode == 0, rev.stderr
    again = json.loads(rev.stdout)
    for key in ("exited", "violations", "min_pair_distance_m", "min_obstacle_center_distance_m"):
        assert again[key] == pytest.approx(summary[key], abs=1e-9), key
    return summary


def _png_has_map(png: Path) -> None:
    """The screenshot is a picture, not a blank page: many colours, the fence's red among them
    (the map's outline colours are drawn whether or not tiles load)."""
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).reshape(-1, 3).astype(int)
    assert len(np.unique(img[::7], axis=0)) > 50
    red = (img[:, 0] > 200) & (img[:, 1] < 90) & (img[:, 2] < 90)  # MAP_FENCE_COLOR E53935
    assert red.sum() > 200


def _until_map(take: Callable[[], object], shot: Path, run: subprocess.Popen[str],
               timeout_s: float = 120.0) -> None:
    """Take screenshots into ``shot`` until one shows the map (``_png_has_map``), the flight
    still going on; the last failure is raised after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        assert run.poll() is None, "the flight ended before the viewer showed the map"
        try:
            take()  # a page still loading may not have a frame to capture yet (RuntimeError)
            _png_has_map(shot)
            return
        except (AssertionError, RuntimeError):
            if time.monotonic() > deadline:
                raise
        time.sleep(2.0)  # the pace of the polling, not a wait for something


@pytest.mark.xdist_group("heavy")  # one at a time (tests/conftest.py)
@pytest.mark.solo  # and nothing else beside it: it draws in software on these cores
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_chromium_shows_the_live_map_and_closing_it_changes_nothing(tmp_path: Path) -> None:
    require("chromium", _have("chromium") or _have("chromium-browser"))
    port = live_view.free_port(2)
    out = tmp_path / "run"
    with mock_process(MISSION, 12) as (_mock, endpoints):
        _browser_run(tmp_path, out, port, endpoints)


def _browser_run(tmp_path: Path, out: Path, port: int, endpoints: list[str]) -> None:
    run = _start_run(out, endpoints, "--serve-web", str(port))
    lines: list[str] = []
    try:
        url = _wait_for_line(run, r"live view: open (\S+) in a browser", lines).group(1)
        assert url.startswith(f"http://127.0.0.1:{port}/?url=")
        _wait_for_line(run, r"stage: tube", lines)
        # the lowest priority: the flight computer's control loop gets the CPU first (docs/
        # recording.md: Chromium drawing in software on these 2 cores can stall the loop)
        with live_view.chromium("1600x900", nice=19) as (browser, dt_port):
            dt = live_view.DevTools(dt_port)
            dt.call("Emulation.setDeviceMetricsOverride", width=1600, height=900,
                    deviceScaleFactor=1, mobile=False)
            dt.call("Page.navigate", url=url)
            shot = tmp_path / "browser.png"
            # the wasm viewer loads, connects and draws (software WebGPU): until the page
            # shows the map, a screenshot every 2 s while the flight goes on
            _until_map(lambda: dt.screenshot(shot), shot, run)
            # the browser dies mid-flight (SIGKILL to its whole process group)
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)
        rc = _finish(run, lines)
    finally:
        if run.poll() is None:
            run.send_signal(signal.SIGINT)
            run.wait(timeout=120)
    _assert_flight_unaffected(out, rc, lines)


@pytest.mark.xdist_group("heavy")  # one at a time (tests/conftest.py)
@pytest.mark.solo  # and nothing else beside it: it draws in software on these cores
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_native_viewer_live_under_xvfb_and_killing_it_changes_nothing(tmp_path: Path) -> None:
    require("Xvfb", _have("Xvfb"))
    require("lavapipe (mesa-vulkan-drivers)", LAVAPIPE.is_file())
    from rerun.experimental import ViewerClient

    out = tmp_path / "run"
    vport = live_view.free_port()
    with live_view.xvfb("1600x900") as display, mock_process(MISSION, 12) as (_, endpoints):
        env = {"DISPLAY": display, "VK_ICD_FILENAMES": str(LAVAPIPE)}
        # the run spawns the viewer on the port --rerun-connect names (the rerun default 9876
        # without it); here a free one, so that no other viewer on this machine is reused
        run = _start_run(out, endpoints, "--viewer", "--rerun-connect", str(vport), env=env)
        lines: list[str] = []
        pid = None
        try:
            m = _wait_for_line(run, r"live view: streaming to the rerun viewer at (\S+) "
                                    r"\(started, process (\d+)\)", lines)
            assert m.group(1) == f"rerun+http://127.0.0.1:{vport}/proxy"
            pid = int(m.group(2))
            _wait_for_line(run, r"stage: tube", lines)
            client = ViewerClient(m.group(1))
            shot = tmp_path / "viewer.png"
            _until_map(lambda: shot.write_bytes(client.take_screenshot()), shot, run)
            state = client.get_state()
            views = {v.name: v for v in state.views}
            assert views["map (WGS84)"].view_class == "Map" and not views["map (WGS84)"].reports
            os.kill(pid, signal.SIGKILL)  # the viewer dies mid-flight
            pid = None
            assert run.poll() is None, "the flight ended before the viewer was killed"
            rc = _finish(run, lines)
        finally:
            if pid is not None:
                os.kill(pid, signal.SIGKILL)
            if run.poll() is None:
                run.send_signal(signal.SIGINT)
                run.wait(timeout=120)
    _assert_flight_unaffected(out, rc, lines)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_recording_renders_in_the_native_viewer_under_xvfb(tmp_path: Path) -> None:
    """The docs' route (tests/live_view.py viewer): the file's blueprint lays out the tube
    view, the map and the safety plots, and the viewer draws every view without a report."""
    require("Xvfb", _have("Xvfb"))
    require("lavapipe (mesa-vulkan-drivers)", LAVAPIPE.is_file())
    path = tmp_path / "run.rrd"
    with open_recorder(path, kind="fleet") as rec:
        _fly_straight(rec, ticks=200)
    shot = tmp_path / "shot.png"
    info = live_view.viewer_screenshot(path, shot, time_s=5.0, size="1600x900", settle_s=5.0)
    views = {v["name"]: v for v in info["views"]}
    assert views["map (WGS84)"]["class"] == "Map"
    assert views["tube (x →, y ↓ drawn downwards)"]["class"] == "2D"
    assert any(v["class"] == "TimeSeries" for v in info["views"])
    assert not [v for v in info["views"] if v["reports"]], info
    _png_has_map(shot)
