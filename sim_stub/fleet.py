"""A fleet of mock PX4 vehicles in one event loop, sharing one :class:`Scheduler` tick."""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from .errors import SimStubError
from .faults import Faults
from .geo import reproject
from .ports import PortScheme, resolve_port_scheme
from .scheduler import Scheduler
from .telemetry import PROFILES
from .vehicle import DEFAULT_HOME, MockVehicle, validate_home

__all__ = ["MockFleet", "grid_homes", "load_homes"]

Home = tuple[float, float, float]


def grid_homes(home: Home, count: int, spacing_m: float) -> list[Home]:
    """``count`` start points on a square grid around ``home``, ``spacing_m`` apart (row-major,
    rows to the north, columns to the east, centred on ``home``)."""
    if count < 0:
        raise SimStubError(f"vehicle count must be >= 0, got {count}")
    if not (math.isfinite(spacing_m) and spacing_m > 0.0):
        raise SimStubError(f"grid spacing must be > 0 m, got {spacing_m}")
    lat0, lon0, alt0 = validate_home(home)
    cols = max(1, math.ceil(math.sqrt(count)))
    rows = max(1, math.ceil(count / cols))
    out = []
    for i in range(count):
        r, c = divmod(i, cols)
        north = (r - (rows - 1) / 2.0) * spacing_m
        east = (c - (cols - 1) / 2.0) * spacing_m
        lat, lon = reproject(lat0, lon0, north, east)
        out.append((lat, lon, alt0))
    return out


def load_homes(path: str | Path) -> list[Home]:
    """Read per-vehicle homes: JSON (a list of [lat, lon, alt]) or text/CSV lines ``lat,lon,alt``
    (``#`` comments and blank lines ignored). Raises :class:`SimStubError` naming file and line."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise SimStubError(f"{p}: cannot read homes file: {exc.strerror or exc}") from None
    homes: list[Home] = []
    stripped = text.lstrip()
    if stripped.startswith("["):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SimStubError(f"{p}: invalid JSON at line {exc.lineno}: {exc.msg}") from None
        for k, item in enumerate(data):
            try:
                homes.append(validate_home(tuple(item)))  # type: ignore[arg-type]
            except (SimStubError, TypeError) as exc:
                raise SimStubError(f"{p}: entry {k}: {exc}") from None
        return homes
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [x for x in line.replace(";", ",").replace(" ", ",").split(",") if x]
        if len(parts) != 3:
            raise SimStubError(f"{p}:{lineno}: expected 'lat,lon,alt', got {line!r}")
        try:
            values = tuple(float(x) for x in parts)
        except ValueError:
            raise SimStubError(f"{p}:{lineno}: not a number in {line!r}") from None
        try:
            homes.append(validate_home(values))  # type: ignore[arg-type]
        except SimStubError as exc:
            raise SimStubError(f"{p}:{lineno}: {exc}") from None
    return homes


def check_fleet_args(count: int | None, homes: Sequence[Home] | None, profile: str
                     ) -> tuple[int, list[Home] | None]:
    """(vehicle count, validated homes) from ``count`` and/or ``homes``; one line on error
    (MockFleet and ProcessFleet alike)."""
    if homes is not None:
        homes = [validate_home(h) for h in homes]
        if count is None:
            count = len(homes)
        elif count != len(homes):
            raise SimStubError(f"count={count} but {len(homes)} homes were given")
    if count is None:
        raise SimStubError("give count or homes")
    if count < 1:
        raise SimStubError(f"vehicle count must be >= 1, got {count}")
    if profile not in PROFILES:
        raise SimStubError(f"profile must be one of {PROFILES}, got {profile!r}")
    return count, homes


class MockFleet:
    """``count`` mock PX4 SITL vehicles (instances 0..count-1) in this event loop.

    ``homes``: one (lat, lon, alt) per vehicle (its start point = local origin); if None every
    vehicle starts at ``home`` (like several SIH instances without PX4_HOME_*), or on a grid
    ``spacing_m`` apart if given. ``port_scheme``: ``"px4"`` (default; at most 40 vehicles),
    ``"wide"`` or a :class:`~sim_stub.ports.PortScheme`. ``faults``: one
    :class:`~sim_stub.faults.Faults` for all, a sequence (one per vehicle) or a mapping
    index → Faults. ``profile``: ``"full"`` or ``"lite"`` stream set. ``boot_time_scale``,
    ``estimator`` (``"px4-sih"`` default, ``"rtk"``, ``"ideal"``), ``estimator_shared`` and
    ``gcs_link`` (``"lite"``, ``"full"``, ``"off"``): see :class:`~sim_stub.vehicle.MockVehicle`.

    Vehicle i has sysid i+1 like PX4; MAVLink sysids are 8-bit, so from the 255th vehicle on they
    repeat (i % 254 + 1): each vehicle keeps its own UDP port pair, so a GCS that keeps one link
    per endpoint still tells them apart (one MAVSDK instance for all would not). ``sysids``
    sets them explicitly (one per vehicle, 1..254; repeats allowed, as on separate networks).

    ``first``: the first PX4 instance (vehicles ``first``..``first+count-1``: ports, default
    sysids, link randomness); :class:`~sim_stub.processes.ProcessFleet` gives each of its
    processes one block. Every list (``homes``, ``faults``, ``sysids``, ``vehicles``,
    ``endpoints``) and :meth:`kill` count from 0 within this fleet. ``signing``: MAVLink 2
    signing of every vehicle, or one setting per vehicle (``False``, ``True`` = waits for
    SETUP_SIGNING, or the 32-byte key it already holds, as after ``vtube-fleet sign-setup``).

    ``async with MockFleet(count=3) as fleet:`` starts all vehicles on one scheduler;
    ``fleet.endpoints[i]`` is the MAVSDK URL the GCS binds for vehicle i, ``fleet.vehicles[i]``
    the vehicle (true state, counters), ``fleet.kill(i, how)`` kills one.
    """

    def __init__(
        self,
        count: int | None = None,
        *,
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
        clock: Callable[[], float] | None = None,
        estimator: str = "px4-sih",
        estimator_shared: bool = False,
        gcs_link: str = "lite",
        sysids: Sequence[int] | None = None,
        first: int = 0,
        signing: bool | bytes | Sequence[bool | bytes] = False,
    ) -> None:
        count, homes = check_fleet_args(count, homes, profile)
        if first < 0:
            raise SimStubError(f"first instance must be >= 0, got {first}")
        if sysids is None:
            sysids = [(first + i) % 254 + 1 for i in range(count)]
        sysids = list(sysids)
        if len(sysids) != count or not all(1 <= int(s) <= 254 for s in sysids):
            raise SimStubError(f"sysids: {count} ids in 1..254 expected, got {sysids!r}")
        self.ports = resolve_port_scheme(port_scheme)
        self.ports.check(first + count)
        if homes is None:
            homes = (
                grid_homes(home, count, spacing_m)
                if spacing_m is not None
                else [validate_home(home)] * count
            )
        self.homes: list[Home] = list(homes)
        self.count = count
        self.first = first
        self.seed = seed
        self._faults = self._resolve_faults(faults, count)
        if isinstance(signing, (bool, bytes)):
            signing = [signing] * count
        signing = list(signing)
        if len(signing) != count:
            raise SimStubError(f"signing: one setting per vehicle expected ({count}), "
                               f"got {len(signing)}")
        self.scheduler = Scheduler(count, tick_hz=tick_hz, clock=clock, seed=seed, stream=first)
        self.vehicles: list[MockVehicle] = [
            MockVehicle(
                first + i,
                home=self.homes[i],
                ports=self.ports,
                faults=self._faults[i],
                params=params,
                seed=seed,
                clock=clock,
                profile=profile,
                boot_time_scale=boot_time_scale,
                scheduler=self.scheduler,
                sysid=sysids[i],
                estimator=estimator,
                estimator_shared=estimator_shared,
                gcs_link=gcs_link,
                signing=signing[i],
            )
            for i in range(count)
        ]
        self.endpoints: list[str] = [self.ports.endpoint(first + i) for i in range(count)]
        self._running = False

    @staticmethod
    def _resolve_faults(
        faults: Faults | Sequence[Faults | None] | Mapping[int, Faults] | None, count: int
    ) -> list[Faults]:
        if faults is None:
            return [Faults()] * count
        if isinstance(faults, Faults):
            return [faults] * count
        if isinstance(faults, Mapping):
            bad = [k for k in faults if not 0 <= k < count]
            if bad:
                raise SimStubError(f"faults given for vehicle(s) {bad}, fleet has 0..{count - 1}")
            return [faults.get(i) or Faults() for i in range(count)]
        seq = list(faults)
        if len(seq) != count:
            raise SimStubError(f"{len(seq)} fault entries for {count} vehicles")
        return [f or Faults() for f in seq]

    async def __aenter__(self) -> MockFleet:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Start the scheduler and bind every vehicle (all boot at the same moment)."""
        if self._running:
            return
        self.scheduler.start()
        started: list[MockVehicle] = []
        try:
            for v in self.vehicles:
                await v.start()
                started.append(v)
        except BaseException:
            for v in started:
                await v.stop()
            self.scheduler.stop()
            raise
        self._running = True

    async def stop(self) -> None:
        """Stop every vehicle and the scheduler."""
        if not self._running:
            return
        self._running = False
        for v in self.vehicles:
            await v.stop()
        self.scheduler.stop()

    async def serve(self, stop: asyncio.Event) -> None:
        """Run until ``stop`` is set (as :meth:`ProcessFleet.serve`, whose children can die)."""
        await stop.wait()

    def kill(self, i: int, how: str = "silent") -> None:
        """Kill vehicle ``i``: ``"silent"`` (link dies) or ``"freeze"`` (hovers, ignores all)."""
        if not 0 <= i < self.count:
            raise SimStubError(f"no vehicle {i}: fleet has 0..{self.count - 1}")
        self.vehicles[i].kill(how)

    def describe(self) -> list[str]:
        """One line per vehicle: instance, sysid, bind address, GCS endpoint, home, estimator,
        the dynamics' tick rate."""
        hz = self.scheduler.tick_hz
        lines = []
        for v in self.vehicles:
            lat, lon, alt = v.origin
            gl = v.gcs_link
            gcs = "" if gl is None else (f"; GCS link udp {gl.bind_address[1]} -> "
                                         f"{gl.remote[1]}")
            lines.append(
                f"vehicle {v.instance}: sysid {v.sysid} compid 1, binds udp {v.bind_address[0]}:"
                f"{v.bind_address[1]} -> GCS {v.endpoint}, home {lat:.7f},{lon:.7f},{alt:.2f}"
                f"{gcs}; estimator {v.estimator.name}; dynamics {hz:g} Hz"
            )
        return lines
