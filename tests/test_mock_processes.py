"""A mock fleet split over OS processes (``ProcessFleet``, ``mock-fleet --processes N``).

Every vehicle answers on its own endpoint over real UDP whichever process serves it, and no
child process outlives its parent on any exit path: a clean stop, a start that fails, a child
dying while the fleet runs, Ctrl-C of ``vtube-fleet mock-fleet --processes`` and a SIGKILL of
it (the children see their stdin close). Process exits are awaited through pidfds (Linux),
never with sleeps.
"""

from __future__ import annotations

import asyncio
import os
import select
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from missions import grid_mission

from sim_stub import MockProcessError, ProcessFleet, SimStubError, grid_homes
from sim_stub.ports import free_port_scheme
from vtube_fleet.link import open_links

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _wait_exit(pidfds: dict[int, int], timeout_s: float = 30.0) -> list[int]:
    """Block until every process behind ``pidfds`` (pid → pidfd) has exited (or the timeout:
    then the pids still running are returned)."""
    pending = dict(pidfds)
    while pending:
        ready, _, _ = select.select(list(pending.values()), [], [], timeout_s)
        if not ready:
            break
        for pid, fd in list(pending.items()):
            if fd in ready:
                del pending[pid]
    for fd in pidfds.values():
        os.close(fd)
    return sorted(pending)


def _children(ppid: int) -> list[int]:
    out = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            stat = Path(f"/proc/{name}/stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == ppid:
            out.append(int(name))
    return out


async def test_four_vehicles_over_two_processes_each_answer_on_its_own_link() -> None:
    homes = grid_homes((47.397742, 8.545594, 488.0), 4, 10.0)
    async with ProcessFleet(homes=homes, processes=2, port_scheme=free_port_scheme(4),
                            profile="lite", gcs_link="off", boot_time_scale=0.2) as fleet:
        assert [list(b) for b in fleet.blocks] == [[0, 1], [2, 3]]
        assert len(set(fleet.pids)) == 2 and os.getpid() not in fleet.pids
        lines = fleet.describe()
        assert [line.split(":")[0] for line in lines] == [f"vehicle {i}" for i in range(4)]
        async with open_links(list(fleet.endpoints), "mavlink", sysids=[1, 2, 3, 4]) as links:
            for link in links:
                await link.connect(timeout_s=20.0)
                await link.wait_ready(timeout_s=30.0)
            # each endpoint is answered by its own vehicle: its sysid parameter and its home
            assert [await link.read_param("MAV_SYS_ID") for link in links] == [1, 2, 3, 4]
            for link, home in zip(links, homes, strict=True):
                assert link.state.home is not None
                assert link.state.home.lat_deg == pytest.approx(home[0], abs=1e-6)
                assert link.state.home.lon_deg == pytest.approx(home[1], abs=1e-6)
    assert not any(_alive(pid) for pid in fleet.pids)


async def test_the_dynamics_rate_reaches_every_process() -> None:
    """--tick-hz crosses the process boundary: each child's scheduler ticks at the rate asked
    (the describe lines come from the children themselves)."""
    async with ProcessFleet(2, processes=2, tick_hz=50, port_scheme=free_port_scheme(2),
                            profile="lite", gcs_link="off", boot_time_scale=0.2) as fleet:
        lines = fleet.describe()
        assert len(lines) == 2
        assert all(line.endswith("; dynamics 50 Hz") for line in lines), lines


async def test_repeated_sysids_across_processes() -> None:
    async with ProcessFleet(2, processes=2, sysids=[1, 1], port_scheme=free_port_scheme(2),
                            profile="lite", gcs_link="off", boot_time_scale=0.2) as fleet:
        async with open_links(list(fleet.endpoints), "mavlink", sysids=[1, 1]) as links:
            for link in links:
                await link.connect(timeout_s=20.0)
            assert [await link.read_param("MAV_SYS_ID") for link in links] == [1, 1]
    assert not any(_alive(pid) for pid in fleet.pids)


async def test_a_failing_process_stops_the_others_and_names_itself() -> None:
    ports = free_port_scheme(4)
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blocker.bind((ports.host, ports.vehicle_port(3)))  # vehicle 3 (process 1) cannot bind
    try:
        fleet = ProcessFleet(4, processes=2, port_scheme=ports, profile="lite", gcs_link="off")
        with pytest.raises(SimStubError) as err:
            await fleet.start()
    finally:
        blocker.close()
    msg = str(err.value)
    assert "mock process 1 (vehicles 2..3)" in msg and "vehicle 3" in msg and "\n" not in msg
    assert len(fleet.pids) == 2 and not any(_alive(pid) for pid in fleet.pids)


async def test_a_child_dying_is_reported_and_the_rest_stopped() -> None:
    fleet = ProcessFleet(3, processes=3, port_scheme=free_port_scheme(3), profile="lite",
                         gcs_link="off")
    async with fleet:
        os.kill(fleet.pids[1], signal.SIGKILL)
        with pytest.raises(MockProcessError, match=r"mock process 1 \(vehicles 1\.\.1\) "
                                                    r"exited with status -9 while the fleet ran"):
            await fleet.serve(asyncio.Event())
    assert not any(_alive(pid) for pid in fleet.pids)


async def test_a_child_that_never_gets_ready_is_an_error() -> None:
    fleet = ProcessFleet(2, processes=2, port_scheme=free_port_scheme(2), python="/bin/false")
    with pytest.raises(MockProcessError, match=r"mock process \d \(vehicles \d\.\.\d\) exited "
                                                r"with status 1 before it was ready"):
        await fleet.start()
    assert len(fleet.pids) == 2 and not any(_alive(pid) for pid in fleet.pids)


def test_bad_process_counts_are_one_line_errors() -> None:
    with pytest.raises(SimStubError, match=r"processes must be in 1\.\.2 \(the vehicle count\), "
                                           r"got 3"):
        ProcessFleet(2, processes=3)
    r = subprocess.run([sys.executable, "-m", "sim_stub", "--count", "2", "--processes", "0"],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip() == (
        "error: --processes must be in 1..2 (the vehicle count), got 0")


@pytest.mark.parametrize("how", ["SIGINT", "SIGKILL"])
def test_mock_fleet_command_leaves_no_orphans(tmp_path: Path, how: str) -> None:
    """``vtube-fleet mock-fleet --processes 2``: every endpoint printed; after Ctrl-C (a clean
    stop, exit 0) or a SIGKILL of the command (no clean-up at all) both children exit."""
    mission = tmp_path / "m.toml"
    mission.write_text(grid_mission(4, 20.0, 5.0))
    gcs = free_port_scheme(8).vehicle_base
    proc = subprocess.Popen(
        [sys.executable, "-m", "vtube_fleet", "mock-fleet", str(mission), "--processes", "2",
         "--gcs-port", str(gcs), "--vehicle-port", str(gcs + 4), "--profile", "lite",
         "--gcs-link", "off"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        head = proc.stdout.readline()
        assert head.startswith("4 mock vehicles"), head + (proc.stderr.read() if
                                                          proc.poll() is not None else "")
        endpoints = proc.stdout.readline().strip().split(",")
        assert endpoints == [f"udpin://127.0.0.1:{gcs + i}" for i in range(4)]
        kids = _children(proc.pid)  # the children are ready before the endpoints are printed
        assert len(kids) == 2
        pidfds = {pid: os.pidfd_open(pid) for pid in kids}
        proc.send_signal(getattr(signal, how))
        rc = proc.wait(timeout=60)
        assert rc == (0 if how == "SIGINT" else -signal.SIGKILL)
        assert _wait_exit(pidfds) == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_mock_fleet_command_passes_its_tick_rate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``mock-fleet --tick-hz 50 --processes 2`` reaches the fleet (bench_fleet runs large mock
    fleets at 50 Hz); without it the mock keeps the 100 Hz its dynamics were fitted at."""
    import contextlib

    import vtube_fleet.cli.mock_fleet as cmd
    from vtube_fleet.cli import main

    mission = tmp_path / "m.toml"
    mission.write_text(grid_mission(4, 20.0, 5.0))
    seen: list[dict[str, object]] = []

    class Served:
        endpoints = ("udpin://127.0.0.1:1",)

        async def serve(self, stop: asyncio.Event) -> None:
            return None

    @contextlib.asynccontextmanager
    async def fake(mission_, count, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(kwargs)
        yield Served()

    monkeypatch.setattr(cmd, "mock_fleet", fake)
    assert main(["mock-fleet", str(mission), "--tick-hz", "50", "--processes", "2"]) == 0
    assert main(["mock-fleet", str(mission)]) == 0
    capsys.readouterr()
    assert [(k["tick_hz"], k["processes"]) for k in seen] == [(50.0, 2), (100.0, 1)]


async def test_launch_gives_the_mock_scheduler_the_rate_asked_for(tmp_path: Path) -> None:
    """``launch.mock_fleet(tick_hz=50)`` (what the command calls): the in-process fleet's
    scheduler steps at 50 Hz (ProcessFleet hands the same keyword to its children)."""
    from fleet_ports import free_ports

    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.launch import mock_fleet

    mission = tmp_path / "m.toml"
    mission.write_text(grid_mission(2, 20.0, 5.0))
    async with mock_fleet(load_mission(mission), 2, tick_hz=50.0, port_scheme=free_ports(2),
                          gcs_link="off") as fleet:
        assert fleet.scheduler.tick_hz == 50.0
        assert fleet.scheduler.dt == pytest.approx(0.02)
