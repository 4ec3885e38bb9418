"""A SITL fleet in one command (issue 34 part 4): ``vtube-fleet sitl`` and ``run --sitl``.

PX4 is not installed here (nor in CI): the instances are ``python -m sim_stub --first I``
processes started through the launcher's generic command template, on free ports (other test
runs may hold PX4's 14540+ range). What is checked is what a user relies on: every instance
answers on its own API port with system id i+1 from slot i's home, Ctrl-C (SIGINT to the
command) stops them all with no process left (judged from /proc: no process in any
instance's process group), ``run --sitl`` flies a small mission to touch-down (judged by the
mock's ground truth, which the run asks every instance for) and leaves no process, and the
refusals are one line, exit 2: a binary that does not exist, an instance that never answers or
exits first (named with its log file), ports already taken.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import stat
import sys
from pathlib import Path

import pytest
from fleet_ports import free_ports
from missions import straight_mission, write_mission
from pymavlink.dialects.v20 import common as mavlink2
from test_inputs import one_error_line

from vtube_fleet.cli import main
from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import sitl_homes
from vtube_fleet.fleet.sitl import (
    InstanceCommand,
    SitlError,
    SitlFleet,
    command_template,
    px4_command,
)

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "MAVLINK20": "1"}

#: One sim_stub vehicle as SITL instance I: its ports (custom bases, + I), sysid I+1, the home
#: of slot I (the launcher fills the placeholders).
STUB = (f"{sys.executable} -m sim_stub --first {{instance}} --home "
        f"{{home_lat}},{{home_lon}},{{home_alt}} --ports {{vehicle_port_base}}:{{api_port_base}}"
        f" --gcs-link off")

pytestmark = pytest.mark.timeout(240)


def small_mission(tmp_path: Path, count: int = 3) -> Path:
    positions = [[2.0, -4.5 + 4.5 * k] for k in range(count)]
    write_mission(tmp_path, straight_mission(12.0, positions))
    return tmp_path / "mission.toml"


def ports(count: int) -> tuple[int, int]:
    """(API port base, vehicle port base) with 2·count free ports."""
    scheme = free_ports(count)
    return scheme.gcs_base, scheme.vehicle_base


def in_groups(pgids: set[int]) -> list[str]:
    """Processes (not zombies) whose process group is one of ``pgids``: what was left."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            text = (d / "stat").read_text()
        except OSError:
            continue
        fields = text.rsplit(")", 1)[1].split()
        if int(fields[2]) in pgids and fields[0] != "Z":
            out.append(f"pid {d.name} ({text.split('(', 1)[1].split(')')[0]}) state "
                       f"{fields[0]}")
    return out


def gone(pid: int) -> bool:
    """Reaped (no /proc entry) or at least dead."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return text.rsplit(")", 1)[1].split()[0] == "Z"


def pids_of(text: str) -> list[int]:
    """The pids of the ``  instance I: pid N, …`` lines."""
    return [int(line.split("pid ")[1].split(",")[0]) for line in text.splitlines()
            if line.lstrip().startswith("instance ") and ": pid " in line]


class Heartbeats(asyncio.DatagramProtocol):
    """The test's own ground station on one API port: the sysids of the HEARTBEATs heard."""

    def __init__(self) -> None:
        self.mav = mavlink2.MAVLink(None)
        self.mav.robust_parsing = True
        self.heard = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr: object) -> None:
        for m in self.mav.parse_buffer(data) or []:
            if m.get_type() == "HEARTBEAT" and not self.heard.done():
                self.heard.set_result(m.get_srcSystem())


async def heard_on(port: int) -> int:
    loop = asyncio.get_running_loop()
    proto = Heartbeats()
    transport, _ = await loop.create_datagram_endpoint(lambda: proto,
                                                       local_addr=("127.0.0.1", port))
    try:
        return await asyncio.wait_for(proto.heard, 20.0)
    finally:
        transport.close()


# ----------------------------------------------------------------------------------------------
async def test_sitl_starts_every_slot_and_ctrl_c_stops_them_all(tmp_path: Path) -> None:
    mission = small_mission(tmp_path)
    api, veh = ports(3)
    out = tmp_path / "out"
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vtube_fleet", "sitl", str(mission), "--command", STUB,
        "--api-port", str(api), "--vehicle-port", str(veh), "--out", str(out),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=ENV)
    lines: list[str] = []
    try:
        while not lines or not lines[-1].startswith("endpoints: "):
            raw = await asyncio.wait_for(proc.stdout.readline(), 60.0)
            assert raw, f"sitl ended early: {lines} {await proc.stderr.read()}"
            lines.append(raw.decode().rstrip())
        text = "\n".join(lines)
        pids = pids_of(text)
        assert len(pids) == 3, text
        assert lines[-1] == "endpoints: " + ",".join(
            f"udpin://127.0.0.1:{api + i}" for i in range(3))
        # they answer, to another ground station too: instance i with sysid i+1
        assert [await heard_on(api + i) for i in range(3)] == [1, 2, 3]
        assert in_groups(set(pids)), "the instances are not running"
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)  # Ctrl-C to the command only
        rest = await asyncio.wait_for(proc.communicate(), 60.0)
    tail = rest[0].decode()
    assert proc.returncode == 0, rest
    assert "sitl: SIGINT: stopping 3 instances" in tail and "sitl: stopped" in tail
    assert all(gone(p) for p in pids)
    assert in_groups(set(pids)) == []
    # instance i ran in its own working directory from slot i's home, logged beside it
    homes = sitl_homes(load_mission(mission))
    info = json.loads((out / "sitl" / "instances.json").read_text())
    assert [i["pid"] for i in info["instances"]] == pids
    for i in range(3):
        log = (out / "sitl" / f"instance-{i}.log").read_text()
        h = homes[i]
        assert (f"vehicle {i}: sysid {i + 1} compid 1, binds udp 127.0.0.1:{veh + i} -> GCS "
                f"udpin://127.0.0.1:{api + i}, home {h['PX4_HOME_LAT']},{h['PX4_HOME_LON']},"
                f"{h['PX4_HOME_ALT']}") in log, log
        assert "sim_stub: stopping" in log  # SIGTERM was enough: it stopped itself
        assert (out / "sitl" / f"instance-{i}").is_dir()
        assert info["instances"][i]["env"]["PX4_HOME_LAT"] == h["PX4_HOME_LAT"]


@pytest.mark.slow
def test_run_sitl_flies_a_small_mission_and_leaves_no_process(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mission = small_mission(tmp_path, 2)
    api, veh = ports(2)
    out = tmp_path / "out"
    rc = main(["run", str(mission), "--sitl-command", STUB, "--sitl-api-port", str(api),
               "--sitl-vehicle-port", str(veh), "--out", str(out), "--no-rerun", "-q"])
    err = capsys.readouterr().err
    pids = pids_of(err)
    assert len(pids) == 2, err
    assert all(gone(p) for p in pids) and in_groups(set(pids)) == [], err
    s = json.loads((out / "summary.json").read_text())
    assert rc == 0 and s["outcome"] == "completed", (s.get("reason"), err)
    assert [v["phase"] for v in s["vehicle_states"]] == ["landed"] * 2
    # judged by the ground truth every instance sent (run --sitl asks for it)
    assert s["truth"] is True and s["truth_violations"] == 0
    assert s["truth_min_pair_distance_airborne_m"] > 2 * 0.3
    assert f"sitl: every instance answers: udpin://127.0.0.1:{api}," in err
    print(f"\nrun --sitl (2 sim_stub instances): {s['outcome']}, true pair "
          f"{s['truth_min_pair_distance_airborne_m']:.2f} m, legs "
          f"{s['truth_min_left_leg_distance_m']:.2f} / {s['truth_min_right_leg_distance_m']:.2f}"
          f" m, flight {s['flight_time_s']:.1f} s")


# ----------------------------------------------------------------------------------------------
# refusals: one line, exit 2
# ----------------------------------------------------------------------------------------------
def test_a_binary_that_does_not_exist_is_refused(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    mission = small_mission(tmp_path)
    out = tmp_path / "out"
    for argv in (["sitl", str(mission), "--px4", str(tmp_path / "nowhere" / "px4")],
                 ["run", str(mission), "--sitl", str(tmp_path / "nowhere" / "px4"), "-q"]):
        assert main([*argv, "--out", str(out)]) == 2
        line = one_error_line(capsys.readouterr().err)
        assert f"--{argv[2][2:] if argv[0] == 'sitl' else 'sitl'}" in line or "--px4" in line
        assert "nowhere/px4: no such file" in line, line
        assert not out.exists()
    # a file that is no PX4 build: not executable, or no etc/ beside its bin/
    fake = tmp_path / "build" / "bin" / "px4"
    fake.parent.mkdir(parents=True)
    fake.write_text("#!/bin/sh\n")
    assert main(["sitl", str(mission), "--px4", str(fake), "--out", str(out)]) == 2
    assert "not an executable file" in one_error_line(capsys.readouterr().err)
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    assert main(["sitl", str(mission), "--px4", str(fake), "--out", str(out)]) == 2
    assert "no PX4 startup files at" in one_error_line(capsys.readouterr().err)
    # a command that is no program; a placeholder that does not exist
    for cmd, want in (("no-such-simulator -i {instance}", "no such program"),
                      (f"{sys.executable} -c pass {{slot}}", "unknown placeholder {slot}")):
        assert main(["sitl", str(mission), "--command", cmd, "--out", str(out)]) == 2
        assert want in one_error_line(capsys.readouterr().err)
    assert not out.exists()


def test_px4_is_started_as_the_captures_started_it(tmp_path: Path) -> None:
    """The PX4 template (no PX4 here: its rendering): ``px4 -i I -d ETC`` with the SIH model
    and slot I's home; a model other than SIH gets no PX4_SIMULATOR."""
    fake = tmp_path / "PX4-Autopilot" / "build" / "px4_sitl_default" / "bin" / "px4"
    (fake.parents[1] / "etc" / "init.d-posix").mkdir(parents=True)
    fake.parent.mkdir(parents=True)
    fake.write_text("#!/bin/sh\n")
    fake.chmod(0o755)
    cmd = px4_command(fake)
    home = sitl_homes(load_mission(small_mission(tmp_path)))[2]
    argv, env = cmd.render(2, home, tmp_path / "w")
    assert argv == [str(fake.resolve()), "-i", "2", "-d", str(fake.parents[1] / "etc")]
    assert env == {**home, "PX4_SIM_MODEL": "sihsim_quadx", "PX4_SIMULATOR": "sihsim"}
    assert cmd.ports(2) == [14542, 14582, 18572]
    assert "PX4_SIMULATOR" not in px4_command(fake, "gz_x500").render(0, home, tmp_path)[1]


def test_an_instance_that_never_answers_is_named_with_its_log(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mission = small_mission(tmp_path)
    api, veh = ports(2)
    out = tmp_path / "out"
    silent = f"{sys.executable} -c \"print('simulating nothing', flush=True); " \
             f"import time; time.sleep(600)\""
    rc = main(["sitl", str(mission), "--command", silent, "--count", "2", "--api-port", str(api),
               "--vehicle-port", str(veh), "--timeout", "1.5", "--out", str(out)])
    cap = capsys.readouterr()
    assert rc == 2
    line = one_error_line(cap.err)
    logs = [out / "sitl" / f"instance-{i}.log" for i in range(2)]
    assert line.startswith("error: 2 of 2 SITL instances did not start: "), line
    for i in range(2):  # each named, with its log
        assert (f"instance {i} did not answer within 1.5 s (no MAVLink HEARTBEAT on udp "
                f"127.0.0.1:{api + i}, 0 datagrams); its log: {logs[i]}; its last line: "
                f"'simulating nothing'") in line, line
    pids = pids_of(cap.out)
    assert len(pids) == 2 and all(gone(p) for p in pids) and in_groups(set(pids)) == []
    # one that exits first
    dead = f"{sys.executable} -c \"print('no simulator here'); raise SystemExit(3)\""
    rc = main(["sitl", str(mission), "--command", dead, "--count", "1", "--api-port", str(api),
               "--vehicle-port", str(veh), "--out", str(out)])
    line = one_error_line(capsys.readouterr().err)
    assert rc == 2
    assert (f"SITL instance 0 exited with code 3 before it answered on udp 127.0.0.1:{api}; "
            f"its log: {logs[0]}; its last line: 'no simulator here'") in line, line


def test_ports_already_taken_are_refused_before_anything_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import socket

    mission = small_mission(tmp_path)
    api, veh = ports(3)
    out = tmp_path / "out"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b:
        a.bind(("127.0.0.1", api + 1))  # a ground station of instance 1 still up
        b.bind(("0.0.0.0", veh + 2))  # something where instance 2 binds
        for argv in (["sitl", str(mission), "--command", STUB, "--api-port", str(api),
                      "--vehicle-port", str(veh)],
                     ["run", str(mission), "--sitl-command", STUB, "--sitl-api-port", str(api),
                      "--sitl-vehicle-port", str(veh), "-q", "--no-rerun"]):
            assert main([*argv, "--out", str(out)]) == 2
            line = one_error_line(capsys.readouterr().err)
            assert (f"UDP ports taken: {api + 1} of instance 1 (the ground-station side of its "
                    f"API link): in use; {veh + 2} of instance 2 (it binds it): in use") in line
            assert "nothing started" in line
            assert not (out / "sitl").exists()


def test_options_that_do_not_go_together(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    mission = small_mission(tmp_path)
    for argv, want in (
            (["run", str(mission), "--sitl-command", STUB, "--endpoints",
              "udpin://127.0.0.1:14540"], "--sitl-command and --endpoints: give one"),
            (["run", str(mission), "--sitl-model", "gz_x500"], "--sitl-model without --sitl"),
            (["sitl", str(mission), "--command", STUB, "--model", "x"], "--model goes with --px4"),
    ):
        assert main([*argv, "--out", str(tmp_path / "o"), "-q"] if argv[0] == "run"
                    else [*argv, "--out", str(tmp_path / "o")]) == 2
        assert want in one_error_line(capsys.readouterr().err)
    assert main(["sitl", str(mission), "--command", STUB, "--api-port", "20000",
                 "--vehicle-port", "20002", "--out", str(tmp_path / "o")]) == 2
    assert ("--command: instances 0 and 2 would both use port 20002" in
            one_error_line(capsys.readouterr().err))
    with pytest.raises(SystemExit) as info:  # sitl needs a simulator
        main(["sitl", str(mission)])
    assert info.value.code == 2
    assert "one of the arguments --px4 --command is required" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
async def test_stop_kills_what_ignores_sigterm_and_what_it_left(tmp_path: Path) -> None:
    """An instance that ignores SIGTERM is killed after the grace, and a process it started
    (its group) goes with it; nothing is left."""
    script = tmp_path / "stubborn.py"
    script.write_text(
        "import signal, subprocess, sys, time\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)'])\n"
        "print('child', child.pid, flush=True)\n"
        "time.sleep(600)\n")
    api, veh = ports(1)
    cmd = InstanceCommand((sys.executable, str(script)), {}, api, (veh,), "stub")
    fleet = SitlFleet(load_mission(small_mission(tmp_path)), cmd, tmp_path / "sitl", count=1,
                      stop_grace_s=0.5)
    await fleet.start()
    try:
        log = fleet.instances[0].log_path
        for _ in range(400):  # until it has started its child
            if "child" in log.read_text():
                break
            await asyncio.sleep(0.025)
        child = int(log.read_text().split()[1])
        leader = fleet.instances[0].pid
        assert not gone(child)
    finally:
        await fleet.stop()
    assert fleet.instances[0].process.returncode == -signal.SIGKILL
    assert gone(leader) and gone(child) and in_groups({leader}) == []


def test_a_template_is_checked_before_anything_starts() -> None:
    with pytest.raises(SitlError, match=r"unknown placeholder \{0\}"):
        command_template(f"{sys.executable} {{0}}")
    with pytest.raises(SitlError, match="bad template"):
        command_template(f"{sys.executable} {{instance:q}}")
    cmd = command_template(f"{sys.executable} -i {{instance}} {{{{literal}}}}",
                           api_port_base=20000, vehicle_port_base=21000)
    home = {"PX4_HOME_LAT": "1", "PX4_HOME_LON": "2", "PX4_HOME_ALT": "3"}
    assert cmd.render(4, home, Path("/w"))[0] == [sys.executable, "-i", "4", "{literal}"]
    assert cmd.ports(4) == [20004, 21004]
