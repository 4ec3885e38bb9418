"""A mock fleet split over several OS processes (``--processes N``), for fleets one process
cannot hold at 100 Hz (about 500 lite vehicles per core, docs/sim_stub.md).

:class:`ProcessFleet` takes :class:`~sim_stub.fleet.MockFleet`'s arguments, gives process k the
contiguous block of instances ``k*count//N .. (k+1)*count//N - 1`` (a ``MockFleet(first=…)``
with its own scheduler) and keeps the port scheme, so vehicle i has the same ports, sysid,
home and faults as in one process. The estimate errors of each block come from their own
generator (independent of the other blocks; ``estimator_shared`` draws stay common).

Each child is ``python -c 'from sim_stub.processes import child_main; …'`` in its own session
(a terminal's Ctrl-C reaches only the parent, which stops the children in order). The parent
sends the child's configuration as one JSON line on its stdin, the child answers one JSON line
on stdout (``{"ok": true, "describe": [...]}`` or ``{"ok": false, "error": "..."}``) and then
runs until its stdin reaches end of file: the parent closing it (:meth:`ProcessFleet.stop`), or
the parent dying in any way (the kernel closes its end), so no child outlives its parent.
SIGTERM/SIGINT stop a child too. A child that dies while the fleet runs is reported by
:meth:`ProcessFleet.serve` (:class:`MockProcessError`).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import os
import signal
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .errors import SimStubError
from .faults import Faults
from .fleet import MockFleet, check_fleet_args, grid_homes
from .ports import PortScheme, resolve_port_scheme
from .vehicle import DEFAULT_HOME, validate_home

__all__ = ["MockProcessError", "ProcessFleet", "child_main", "split_blocks"]

Home = tuple[float, float, float]

#: the child's entry point (``python -c``)
_CHILD = "from sim_stub.processes import child_main; raise SystemExit(child_main())"
_STOP_TIMEOUT_S = 10.0  # a child gets this long to stop after EOF, then SIGTERM, then SIGKILL


class MockProcessError(SimStubError):
    """A mock process failed to start or died while the fleet ran (exit status 1)."""

    exit_code: int = 1


def split_blocks(count: int, processes: int) -> list[range]:
    """The instances of each process: ``processes`` contiguous blocks, sizes differing by <= 1."""
    if not 1 <= processes <= count:
        raise SimStubError(f"processes must be in 1..{count} (the vehicle count), got "
                           f"{processes}")
    return [range(k * count // processes, (k + 1) * count // processes)
            for k in range(processes)]


class ProcessFleet:
    """``count`` mock vehicles (instances 0..count-1) in ``processes`` child processes.

    Arguments as :class:`~sim_stub.fleet.MockFleet` (no ``clock``: each child uses its own
    event loop's). ``python``: the interpreter of the children (default this one). Exposes
    ``count``, ``ports``, ``endpoints`` (vehicle i's GCS URL, as ``MockFleet``), ``blocks``
    (the instances of each process), ``pids``, :meth:`describe`; the vehicles themselves (true
    state, ``kill``) live in the children and are not reachable from here.

    ``async with ProcessFleet(1000, processes=4, port_scheme="wide") as fleet:`` starts every
    child (they boot in parallel) and waits until each has bound its vehicles; on any failure
    the children already started are stopped before the error propagates.
    """

    def __init__(
        self,
        count: int | None = None,
        *,
        processes: int,
        homes: Sequence[Home] | None = None,
        home: Home = DEFAULT_HOME,
        spacing_m: float | None = None,
        port_scheme: str | PortScheme = "px4",
        faults: Faults | Sequence[Faults | None] | Mapping[int, Faults] | None = None,
        params: dict[str, float] | None = None,
        seed: int = 0,
        profile: str = "full",
        boot_time_scale: float = 1.0,
        tick_hz: float = 100.0,
        estimator: str = "px4-sih",
        estimator_shared: bool = False,
        gcs_link: str = "lite",
        sysids: Sequence[int] | None = None,
        python: str = sys.executable,
        ready_timeout_s: float = 120.0,
    ) -> None:
        count, homes = check_fleet_args(count, homes, profile)
        self.blocks = split_blocks(count, processes)
        if sysids is None:
            sysids = [i % 254 + 1 for i in range(count)]
        sysids = [int(s) for s in sysids]
        if len(sysids) != count or not all(1 <= s <= 254 for s in sysids):
            raise SimStubError(f"sysids: {count} ids in 1..254 expected, got {sysids!r}")
        self.ports = resolve_port_scheme(port_scheme)
        self.ports.check(count)
        if homes is None:
            homes = (grid_homes(home, count, spacing_m) if spacing_m is not None
                     else [validate_home(home)] * count)
        all_faults = MockFleet._resolve_faults(faults, count)
        self.count = count
        self.processes = processes
        self.endpoints: list[str] = [self.ports.endpoint(i) for i in range(count)]
        self.python = python
        self.ready_timeout_s = ready_timeout_s
        common = dict(port_scheme=dataclasses.asdict(self.ports), params=params, seed=seed,
                      profile=profile, boot_time_scale=boot_time_scale, tick_hz=tick_hz,
                      estimator=estimator, estimator_shared=estimator_shared,
                      gcs_link=gcs_link)
        self._configs = [
            dict(common, count=len(b), first=b.start,
                 homes=[list(h) for h in homes[b.start:b.stop]],
                 faults=[dataclasses.asdict(f) for f in all_faults[b.start:b.stop]],
                 sysids=sysids[b.start:b.stop])
            for b in self.blocks
        ]
        self._procs: list[asyncio.subprocess.Process] = []
        self._pids: list[int] = []
        self._watchers: list[asyncio.Task[None]] = []
        self._describe: list[str] = []
        self._running = False
        self._stopping = False
        self.failure: str | None = None
        self._failed: asyncio.Event | None = None

    @property
    def pids(self) -> list[int]:
        """Process ids of the children of the last :meth:`start` (also once stopped)."""
        return list(self._pids)

    def _what(self, k: int) -> str:
        b = self.blocks[k]
        return f"mock process {k} (vehicles {b.start}..{b.stop - 1})"

    async def __aenter__(self) -> ProcessFleet:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Start every child and wait until each has bound its vehicles."""
        if self._running or self._procs:
            return
        self._failed = asyncio.Event()
        self._stopping = False
        self.failure = None
        self._pids = []
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        try:
            for cfg in self._configs:
                proc = await asyncio.create_subprocess_exec(
                    self.python, "-c", _CHILD, stdin=asyncio.subprocess.PIPE,
                    stdout=asyncio.subprocess.PIPE, env=env, start_new_session=True,
                    limit=1 << 24)
                self._procs.append(proc)
                self._pids.append(proc.pid)
                assert proc.stdin is not None
                proc.stdin.write(json.dumps(cfg).encode() + b"\n")
            for proc in self._procs:
                assert proc.stdin is not None
                try:
                    await proc.stdin.drain()
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the child died at once: its exit status is reported below
            try:
                replies = await asyncio.wait_for(
                    asyncio.gather(*(self._reply(k, p) for k, p in enumerate(self._procs))),
                    self.ready_timeout_s)
            except TimeoutError:
                raise MockProcessError(
                    f"{self.processes} mock process(es) not ready within "
                    f"{self.ready_timeout_s:g} s") from None
        except BaseException:
            await self._terminate()
            raise
        self._describe = [line for r in replies for line in r]
        self._watchers = [asyncio.ensure_future(self._watch(k, p))
                          for k, p in enumerate(self._procs)]
        self._running = True

    async def _reply(self, k: int, proc: asyncio.subprocess.Process) -> list[str]:
        assert proc.stdout is not None
        line = await proc.stdout.readline()
        if not line:
            rc = await proc.wait()
            raise MockProcessError(f"{self._what(k)} exited with status {rc} before it was "
                                   f"ready")
        try:
            reply = json.loads(line)
        except json.JSONDecodeError:
            raise MockProcessError(f"{self._what(k)}: unexpected reply {line[:200]!r}") from None
        if not reply.get("ok"):
            err = SimStubError(f"{self._what(k)}: {reply.get('error')}")
            raise err
        return [str(x) for x in reply.get("describe", [])]

    async def _watch(self, k: int, proc: asyncio.subprocess.Process) -> None:
        rc = await proc.wait()
        if not self._stopping and self.failure is None:
            self.failure = f"{self._what(k)} exited with status {rc} while the fleet ran"
            assert self._failed is not None
            self._failed.set()

    async def serve(self, stop: asyncio.Event) -> None:
        """Run until ``stop`` is set; raise :class:`MockProcessError` if a child dies first."""
        assert self._failed is not None, "start() first"
        waits = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(self._failed.wait())]
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()
        if self.failure is not None and not stop.is_set():
            raise MockProcessError(self.failure)

    async def stop(self) -> None:
        """Stop every child: close its stdin (it stops its vehicles and exits), then SIGTERM
        and SIGKILL for any that has not exited within 10 s. Idempotent."""
        if not self._procs:
            return
        self._running = False
        await self._terminate()

    async def _terminate(self) -> None:
        self._stopping = True
        procs, self._procs = self._procs, []
        try:
            for p in procs:
                if p.stdin is not None:
                    with contextlib.suppress(Exception):
                        p.stdin.close()
            waits = [asyncio.ensure_future(p.wait()) for p in procs]
            if waits:
                await asyncio.wait(waits, timeout=_STOP_TIMEOUT_S)
            for sig in (signal.SIGTERM, signal.SIGKILL):
                alive = [p for p in procs if p.returncode is None]
                if not alive:
                    break
                for p in alive:
                    with contextlib.suppress(ProcessLookupError):
                        p.send_signal(sig)
                await asyncio.wait([asyncio.ensure_future(p.wait()) for p in alive], timeout=5.0)
        except BaseException:  # cancelled while stopping: no orphans, kill outright
            for p in procs:
                if p.returncode is None:
                    with contextlib.suppress(ProcessLookupError):
                        p.kill()
            raise
        finally:
            for w in self._watchers:
                w.cancel()
            self._watchers = []

    def describe(self) -> list[str]:
        """One line per vehicle (as :meth:`MockFleet.describe`), from the children."""
        return list(self._describe)


# --------------------------------------------------------------------------------------------
# the child
# --------------------------------------------------------------------------------------------
def _fleet_from_config(cfg: dict[str, Any]) -> MockFleet:
    ports = dict(cfg.pop("port_scheme"))
    ports["gcs_link_remotes"] = tuple(tuple(r) for r in ports["gcs_link_remotes"])
    cfg["port_scheme"] = PortScheme(**ports)
    cfg["homes"] = [tuple(h) for h in cfg["homes"]]
    cfg["faults"] = [Faults(**f) for f in cfg["faults"]]
    return MockFleet(**cfg)


def _say(reply: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(reply) + "\n")
    sys.stdout.flush()


async def _child_run(fleet: MockFleet) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    fd = sys.stdin.fileno()

    def on_stdin() -> None:
        try:
            data = os.read(fd, 65536)
        except OSError:
            data = b""
        if not data:  # the parent closed our stdin or died
            loop.remove_reader(fd)
            stop.set()

    try:
        await fleet.start()
    except SimStubError as exc:
        _say({"ok": False, "error": str(exc)})
        return
    try:
        loop.add_reader(fd, on_stdin)
        _say({"ok": True, "describe": fleet.describe()})
        await stop.wait()
    finally:
        await fleet.stop()


def child_main() -> int:
    """Entry point of one child process (see the module docstring)."""
    line = sys.stdin.buffer.readline()
    if not line:
        return 0
    try:
        fleet = _fleet_from_config(json.loads(line))
    except (SimStubError, TypeError, ValueError, KeyError) as exc:
        _say({"ok": False, "error": str(exc)})
        return 2
    try:
        asyncio.run(_child_run(fleet))
    except BrokenPipeError:  # the parent went away while we answered
        return 0
    except KeyboardInterrupt:
        return 0
    return 0
