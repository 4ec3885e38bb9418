"""The built-in mock fleet in a child process (``vtube-fleet mock-fleet``), for the tests that
kill, stop or interrupt the vehicles' host while a supervisor flies them."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from fleet_ports import free_ports

__all__ = ["ROOT", "child_env", "mock_process", "read_line", "start_run"]

ROOT = Path(__file__).resolve().parents[1]


def child_env() -> dict[str, str]:
    """The environment of a child ``python -m vtube_fleet``: this checkout first, MAVLink 2."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("MAVLINK20", "1")
    return env


def read_line(proc: subprocess.Popen[str], stream: str, pred: Callable[[str], bool],
              timeout_s: float) -> str:
    """Read lines of ``proc.<stream>`` until ``pred(line)``; fail with what was read."""
    pipe = getattr(proc, stream)
    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = pipe.readline()
        if not line:
            break
        seen.append(line.rstrip())
        if pred(line):
            return line
    raise AssertionError(f"condition not seen on {stream} (exit {proc.poll()}):\n"
                         + "\n".join(seen[-30:]))


@contextlib.contextmanager
def mock_process(mission_path: Path, count: int
                 ) -> Iterator[tuple[subprocess.Popen[str], list[str]]]:
    """``vtube-fleet mock-fleet`` in a child process on free ports: (process, endpoints).
    On exit a process still running is continued (if SIGSTOPped) and interrupted, killed if
    it does not end within 20 s."""
    ports = free_ports(count)
    proc = subprocess.Popen(
        [sys.executable, "-m", "vtube_fleet", "mock-fleet", str(mission_path), "--count",
         str(count), "--boot-time-scale", "0.3", "--gcs-port", str(ports.gcs_base),
         "--vehicle-port", str(ports.vehicle_base)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=child_env(), cwd=ROOT)
    try:
        line = read_line(proc, "stdout", lambda s: s.startswith("udpin://"), 60)
        yield proc, line.strip().split(",")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGCONT)
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def start_run(mission_path: Path, endpoints: list[str], out: Path) -> subprocess.Popen[str]:
    """``vtube-fleet run MISSION --endpoints … --out OUT`` in a child process, its stderr
    piped (read it with :func:`read_line`)."""
    return subprocess.Popen(
        [sys.executable, "-m", "vtube_fleet", "run", str(mission_path), "--endpoints",
         ",".join(endpoints), "--out", str(out)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=child_env(), cwd=ROOT)
