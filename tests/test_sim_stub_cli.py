"""``python -m sim_stub``: endpoints printed, runs until SIGINT/SIGTERM, clean exit; one-line
errors with exit status 2 for bad input."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mav

from sim_stub.ports import free_port_scheme

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(60)


def _run(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-m", "sim_stub", *args], capture_output=True, text=True, timeout=30,
        cwd=ROOT, env=env,
    )  # fmt: skip


@pytest.mark.parametrize(
    "args, message",
    [
        (["--home", "47.4,8.5"],
         "error: --home must be LAT,LON,ALT (three numbers), got '47.4,8.5'"),
        (["--home", "95,8.5,400"], "error: home latitude must be in (-90, 90) deg, got 95.0"),
        (["--count", "41"], "error: port scheme 'px4' (vehicles 14580+i, GCS 14540+i) holds at "
                            "most 40 vehicles, 41 requested (use port_scheme='wide' / --ports "
                            "wide)"),
        (["--count", "0"], "error: --count must be >= 1, got 0"),
        (["--ports", "abc"],
         "error: --ports must be px4, wide or VEHICLE_BASE:GCS_BASE, got 'abc'"),
        (["--fault", "3:loss=5"], "error: --fault '3:loss=5': no vehicle 3 (count is 1)"),
        (["--homes", "/nonexistent/homes.csv"], "error: /nonexistent/homes.csv: cannot read homes "
                                                "file: No such file or directory"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(args: list[str], message: str) -> None:
    r = _run(*args)
    assert r.returncode == 2
    assert r.stderr.strip() == message
    assert "Traceback" not in r.stderr


def test_port_in_use_is_reported() -> None:
    ports = free_port_scheme(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((ports.host, ports.vehicle_port(0)))
        r = _run("--ports", f"{ports.vehicle_base}:{ports.gcs_base}")
    assert r.returncode == 2
    assert r.stderr.startswith(f"error: vehicle 0: cannot bind UDP 127.0.0.1:{ports.vehicle_base}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_runs_prints_endpoints_streams_and_stops_cleanly(sig: int, tmp_path) -> None:
    ports = free_port_scheme(2)
    homes = tmp_path / "homes.csv"
    homes.write_text("47.397742,8.545594,489.4\n47.397842,8.545594,489.4\n")
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind((ports.host, ports.gcs_port(1)))
    gcs.settimeout(10.0)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen(
        [sys.executable, "-m", "sim_stub", "--homes", str(homes), "--ports",
         f"{ports.vehicle_base}:{ports.gcs_base}", "--seed", "5"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
    )  # fmt: skip
    try:
        assert p.stdout is not None
        head = p.stdout.readline()
        assert head.startswith("sim_stub: 2 vehicle(s), ports custom, profile full")
        lines = [p.stdout.readline().strip() for _ in range(2)]
        assert lines[1] == (
            f"vehicle 1: sysid 2 compid 1, binds udp 127.0.0.1:{ports.vehicle_port(1)} -> GCS "
            f"udpin://127.0.0.1:{ports.gcs_port(1)}, home 47.3978420,8.5455940,489.40; "
            f"estimator px4-sih; dynamics 100 Hz"
        )
        # vehicle 1 streams MAVLink to its GCS port
        m = mav.MAVLink(None, 255, 190)
        data, _ = gcs.recvfrom(2048)
        msg = m.parse_buffer(data)[0]
        assert msg.get_srcSystem() == 2
        p.send_signal(sig)
        out, err = p.communicate(timeout=10)
        assert p.returncode == 0, err
        assert "sim_stub: stopping" in out and "Traceback" not in err
    finally:
        if p.poll() is None:
            p.kill()
        gcs.close()


def test_the_gcs_link_serves_ground_truth_on_request(tmp_path) -> None:
    """``python -m sim_stub`` runs PX4's second link (here --gcs-link-base/--gcs-link-port on
    free ports instead of 18570+i → 14550): an observer there gets HEARTBEATs and, when it asks
    (SET_MESSAGE_INTERVAL 115), HIL_STATE_QUATERNION: the vehicle's true position."""
    ports = free_port_scheme(2)  # vehicle side + the GCS link's bind port
    obs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    obs.bind((ports.host, ports.gcs_port(0)))  # where the GCS link sends (as 14550)
    obs.settimeout(10.0)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen(
        [sys.executable, "-m", "sim_stub", "--count", "1", "--ports",
         f"{ports.vehicle_base}:{ports.gcs_base + 1}", "--gcs-link-base",
         str(ports.vehicle_base + 1), "--gcs-link-port", str(ports.gcs_port(0))],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
    )  # fmt: skip
    m = mav.MAVLink(None, 254, 190)
    try:
        assert p.stdout is not None
        p.stdout.readline()
        line = p.stdout.readline()
        assert f"GCS link udp {ports.vehicle_base + 1} -> {ports.gcs_port(0)}" in line
        msgs: list = []

        def until(pred, what: str):
            for _ in range(2000):
                data, addr = obs.recvfrom(4096)
                for msg in m.parse_buffer(data) or []:
                    msgs.append(msg)
                    if pred(msg):
                        return msg, addr
            raise AssertionError(f"no {what}")

        _, addr = until(lambda x: x.get_type() == "HEARTBEAT", "HEARTBEAT on the GCS link")
        assert addr[1] == ports.vehicle_base + 1
        obs.sendto(mav.MAVLink_command_long_message(1, 1, 511, 0, 115, 50000, 0, 0, 0, 0, 0)
                   .pack(m), addr)
        ack, _ = until(lambda x: x.get_type() == "COMMAND_ACK" and x.command == 511, "ACK")
        assert ack.result == 0 and ack.target_system == 254
        truth, _ = until(lambda x: x.get_type() == "HIL_STATE_QUATERNION", "ground truth")
        assert truth.time_usec == 0
        assert truth.lat == pytest.approx(473977420, abs=2) and truth.alt == pytest.approx(
            489400, abs=5)  # on the ground at the default home, mm AMSL
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=10)
        assert p.returncode == 0 and "Traceback" not in err
    finally:
        if p.poll() is None:
            p.kill()
        obs.close()


def test_mock_fleet_custom_ports_say_what_becomes_of_the_gcs_link(tmp_path) -> None:
    """``vtube-fleet mock-fleet --gcs-port/--vehicle-port`` (audit of issue 9): a GCS link
    asked for without ``--gcs-link-base`` is one error line; with it, the GCS link runs on
    those ports (HEARTBEATs from N+i to ``--gcs-link-port``); without either, stderr says
    there is none instead of starting none silently."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    mission = str(ROOT / "configs" / "px4_sitl_3.toml")
    cmd = [sys.executable, "-m", "vtube_fleet", "mock-fleet", mission, "--count", "1"]
    ports = free_port_scheme(2)  # [0]: API link, [1]: the GCS link's bind port
    custom = ["--gcs-port", str(ports.gcs_base), "--vehicle-port", str(ports.vehicle_base)]
    refused = subprocess.run([*cmd, *custom, "--gcs-link", "full"], capture_output=True,
                             text=True, timeout=30, cwd=ROOT, env=env)
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.splitlines() == [
        "error: --gcs-link full with --gcs-port/--vehicle-port: give --gcs-link-base N too "
        "(vehicle i's GCS link binds N+i; PX4: 18570), or --gcs-link off"]

    obs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    obs.bind((ports.host, ports.gcs_port(1)))  # where the GCS link sends (as 14550)
    obs.settimeout(10.0)
    m = mav.MAVLink(None, 254, 190)
    runs = {"with": ["--gcs-link-base", str(ports.vehicle_base + 1), "--gcs-link-port",
                     str(ports.gcs_port(1))], "without": []}
    try:
        for name, extra in runs.items():
            p = subprocess.Popen([*cmd, *custom, "--boot-time-scale", "0.3", *extra],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 cwd=ROOT, env=env)
            try:
                assert p.stdout is not None
                p.stdout.readline()
                assert p.stdout.readline().strip() == ports.endpoint(0)
                if name == "with":
                    for _ in range(200):
                        data, addr = obs.recvfrom(4096)
                        if any(x.get_type() == "HEARTBEAT" for x in m.parse_buffer(data) or []):
                            break
                    else:
                        raise AssertionError("no HEARTBEAT on the GCS link")
                    assert addr[1] == ports.vehicle_base + 1
                p.send_signal(signal.SIGINT)
                _, err = p.communicate(timeout=10)
                assert p.returncode == 0 and "Traceback" not in err, err
                said = "no GCS link (custom ports: --gcs-link-base N gives one" in err
                assert said == (name == "without"), err
            finally:
                if p.poll() is None:
                    p.kill()
    finally:
        obs.close()
