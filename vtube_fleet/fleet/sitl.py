"""A SITL fleet in one command: one simulator process per mission slot (``vtube-fleet sitl``,
``run --sitl``; docs/sitl.md).

The launcher is generic: an :class:`InstanceCommand` says how to start instance i (an argv
and environment template with placeholders, the ports it uses); :func:`px4_command` is the
one for PX4 SITL (SIH by default), and the tests use one that starts ``python -m sim_stub``
processes where PX4 is not installed.

:func:`sitl_fleet` (an async context manager) does the whole life cycle:

1. refuse ports that are taken (another SITL fleet, a ``run`` still bound): the instance's
   own ports are probed, and the ground-station side of each API link is bound at once by a
   :class:`~vtube_fleet.link.probe.HeartbeatListener` before anything starts (so that no
   HEARTBEAT is missed);
2. start instance i in its own empty working directory ``OUT/instance-I`` with the
   ``PX4_HOME_*`` of slot i (:func:`~vtube_fleet.fleet.launch.sitl_homes`), its stdout and
   stderr in ``OUT/instance-I.log``, in a process group of its own (so that Ctrl-C in the
   terminal reaches the launcher only, which stops the instances in order) that is sent
   SIGTERM if the launcher itself dies (Linux ``PR_SET_PDEATHSIG``);
3. wait until every instance answers (its first autopilot HEARTBEAT on API port
   ``api_port + i``), or refuse: an instance that exits first or stays silent for
   ``answer_timeout_s`` is named with its log file;
4. on exit, whatever the path (error, cancellation, a second Ctrl-C), stop every instance:
   SIGTERM to its process group, SIGKILL after ``stop_grace_s``, and SIGKILL to the group
   again once its leader is gone (whatever it left behind); then wait until no live member of
   the group is left (a SIGKILLed process dies when the kernel next schedules it, not when
   ``kill`` returns). :meth:`SitlFleet.kill_now` is the synchronous last resort for a caller
   whose event loop died.

Instance i flies slot i on ``udpin://127.0.0.1:{api_port + i}`` (PX4: 14540+i, system id i+1).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import os
import shlex
import shutil
import signal
import string
import sys
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vtube_fleet.artifacts import write_json_atomic
from vtube_fleet.config.mission import Mission
from vtube_fleet.errors import UserError
from vtube_fleet.fleet.launch import sitl_homes, slot_count
from vtube_fleet.link.endpoints import PX4_SITL_API_PORT, PX4_SITL_MAX_INSTANCES
from vtube_fleet.link.probe import HeartbeatListener, taken_ports

__all__ = [
    "DEFAULT_ANSWER_TIMEOUT_S",
    "DEFAULT_PX4_MODEL",
    "DEFAULT_STOP_GRACE_S",
    "PLACEHOLDERS",
    "PX4_BIND_PORTS",
    "InstanceCommand",
    "SitlError",
    "SitlFleet",
    "SitlInstance",
    "command_template",
    "instance_lines",
    "px4_command",
    "sitl_fleet",
]

#: PX4's SITL model by default: the SIH quadrotor (no Gazebo), as in the captures.
DEFAULT_PX4_MODEL = "sihsim_quadx"
#: Seconds every instance has to send its first HEARTBEAT (PX4 SIH: ~1.4 s after launch on an
#: idle machine; many instances on 2 cores take longer).
DEFAULT_ANSWER_TIMEOUT_S = 60.0
#: Seconds between SIGTERM and SIGKILL when the instances are stopped (PX4 exits within ~1 s).
DEFAULT_STOP_GRACE_S = 5.0
#: The ports PX4 SITL instance i binds itself, as bases (+i): its API link (14580+i, which
#: sends to 14540+i) and its GCS link (18570+i, which sends to 14550).
PX4_BIND_PORTS = (14580, 18570)

#: The placeholders of a command template, and what they become for instance i.
PLACEHOLDERS: dict[str, str] = {
    "instance": "the instance number i (slot i)",
    "sysid": "i + 1 (PX4's system id of instance i)",
    "home_lat": "PX4_HOME_LAT of slot i (deg)",
    "home_lon": "PX4_HOME_LON of slot i (deg)",
    "home_alt": "PX4_HOME_ALT of slot i (m AMSL)",
    "api_port": "the ground-station port of its API link: api_port_base + i",
    "api_port_base": "the API port of instance 0 (PX4: 14540)",
    "vehicle_port": "the first port it binds: vehicle_port_base + i",
    "vehicle_port_base": "the first port instance 0 binds (PX4: 14580)",
    "workdir": "its own working directory (absolute)",
}


class SitlError(UserError):
    """A SITL fleet that cannot be started: a missing binary, ports taken, an instance that
    never answered (exit code 2)."""


@dataclass(frozen=True)
class InstanceCommand:
    """How to start SITL instance i: ``argv`` and ``env`` (templates: :data:`PLACEHOLDERS`
    in ``{…}``, ``str.format`` syntax), run in its working directory with ``PX4_HOME_LAT``,
    ``PX4_HOME_LON`` and ``PX4_HOME_ALT`` of slot i set too. ``api_port_base`` + i is the
    ground-station side of its API link (what the fleet binds: ``udpin``), ``bind_ports`` the
    bases (+i) of the ports it binds itself (probed before anything starts). ``name``: what
    the messages call it (``PX4 SITL``)."""

    argv: tuple[str, ...]
    env: Mapping[str, str] = field(default_factory=dict)
    api_port_base: int = PX4_SITL_API_PORT
    bind_ports: tuple[int, ...] = PX4_BIND_PORTS
    name: str = "SITL"
    option: str = "--command"

    def __post_init__(self) -> None:
        if not self.argv:
            raise SitlError(f"{self.option}: an empty command")
        for text in (*self.argv, *self.env.values()):
            for _, key, _, _ in string.Formatter().parse(text):
                if key is not None and key not in PLACEHOLDERS:
                    raise SitlError(
                        f"{self.option}: unknown placeholder {{{key}}} in {text!r} (known: "
                        + ", ".join(f"{{{k}}}" for k in PLACEHOLDERS) + "; {{ }} for braces)")
        self.values(0, {"PX4_HOME_LAT": "0", "PX4_HOME_LON": "0", "PX4_HOME_ALT": "0"},
                    Path("."))  # a bad format spec fails here, before anything starts

    def ports(self, i: int) -> list[int]:
        """Instance i's ports: its API port (the fleet's side), then the ones it binds."""
        return [self.api_port_base + i, *(b + i for b in self.bind_ports)]

    def values(self, i: int, home: Mapping[str, str], workdir: Path) -> dict[str, Any]:
        """The placeholders' values for instance ``i``."""
        vals: dict[str, Any] = {
            "instance": i, "sysid": i + 1, "home_lat": home["PX4_HOME_LAT"],
            "home_lon": home["PX4_HOME_LON"], "home_alt": home["PX4_HOME_ALT"],
            "api_port": self.api_port_base + i, "api_port_base": self.api_port_base,
            "vehicle_port": (self.bind_ports[0] + i) if self.bind_ports else "",
            "vehicle_port_base": self.bind_ports[0] if self.bind_ports else "",
            "workdir": str(workdir)}
        try:
            for text in (*self.argv, *self.env.values()):
                text.format(**vals)
        except (ValueError, IndexError, KeyError) as exc:
            raise SitlError(f"{self.option}: bad template: {exc}") from None
        return vals

    def render(self, i: int, home: Mapping[str, str], workdir: Path
               ) -> tuple[list[str], dict[str, str]]:
        """(argv, extra environment) of instance ``i``."""
        vals = self.values(i, home, workdir)
        env = {**home, **{k: v.format(**vals) for k, v in self.env.items()}}
        return [a.format(**vals) for a in self.argv], env


def px4_command(px4: str | os.PathLike[str], model: str = DEFAULT_PX4_MODEL) -> InstanceCommand:
    """PX4 SITL: ``px4 -i I -d ETC`` in the instance's working directory, ``ETC`` the
    ``etc`` folder of the PX4 build (beside the binary's ``bin``), ``PX4_SIM_MODEL`` =
    ``model`` (``PX4_SIMULATOR=sihsim`` for the SIH models). Refuses a binary that does not
    exist, is not executable, or has no ``etc`` beside it."""
    path = Path(px4).expanduser()
    what = f"--px4 {px4}"
    if not path.exists():
        raise SitlError(f"{what}: no such file (give PX4's SITL binary, e.g. "
                        f"PX4-Autopilot/build/px4_sitl_default/bin/px4)")
    if path.is_dir() or not os.access(path, os.X_OK):
        raise SitlError(f"{what}: not an executable file (give PX4's SITL binary, e.g. "
                        f"PX4-Autopilot/build/px4_sitl_default/bin/px4)")
    binary = path.resolve()
    etc = binary.parent.parent / "etc"
    if not (etc / "init.d-posix").is_dir():
        raise SitlError(f"{what}: no PX4 startup files at {etc}/init.d-posix (the px4 of a "
                        f"PX4 SITL build has its etc/ folder beside its bin/)")
    if not model or any(c.isspace() for c in model):
        raise SitlError(f"--model: a PX4 SITL model name like {DEFAULT_PX4_MODEL}, got "
                        f"{model!r}")
    env = {"PX4_SIM_MODEL": model}
    if model.startswith("sihsim"):
        env["PX4_SIMULATOR"] = "sihsim"
    return InstanceCommand((str(binary), "-i", "{instance}", "-d", str(etc)), env,
                           PX4_SITL_API_PORT, PX4_BIND_PORTS, "PX4 SITL", "--px4")


def command_template(text: str, *, api_port_base: int | None = None,
                     vehicle_port_base: int | None = None,
                     option: str = "--command") -> InstanceCommand:
    """Any other simulator: ``text`` split like a shell would (no shell runs it), its first
    word a program on PATH or a file. Its API port base defaults to PX4's 14540, the port it
    binds to PX4's 14580."""
    try:
        argv = tuple(shlex.split(text))
    except ValueError as exc:
        raise SitlError(f"{option}: {exc}: {text!r}") from None
    if not argv:
        raise SitlError(f"{option}: an empty command")
    if "{" not in argv[0] and shutil.which(argv[0]) is None:
        raise SitlError(f"{option}: {argv[0]!r}: no such program (not a file, not on PATH)")
    api = PX4_SITL_API_PORT if api_port_base is None else api_port_base
    veh = PX4_BIND_PORTS[0] if vehicle_port_base is None else vehicle_port_base
    return InstanceCommand(argv, {}, api, (veh,), "SITL", option)


# ----------------------------------------------------------------------------------------------
def _pdeathsig() -> Callable[[], None] | None:
    """A ``preexec_fn`` that has the child sent SIGTERM when the launcher dies (Linux), or
    None elsewhere. The libc function is looked up here, in the parent: the child only calls
    it."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # pragma: no cover - a libc without prctl
        return None
    pr_set_pdeathsig, sigterm = 1, int(signal.SIGTERM)

    def preexec() -> None:
        prctl(pr_set_pdeathsig, sigterm, 0, 0, 0)

    return preexec


def _killpg(pid: int, sig: signal.Signals) -> bool:
    """Send ``sig`` to the process group ``pid``; False if the group is gone."""
    try:
        os.killpg(pid, sig)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:  # pragma: no cover - a group id now someone else's
        return False


#: Seconds :meth:`SitlFleet.stop` waits for the SIGKILLed members of a group to die.
GROUP_DEATH_TIMEOUT_S = 5.0


def _live_group_members(pgids: set[int]) -> list[int]:
    """The pids of processes, zombies excepted, whose process group is one of ``pgids`` (from
    /proc; empty where there is no /proc)."""
    live = []
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if fields[0] != "Z" and int(fields[2]) in pgids:
            live.append(int(entry.name))
    return live


def _last_line(path: Path, limit: int = 160) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, os.path.getsize(path) - 4096))
            lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines()]
    except OSError:
        return ""
    text = next((ln for ln in reversed(lines) if ln), "")
    return text if len(text) <= limit else text[: limit - 1] + "…"


@dataclass
class SitlInstance:
    """One started instance: its number (= slot), command, files, process and answer."""

    index: int
    argv: list[str]
    env: dict[str, str]
    workdir: Path
    log_path: Path
    api_port: int
    process: asyncio.subprocess.Process | None = None
    sysid: int | None = None  # from its first HEARTBEAT
    answered_s: float | None = None  # seconds from start to that HEARTBEAT

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def endpoint(self, host: str) -> str:
        return f"udpin://{host}:{self.api_port}"

    def as_dict(self, host: str) -> dict[str, Any]:
        return {"instance": self.index, "slot": self.index, "pid": self.pid,
                "endpoint": self.endpoint(host), "sysid": self.sysid,
                "answered_s": self.answered_s, "workdir": str(self.workdir),
                "log": str(self.log_path), "argv": self.argv,
                "env": {k: v for k, v in self.env.items()}}


class SitlFleet:
    """One SITL instance per slot of ``mission`` (the first ``count``), started by ``command``
    under ``out_dir`` (see the module docstring; use :func:`sitl_fleet`)."""

    def __init__(self, mission: Mission, command: InstanceCommand, out_dir: Path, *,
                 count: int | None = None, host: str = "127.0.0.1",
                 answer_timeout_s: float = DEFAULT_ANSWER_TIMEOUT_S,
                 stop_grace_s: float = DEFAULT_STOP_GRACE_S) -> None:
        self.mission = mission
        self.command = command
        self.count = slot_count(mission, count)
        if command.api_port_base == PX4_SITL_API_PORT and self.count > PX4_SITL_MAX_INSTANCES:
            raise SitlError(f"{self.count} instances: PX4's port scheme holds at most "
                            f"{PX4_SITL_MAX_INSTANCES} (14540+40 is instance 0's own port)")
        top = max(command.ports(self.count - 1))
        if top > 65535:
            raise SitlError(f"{self.count} instances from port {command.api_port_base}: "
                            f"instance {self.count - 1} would need port {top} > 65535")
        seen: dict[int, int] = {}
        for i in range(self.count):
            for port in command.ports(i):
                if port in seen:
                    raise SitlError(f"{command.option}: instances {seen[port]} and {i} would "
                                    f"both use port {port} (API ports from "
                                    f"{command.api_port_base}, bound ports from "
                                    f"{', '.join(map(str, command.bind_ports))}: keep them "
                                    f"{self.count} apart)")
                seen[port] = i
        self.out_dir = Path(out_dir)
        self.host = host
        self.answer_timeout_s = answer_timeout_s
        self.stop_grace_s = stop_grace_s
        self.instances: list[SitlInstance] = []
        self._listeners: list[HeartbeatListener] = []
        self._t0 = time.monotonic()

    # -- what the fleet flies ------------------------------------------------------------------
    @property
    def endpoints(self) -> list[str]:
        return [inst.endpoint(self.host) for inst in self.instances]

    @property
    def sysids(self) -> list[int | None]:
        """Each instance's system id as it answered (PX4: i + 1)."""
        return [inst.sysid for inst in self.instances]

    def describe(self) -> dict[str, Any]:
        """What ``instances.json`` holds: the command, the instances."""
        return {"name": self.command.name, "mission": self.mission.source,
                "count": self.count, "instances": [i.as_dict(self.host)
                                                   for i in self.instances]}

    # -- life cycle ----------------------------------------------------------------------------
    async def start(self) -> None:
        """Probe the ports, bind the API ports, create the working directories and start
        every instance (module docstring, steps 1-2). On an error the ones started are
        stopped before it is raised."""
        homes = sitl_homes(self.mission, self.count)
        cmd = self.command
        own = {p: i for i in range(self.count) for p in cmd.ports(i)[1:]}
        taken = taken_ports(own)
        try:
            for i in range(self.count):
                port = cmd.api_port_base + i
                try:
                    self._listeners.append(await HeartbeatListener.open(self.host, port))
                except OSError as exc:
                    taken[port] = ("in use" if exc.errno == errno.EADDRINUSE
                                   else str(exc.strerror))
            if taken:
                raise SitlError(self._taken_text(taken))
            self.out_dir.mkdir(parents=True, exist_ok=True)
            preexec = _pdeathsig()
            self._t0 = time.monotonic()
            for i in range(self.count):
                workdir = (self.out_dir / f"instance-{i}").resolve()
                if workdir.is_dir():  # every start is a fresh instance: PX4's defaults
                    shutil.rmtree(workdir)
                workdir.mkdir(parents=True)
                argv, extra = cmd.render(i, homes[i], workdir)
                inst = SitlInstance(i, argv, extra, workdir, self.out_dir / f"instance-{i}.log",
                                    cmd.api_port_base + i)
                self.instances.append(inst)
                with open(inst.log_path, "wb") as log:
                    try:
                        inst.process = await asyncio.create_subprocess_exec(
                            *argv, cwd=workdir, env={**os.environ, **extra},
                            stdin=asyncio.subprocess.DEVNULL, stdout=log,
                            stderr=asyncio.subprocess.STDOUT, start_new_session=True,
                            preexec_fn=preexec)
                    except OSError as exc:
                        raise SitlError(f"{cmd.option}: cannot start {cmd.name} instance {i} "
                                        f"({argv[0]}): {exc.strerror or exc}") from None
        except BaseException:
            await self.stop()
            raise

    def _taken_text(self, taken: Mapping[int, str]) -> str:
        cmd = self.command
        parts = []
        for port, why in sorted(taken.items()):
            for i in range(self.count):
                ports = cmd.ports(i)
                if port in ports:
                    role = ("the ground-station side of its API link" if port == ports[0]
                            else "it binds it")
                    parts.append(f"{port} of instance {i} ({role}): {why}")
                    break
        return (f"UDP port{'s' if len(parts) > 1 else ''} taken: " + "; ".join(parts)
                + f" (another {cmd.name} fleet or a run still up? stop it, or fly it with "
                f"`run --endpoints`); nothing started")

    async def wait_answers(self) -> None:
        """Wait until every instance has sent its first HEARTBEAT (module docstring, step 3);
        refuse an instance that exits first or stays silent. The API ports are released
        afterwards, for the fleet's links."""
        try:
            problems = [p for p in await asyncio.gather(*(
                self._answer(inst, lst) for inst, lst in
                zip(self.instances, self._listeners, strict=True))) if p]
            if len(problems) == 1:
                raise SitlError(f"{self.command.name} instance {problems[0]}")
            if problems:
                raise SitlError(f"{len(problems)} of {self.count} {self.command.name} "
                                f"instances did not start: instance " + "; instance ".join(
                                    problems))
        finally:
            listeners, self._listeners = self._listeners, []
            for lst in listeners:  # (the ports are free once this returns)
                await lst.aclose()

    async def _answer(self, inst: SitlInstance, listener: HeartbeatListener) -> str | None:
        """None once ``inst`` answered, else why not (after its number)."""
        assert inst.process is not None
        exited = asyncio.ensure_future(inst.process.wait())
        remaining = self.answer_timeout_s - (time.monotonic() - self._t0)
        try:
            done, _ = await asyncio.wait({listener.heard, exited}, timeout=max(remaining, 0.0),
                                         return_when=asyncio.FIRST_COMPLETED)
        finally:
            if not exited.done():
                exited.cancel()
        where = f"udp {self.host}:{inst.api_port}"
        if listener.heard in done:
            inst.sysid = listener.heard.result()
            inst.answered_s = time.monotonic() - self._t0
            return None
        last = _last_line(inst.log_path)
        tail = f"; its last line: {last!r}" if last else " (empty)"
        if exited in done:
            return (f"{inst.index} exited with code {inst.process.returncode} before it "
                    f"answered on {where}; its log: {inst.log_path}{tail}")
        return (f"{inst.index} did not answer within {self.answer_timeout_s:g} s (no MAVLink "
                f"HEARTBEAT on {where}, {listener.datagrams} datagrams); its log: "
                f"{inst.log_path}{tail}")

    def _close_listeners(self) -> None:
        for lst in self._listeners:
            lst.close()
        self._listeners = []

    async def watch(self) -> SitlInstance:
        """Return the first instance that exits (the ``sitl`` command reports it)."""
        waits = {asyncio.ensure_future(i.process.wait()): i for i in self.instances
                 if i.process is not None}
        if not waits:
            raise SitlError("no instance running")
        try:
            done, _ = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                if not w.done():
                    w.cancel()
        return waits[next(iter(done))]

    async def stop(self) -> None:
        """Stop every instance (module docstring, step 4). A cancellation while waiting (a
        second Ctrl-C) skips the grace: SIGKILL at once, then the cancellation goes on."""
        self._close_listeners()
        procs = [i.process for i in self.instances if i.process is not None]
        for p in procs:
            if p.returncode is None:
                _killpg(p.pid, signal.SIGTERM)
        cancelled: BaseException | None = None
        try:
            await asyncio.wait_for(asyncio.gather(*(p.wait() for p in procs)),
                                   self.stop_grace_s)
        except TimeoutError:
            pass
        except asyncio.CancelledError as exc:
            cancelled = exc
        for p in procs:  # the stragglers, and whatever a leader left in its group
            _killpg(p.pid, signal.SIGKILL)
        for p in procs:
            if p.returncode is None:
                with contextlib.suppress(asyncio.CancelledError):
                    await p.wait()
        pgids = {p.pid for p in procs}
        deadline = time.monotonic() + GROUP_DEATH_TIMEOUT_S
        try:
            while _live_group_members(pgids) and time.monotonic() < deadline:
                await asyncio.sleep(0.02)  # no event tells a grandparent that they died
        except asyncio.CancelledError as exc:
            cancelled = cancelled or exc
        if cancelled is not None:
            raise cancelled

    def kill_now(self) -> None:
        """SIGKILL every instance's process group now (synchronous; a no-op for groups that
        are gone): for a caller whose event loop stopped before :meth:`stop` ran."""
        self._close_listeners()
        for inst in self.instances:
            if inst.pid is not None:
                _killpg(inst.pid, signal.SIGKILL)


@contextlib.asynccontextmanager
async def sitl_fleet(mission: Mission, command: InstanceCommand, out_dir: str | os.PathLike[str],
                     *, count: int | None = None, on_start: Callable[[SitlFleet], None]
                     | None = None, holder: list[SitlFleet] | None = None,
                     **kwargs: Any) -> AsyncIterator[SitlFleet]:
    """Start a :class:`SitlFleet`, wait until every instance answers, yield it, stop it on
    every exit path. ``on_start(fleet)``: called once the processes run (before they
    answer: the command prints their pids and logs); ``holder``: the fleet is appended to it
    at once (for :meth:`SitlFleet.kill_now` by a caller outside the event loop); ``kwargs``:
    :class:`SitlFleet`'s."""
    fleet = SitlFleet(mission, command, Path(out_dir), count=count, **kwargs)
    if holder is not None:
        holder.append(fleet)
    await fleet.start()
    try:
        _write_instances(fleet)
        if on_start is not None:
            on_start(fleet)
        await fleet.wait_answers()
        _write_instances(fleet)
        yield fleet
    finally:
        await fleet.stop()


def _write_instances(fleet: SitlFleet) -> None:
    write_json_atomic(fleet.out_dir / "instances.json", fleet.describe())


def instance_lines(fleet: SitlFleet, *, answered: bool = False) -> Sequence[str]:
    """One line per instance for the terminal: pid, slot, home and log (``answered``: its
    endpoint and system id instead)."""
    out = []
    for inst in fleet.instances:
        if answered:
            out.append(f"  instance {inst.index}: {inst.endpoint(fleet.host)} (sysid "
                       f"{inst.sysid}, answered after {inst.answered_s or 0:.1f} s)")
        else:
            home = " ".join(f"{k}={v}" for k, v in inst.env.items() if k.startswith("PX4_HOME"))
            out.append(f"  instance {inst.index}: pid {inst.pid}, slot {inst.index} ({home}), "
                       f"log {inst.log_path}")
    return out
