"""Live viewing without setting up a viewer first: the rerun web viewer served to a browser, or
the native viewer spawned — both child processes of the rerun CLI that ships with rerun-sdk.

* :class:`WebViewerServer` runs ``rerun --serve-web``: the web viewer's page (HTTP, ``web_port``)
  and a gRPC server (``grpc_port``, by default ``web_port + 1``) that the recorder streams to
  and the page reads from, both bound to ``bind`` (loopback by default; ``0.0.0.0`` serves every
  interface, and the page's origin is then allowed to read the gRPC port: CORS). The server
  keeps what it was sent (up to ``memory_limit``), so a browser opened late sees the run from
  its start. It is stopped when the recording closes. A separate process on purpose: the rerun
  SDK's own web server (``rerun.serve_web_viewer``) always listens on every interface.
* :func:`spawn_viewer` starts the native viewer (``rerun --port P --bind 127.0.0.1``), detached:
  it stays open after the run, like ``rerun.spawn``; it reuses a viewer already listening there.

Neither is on the control loop's path: the recorder sends from its own thread, and a viewer or
browser that never connects, or goes away, is the server's business (the file is written all
the same; ``docs/recording.md``).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO
from urllib.parse import quote

from vtube_fleet.recording.api import RecordingError

__all__ = [
    "DEFAULT_BIND",
    "DEFAULT_WEB_PORT",
    "VIEWER_PORT",
    "WebViewerServer",
    "rerun_executable",
    "spawn_viewer",
]

#: ``--rerun-serve-web`` without a port: the web viewer's page here, its gRPC data on port + 1.
DEFAULT_WEB_PORT = 9090
#: ``--rerun-bind`` default: this machine only.
DEFAULT_BIND = "127.0.0.1"
#: The native viewer's gRPC port (the rerun default; ``--rerun-connect`` without an address).
VIEWER_PORT = 9876
_ANY = ("0.0.0.0", "::", "")


def rerun_executable() -> str:
    """The rerun CLI binary shipped by the rerun-sdk wheel (not a wrapper script: its process
    id is the viewer's), else ``rerun`` on PATH. :class:`RecordingError` if there is none."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found is None:
        raise RecordingError("no rerun viewer binary found (the rerun-sdk package ships one)")
    return found


def _port_free(bind: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # as the server binds (SO_REUSEADDR): a port whose last connections linger in
        # TIME_WAIT is free, one a process listens on is not
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind or "0.0.0.0", port))
        except OSError:
            return False
    return True


def _answers(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _local_host(bind: str) -> str:
    """Where this machine reaches a server bound to ``bind``."""
    if bind in _ANY:
        return "127.0.0.1"
    return bind


#: The web viewer server runs this much nicer than the run: on a busy computer the control loop
#: gets the CPU first, the live view waits (``os.nice``).
SERVER_NICE = 10


def _server_child() -> None:  # pragma: no cover - runs in the child before exec
    """The server ends with us even when we are killed outright (Linux PR_SET_PDEATHSIG), runs
    in its own session (a Ctrl-C in the terminal reaches us, and we stop it after the flush)
    and at a lower priority (:data:`SERVER_NICE`)."""
    os.setsid()
    with contextlib.suppress(OSError):
        os.nice(SERVER_NICE)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _tail(log: IO[bytes], lines: int = 3) -> str:
    """The last lines of a child's output (its reason to exit), without colour codes."""
    import re

    log.flush()
    log.seek(0)
    text = re.sub(r"\x1b\[[0-9;]*m", "", log.read().decode(errors="replace"))
    useful = [ln.strip() for ln in text.splitlines()
              if ln.strip() and ("ERROR" in ln or "Error" in ln or "error" in ln)]
    return " | ".join((useful or [ln.strip() for ln in text.splitlines() if ln.strip()])
                      [-lines:]) or "no output"


def _env() -> dict[str, str]:
    # RERUN_APP_ONLY: the CLI skips its first-run analytics notice (as rerun.spawn sets it)
    return {**os.environ, "RERUN_APP_ONLY": "true"}


@dataclass
class WebViewerServer:
    """``rerun --serve-web`` as a child process (module docstring). :meth:`start` raises
    :class:`RecordingError` (one line: the port, the bind address, the cause)."""

    bind: str = DEFAULT_BIND
    web_port: int = DEFAULT_WEB_PORT
    grpc_port: int | None = None
    memory_limit: str = "1GiB"
    start_timeout_s: float = 20.0
    proc: subprocess.Popen[bytes] | None = field(default=None, init=False)
    _log: IO[bytes] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.grpc_port is None:
            self.grpc_port = self.web_port + 1
        for name, port in (("page", self.web_port), ("data", self.grpc_port)):
            if not 1 <= int(port) <= 65535:
                raise RecordingError(f"--rerun-serve-web: the {name} port {port} is outside "
                                     f"1..65535")

    @property
    def public_host(self) -> str:
        """The host name a browser uses: the bind address, or this machine's name when the
        server listens on every interface."""
        if self.bind in _ANY:
            return socket.gethostname()
        return self.bind if ":" not in self.bind else f"[{self.bind}]"

    @property
    def grpc_url(self) -> str:
        """Where the recorder streams to (this machine)."""
        host = _local_host(self.bind)
        host = f"[{host}]" if ":" in host else host
        return f"rerun+http://{host}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The page to open in a browser (it reads the data from the gRPC port)."""
        data = f"rerun+http://{self.public_host}:{self.grpc_port}/proxy"
        return f"http://{self.public_host}:{self.web_port}/?url={quote(data, safe='')}"

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def start(self) -> None:
        """Check the ports, start the server, wait until both ports answer."""
        assert self.grpc_port is not None
        for what, port in (("page", self.web_port), ("data (gRPC)", self.grpc_port)):
            if not _port_free(self.bind, port):
                raise RecordingError(
                    f"--rerun-serve-web: the {what} port {port} is in use on {self.bind or '*'} "
                    f"(another viewer or server? choose another with --rerun-serve-web PORT: "
                    f"the page on PORT, the data on PORT + 1)")
        args = [rerun_executable(), "--serve-web", "--bind", self.bind or "0.0.0.0",
                "--port", str(self.grpc_port), "--web-viewer-port", str(self.web_port),
                "--server-memory-limit", self.memory_limit]
        if self.bind in _ANY or not self.bind.startswith("127."):
            # the page is served from this origin and reads the gRPC port (another origin)
            args += ["--cors-allow-origin", f"http://*:{self.web_port}"]
        self._log = tempfile.TemporaryFile()
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=self._log,
                                     stderr=subprocess.STDOUT, env=_env(),
                                     preexec_fn=_server_child)
        host = _local_host(self.bind)
        deadline = time.monotonic() + self.start_timeout_s
        while not (_answers(host, self.web_port) and _answers(host, self.grpc_port)):
            if self.proc.poll() is not None:
                why = _tail(self._log)
                self.stop()
                raise RecordingError(f"--rerun-serve-web: the rerun web viewer server exited "
                                     f"at start: {why}")
            if time.monotonic() > deadline:
                self.stop()
                raise RecordingError(f"--rerun-serve-web: the rerun web viewer server did not "
                                     f"listen on {self.bind}:{self.web_port} within "
                                     f"{self.start_timeout_s:g} s")
            time.sleep(0.05)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the server (SIGTERM, then SIGKILL). Idempotent."""
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=timeout_s)
        if self._log is not None:
            self._log.close()
            self._log = None


@dataclass(frozen=True)
class SpawnedViewer:
    """A native viewer to stream to: its gRPC URL; ``pid`` when we started it (None: one was
    already listening); ``problem``: why none could be started (then ``url`` is None)."""

    url: str | None
    pid: int | None = None
    problem: str = ""


def spawn_viewer(port: int = VIEWER_PORT, *, start_timeout_s: float = 15.0) -> SpawnedViewer:
    """Start the native rerun viewer on ``127.0.0.1:port`` (detached: it outlives the run),
    or use the one already listening there. Never raises: a viewer that cannot start (no
    display, no graphics driver) is reported in ``problem``."""
    url = f"rerun+http://127.0.0.1:{int(port)}/proxy"
    if _answers("127.0.0.1", port):
        return SpawnedViewer(url)
    if not sys.platform.startswith(("darwin", "win")) and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return SpawnedViewer(None, problem="no display (neither DISPLAY nor WAYLAND_DISPLAY "
                                           "is set)")
    try:
        exe = rerun_executable()
        # detached, output discarded: the viewer stays open after the run, and a long-lived
        # viewer's log (e.g. map tiles it cannot fetch offline) must not fill a file of ours
        proc = subprocess.Popen(
            [exe, "--port", str(int(port)), "--bind", "127.0.0.1", "--expect-data-soon"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env=_env(), start_new_session=True)
    except (OSError, RecordingError) as exc:
        return SpawnedViewer(None, problem=f"cannot start the rerun viewer: {exc}")
    deadline = time.monotonic() + start_timeout_s
    while not _answers("127.0.0.1", port):
        code = proc.poll()
        if code is not None:
            return SpawnedViewer(None, problem=f"it exited at start (code {code}; run `rerun` "
                                               f"by hand to see why: a graphics driver?)")
        if time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            return SpawnedViewer(None, problem=f"it did not listen on port {port} within "
                                               f"{start_timeout_s:g} s")
        time.sleep(0.05)
    return SpawnedViewer(url, pid=proc.pid)
