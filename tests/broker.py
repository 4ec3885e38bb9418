"""Start and stop a local MQTT broker process on a free loopback port (tests, bench, demos).

:class:`LocalBroker` runs **mosquitto** when it is installed (on ``PATH`` or in ``/usr/sbin``,
where Debian puts it) and otherwise falls back to **amqtt**'s broker in a Python subprocess
(``python tests/broker.py --amqtt PORT``), so the test suite also passes on a machine without
the Debian package. Readiness is checked by an MQTT CONNECT/CONNACK handshake, never by
sleeping. ``kill()`` (SIGKILL: no clean shutdown, clients see their TCP connection drop) and
``restart()`` on the same port serve the broker-loss fault tests::

    with LocalBroker() as broker:          # mosquitto on 127.0.0.1:<free port>
        bus = MqttBus(broker.url, ...)
        broker.kill(); broker.restart()

    setup = bus_setup(tmp / "bus", "demo", 4, port=free_port(), bind="127.0.0.1")
    with LocalBroker(config=setup.conf, ca_file=setup.ca_file) as broker:   # secured
        bus = MqttBus(broker.url, "demo", 0, credentials=setup.vehicle_credentials(0))

A secured broker runs mosquitto with the configuration ``vtube-fleet bus-setup`` wrote (TLS
listener, passwords, ACL) plus one line, ``user <this user>`` (mosquitto started as root
would otherwise switch to the ``mosquitto`` user, who cannot read the 0600 key files); its
readiness probe is a TLS handshake verified with the setup's CA and an (anonymous, refused)
CONNECT: any CONNACK means the broker answers.

Under ``CI=true`` (``.ci/run``, which installs mosquitto) the fallback is refused: a missing
mosquitto makes ``LocalBroker()`` and every test that needs mosquitto (:func:`require_tool`)
FAIL with a message saying so, instead of running on amqtt or being skipped — a CI without
mosquitto must not pass without the secured-bus and mission tests.

Test and benchmark infrastructure (not part of the package): production fleets use their own
broker (``--broker mqtt://HOST:PORT``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import re
import shutil
import signal
import socket
import ssl
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Literal

from vtube_fleet.errors import UserError

__all__ = [
    "BrokerError",
    "LocalBroker",
    "find_mosquitto",
    "find_tool",
    "free_port",
    "mqtt_handshake",
    "require_kind",
    "require_tool",
    "under_ci",
]

log = logging.getLogger(__name__)

BrokerKind = Literal["auto", "mosquitto", "amqtt"]


def require_kind(kind: str) -> None:
    """For a test parametrized over the broker kinds (both, always): ``"mosquitto"`` needs it
    installed (:func:`require_tool`: skipped, FAILED under CI=true)."""
    if kind == "mosquitto":
        require_tool("mosquitto", "the test with the mosquitto broker")


class BrokerError(UserError):
    """A local broker could not be started (or did not become ready in time)."""


def find_tool(name: str) -> str | None:
    """Path of an executable: ``PATH`` first, then ``/usr/sbin``, ``/usr/local/sbin`` and
    ``/usr/bin`` (Debian puts mosquitto in /usr/sbin, mosquitto_passwd in /usr/bin)."""
    found = shutil.which(name)
    if found:
        return found
    for d in ("/usr/sbin", "/usr/local/sbin", "/usr/bin"):
        p = Path(d) / name
        if p.is_file() and os.access(p, os.X_OK):
            return str(p)
    return None


def find_mosquitto() -> str | None:
    """Path of the mosquitto binary (:func:`find_tool`)."""
    return find_tool("mosquitto")


def under_ci() -> bool:
    """``CI`` is set to true (``.ci/run``; GitHub Actions and most CIs set ``CI=true``)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


#: What to install for a tool the tests need (Debian package names).
INSTALL = {"mosquitto": "apt-get install -y mosquitto",
           "mosquitto_passwd": "apt-get install -y mosquitto"}


def require_tool(name: str, what: str) -> str:
    """The path of ``name`` for a test (``what`` says which) that needs it. Missing: the test
    is skipped, but under ``CI=true`` it FAILS, saying what to install (a CI that skipped it
    would pass without testing it)."""
    path = find_tool(name)
    if path is not None:
        return path
    import pytest

    msg = (f"{what} needs {name}, which is not installed "
           f"({INSTALL.get(name, 'install it')})")
    if under_ci():
        pytest.fail(f"CI=true: {msg}; .ci/run installs it, a CI run must not skip these "
                    "tests", pytrace=False)
    pytest.skip(msg)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind to port 0 and read what the kernel chose)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


# MQTT 3.1.1 CONNECT: protocol "MQTT" level 4, clean session, keepalive 5 s, client id "probe".
_CONNECT = bytes([0x10, 17, 0, 4]) + b"MQTT" + bytes([4, 0x02, 0, 5, 0, 5]) + b"probe"
_DISCONNECT = bytes([0xE0, 0])


def mqtt_handshake(host: str, port: int, timeout_s: float = 1.0, *,
                   tls: ssl.SSLContext | None = None, any_answer: bool = False) -> bool:
    """True if an MQTT broker at ``host:port`` answers CONNECT with an accepting CONNACK
    (``any_answer``: with any CONNACK, e.g. "not authorized" from a secured broker); ``tls``:
    over TLS with this context (certificate and host name verified)."""
    try:
        with contextlib.ExitStack() as stack:
            raw = stack.enter_context(socket.create_connection((host, port), timeout=timeout_s))
            s = stack.enter_context(tls.wrap_socket(raw, server_hostname=host)) if tls else raw
            s.sendall(_CONNECT)
            ack = b""
            while len(ack) < 4:
                chunk = s.recv(4 - len(ack))
                if not chunk:
                    return False
                ack += chunk
            with contextlib.suppress(OSError):
                s.sendall(_DISCONNECT)
            return ack[0] == 0x20 and (any_answer or ack[3] == 0)
    except OSError:
        return False


def _user_name() -> str:
    import pwd

    return pwd.getpwuid(os.getuid()).pw_name


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGKILL it when the process that started it dies."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)


class LocalBroker:
    """A broker subprocess on ``host:port`` (a free port unless given).

    ``kind="auto"`` uses mosquitto if found, else amqtt; ``"mosquitto"``/``"amqtt"`` force one.
    """

    def __init__(
        self,
        *,
        kind: BrokerKind = "auto",
        host: str = "127.0.0.1",
        port: int | None = None,
        ready_timeout_s: float = 15.0,
        config: str | os.PathLike[str] | None = None,
        ca_file: str | os.PathLike[str] | None = None,
    ) -> None:
        """``config``: run mosquitto with this configuration (``vtube-fleet bus-setup``'s
        mosquitto.conf); the broker's address is its TLS listener (the first with a
        ``certfile``), or its first listener; ``ca_file``: the CA its certificate is verified
        with (readiness probe)."""
        if kind not in ("auto", "mosquitto", "amqtt"):
            raise BrokerError(f"unknown broker kind {kind!r}: use auto, mosquitto or amqtt")
        mosquitto = find_mosquitto()
        self._config_text: str | None = None
        self.tls = False
        self.plain_port: int | None = None
        if config is not None:
            kind = "mosquitto"
            self._config_text = Path(config).read_text()
            host, port, self.tls, self.plain_port = _listeners(self._config_text)
        if kind == "mosquitto" and mosquitto is None:
            raise BrokerError(
                "mosquitto not found on PATH or in /usr/sbin (apt-get install mosquitto)"
            )
        if kind == "auto" and mosquitto is None and under_ci():
            raise BrokerError(
                "CI=true: mosquitto not found on PATH or in /usr/sbin (apt-get install -y "
                "mosquitto; .ci/run installs it): the tests do not fall back to amqtt in CI"
            )
        self.kind: Literal["mosquitto", "amqtt"] = (
            "mosquitto" if kind != "amqtt" and mosquitto is not None else "amqtt"
        )
        self._mosquitto = mosquitto
        self.host = host
        self._fixed_port = port
        self.port = port if port is not None else 0
        self.ready_timeout_s = ready_timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._dir = tempfile.TemporaryDirectory(prefix="vtube-broker-")
        self._log_file: Path = Path(self._dir.name) / "broker.log"
        self._tls_probe = ssl.create_default_context(
            cafile=None if ca_file is None else str(ca_file)) if self.tls else None

    # -- properties ---------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def log_tail(self, lines: int = 20) -> str:
        """The last lines the broker wrote (for error messages)."""
        try:
            text = self._log_file.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])

    # -- lifecycle ----------------------------------------------------------------------------
    def _command(self) -> list[str]:
        if self.kind == "mosquitto" and self._config_text is not None:
            conf = Path(self._dir.name) / "mosquitto.conf"
            # stay this user: dropping privileges would also drop the parent-death signal
            # and make the 0600 key files unreadable
            conf.write_text(f"user {_user_name()}\nlog_dest stderr\n" + self._config_text)
            assert self._mosquitto is not None
            return [self._mosquitto, "-c", str(conf)]
        if self.kind == "mosquitto":
            conf = Path(self._dir.name) / "mosquitto.conf"
            conf.write_text(
                f"listener {self.port} {self.host}\n"
                "allow_anonymous true\n"
                "persistence false\n"
                # stay this user: dropping privileges would also drop the parent-death signal
                f"user {_user_name()}\n"
                # Small messages at 20 Hz: do not let Nagle hold them back.
                "set_tcp_nodelay true\n"
                "log_dest stderr\n"
                "log_type error\nlog_type warning\nlog_type notice\n"
            )
            assert self._mosquitto is not None
            return [self._mosquitto, "-c", str(conf)]
        return [
            sys.executable,
            str(Path(__file__).resolve()),
            "--amqtt",
            str(self.port),
            "--host",
            self.host,
        ]

    def _spawn(self) -> None:
        with open(self._log_file, "ab") as logf:
            self._proc = subprocess.Popen(  # noqa: S603
                self._command(),
                stdin=subprocess.DEVNULL,
                stdout=logf,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # Ctrl-C in a terminal goes to us; we stop it
                preexec_fn=_die_with_parent,  # noqa: PLW1509 - no broker outlives a killed test
            )

    def start(self, *, wait: bool = True) -> LocalBroker:
        """Launch the broker (a new free port unless one was given) and wait until it answers."""
        if self.running:
            raise BrokerError(f"broker already running on {self.url}")
        attempts = 1 if self._fixed_port is not None else 3
        for attempt in range(attempts):
            if self._fixed_port is None:
                self.port = free_port(self.host)
            self._spawn()
            if not wait:
                return self
            try:
                self.wait_ready()
                return self
            except BrokerError:
                # The free port may have been taken between probing and binding: retry.
                if attempt == attempts - 1 or self.running:
                    self.stop()
                    raise
                self.stop()
        raise AssertionError("unreachable")

    def _check_alive(self) -> None:
        if self._proc is not None and self._proc.poll() is not None:
            raise BrokerError(
                f"{self.kind} broker on {self.url} exited with code {self._proc.returncode}: "
                f"{self.log_tail(5) or '(no output)'}"
            )

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Block until an MQTT handshake succeeds; :class:`BrokerError` on exit or timeout."""
        timeout = self.ready_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        while True:
            self._check_alive()
            if mqtt_handshake(self.host, self.port, timeout_s=0.5, tls=self._tls_probe,
                              any_answer=self._config_text is not None):
                return
            if time.monotonic() > deadline:
                raise BrokerError(
                    f"{self.kind} broker on {self.url} did not answer an MQTT CONNECT within "
                    f"{timeout:.1f} s: {self.log_tail(5) or '(no output)'}"
                )
            time.sleep(0.02)  # polling interval of the readiness probe

    async def wait_ready_async(self, timeout_s: float | None = None) -> None:
        """:meth:`wait_ready` without blocking the event loop."""
        await asyncio.to_thread(self.wait_ready, timeout_s)

    def kill(self) -> None:
        """SIGKILL the broker: no goodbye to clients, their connections just drop."""
        if self._proc is None:
            return
        if self._proc.poll() is None:
            self._proc.send_signal(signal.SIGKILL)
        self._proc.wait()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Terminate the broker (SIGTERM, then SIGKILL after ``timeout_s``); idempotent."""
        if self._proc is None:
            return
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._proc = None

    def restart(self, *, wait: bool = True) -> LocalBroker:
        """Start again on the SAME port (after :meth:`kill` or :meth:`stop`)."""
        if self.running:
            raise BrokerError(f"broker still running on {self.url}; kill() or stop() it first")
        self._proc = None
        self._spawn()
        if wait:
            self.wait_ready()
        return self

    def close(self) -> None:
        self.stop()
        self._dir.cleanup()

    def __enter__(self) -> LocalBroker:
        if not self.running:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = f"pid {self.pid}" if self.running else "stopped"
        return f"LocalBroker({self.kind} {self.url}, {state})"


def _listeners(text: str) -> tuple[str, int, bool, int | None]:
    """(host, port, tls, plain port) of a mosquitto configuration: its TLS listener (the first
    followed by a ``certfile``) or else its first listener; a plain one besides it."""
    found: list[list[object]] = []  # [host, port, tls]
    for line in text.splitlines():
        m = re.match(r"\s*listener\s+(\d+)(?:\s+(\S+))?", line)
        if m:
            found.append([m.group(2) or "127.0.0.1", int(m.group(1)), False])
        elif found and re.match(r"\s*certfile\s", line):
            found[-1][2] = True
    if not found:
        raise BrokerError("the mosquitto configuration has no listener line")
    tls = [f for f in found if f[2]]
    main = tls[0] if tls else found[0]
    plain = [f for f in found if not f[2] and f is not main]
    host = "127.0.0.1" if main[0] in ("0.0.0.0", "::") else str(main[0])
    return host, int(main[1]), bool(main[2]), int(plain[0][1]) if plain else None  # type: ignore[call-overload]


# -- amqtt fallback (runs in the subprocess) ------------------------------------------------
async def _run_amqtt(host: str, port: int) -> None:
    from amqtt.broker import Broker  # imported here: optional dependency

    config = {
        "listeners": {"default": {"type": "tcp", "bind": f"{host}:{port}"}},
        "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
    }
    broker = Broker(config)
    await broker.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    await broker.shutdown()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python tests/broker.py",
        description="Run a local MQTT broker on loopback (mosquitto if installed, else amqtt).",
    )
    parser.add_argument("--amqtt", type=int, metavar="PORT", help="run amqtt's broker on PORT")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=None, help="port (default: a free one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.amqtt is not None:
        try:
            import amqtt  # noqa: F401
        except ImportError:
            print("error: amqtt is not installed (pip install amqtt)", file=sys.stderr)
            return 2
        asyncio.run(_run_amqtt(args.host, args.amqtt))
        return 0
    # SIGTERM ends the loop below like Ctrl-C, so the broker process is stopped with us
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    with LocalBroker(host=args.host, port=args.port) as broker:
        print(
            f"{broker.kind} broker at {broker.url} (pid {broker.pid}); Ctrl-C stops it", flush=True
        )
        with contextlib.suppress(KeyboardInterrupt):
            while broker.running:
                time.sleep(0.5)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
