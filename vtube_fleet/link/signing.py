"""MAVLink 2 signing for the ``mavlink`` backend: key files, the persistent monotonic timestamp,
and provisioning a vehicle with SETUP_SIGNING (``vtube-fleet sign-setup``). docs/security.md.

* **Key file** (:func:`load_key`): exactly 32 raw bytes, or 64 hex digits (one line). Refused
  if it is readable or writable by group or others (mode must be 0600 or stricter: anybody who
  reads it can fly the fleet), if it is not a regular file, or if the key is all zeros (PX4
  reads an all-zero key as "signing off"). Named by the mission (``signing_key_file``), never
  written into it; ``{slot}`` in the name gives per-vehicle keys.
* **Timestamp** (:class:`TimestampStore`): MAVLink signing timestamps are 48-bit counts of
  10 µs since 2015-01-01 00:00 UTC; PX4 rejects a packet whose timestamp is not newer than the
  last one it accepted from the same stream (sysid, compid, link id), so ours must never go
  backwards, across restarts too, even if the wall clock does. The store keeps a *reserved
  mark* in ``<key file>.timestamp`` (decimal, mode 0600, updated under ``flock``): every
  timestamp we send is below the mark on disk, and a restart starts at or above it. The mark
  is moved :data:`LEASE` (1 s) ahead when we reach it, so the file is written (and synced)
  about once a second, not per packet; a crash at any point costs at most 1 s of counter. The
  lease is short on purpose: a restarted link starts at most ~1 s ahead of the wall clock,
  well inside the one minute by which a receiver may trail a new stream (MAVLink's rule for
  a stream it has not seen), so the vehicle's own signed packets are not refused as old.
* **Provisioning** (:func:`sign_setup`): per vehicle, connect accepting unsigned traffic (the
  vehicle may have no key yet), refuse if it is armed (PX4 ≥ 1.18 ignores SETUP_SIGNING while
  armed), send SETUP_SIGNING (key, our timestamp), then require signed traffic and wait for a
  HEARTBEAT signed with the key: the proof that the vehicle took it. There is no ACK.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import secrets
import stat
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vtube_fleet.errors import UserError

__all__ = [
    "EPOCH_2015_UNIX_S",
    "KEY_BYTES",
    "LEASE",
    "LINK_UNSIGNED_ALLOWED",
    "PX4_UNSIGNED_ALLOWED",
    "LinkSigning",
    "SignSetupResult",
    "SigningError",
    "TimestampStore",
    "fleet_signing",
    "generate_key",
    "load_key",
    "mission_key_path",
    "sign_setup",
    "signing_timestamp",
    "slot_signing",
]

KEY_BYTES = 32
#: 2015-01-01 00:00:00 UTC: the origin of MAVLink signing timestamps (10 µs units).
EPOCH_2015_UNIX_S = 1420070400
#: How far (10 µs units: 1 s) the reserved mark on disk runs ahead of what we sent.
LEASE = 100_000
_MAX_TS = (1 << 48) - 1
#: What PX4 ≥ 1.18 accepts unsigned once it has a key: HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE,
#: COLLISION (mavlink_sign_control.cpp).
PX4_UNSIGNED_ALLOWED: frozenset[int] = frozenset({0, 109, 246, 247})
#: What *we* accept unsigned from a vehicle: PX4's list without HEARTBEAT, which drives our
#: view of armed state and flight mode (PX4 signs its own heartbeats once it has the key).
LINK_UNSIGNED_ALLOWED: frozenset[int] = PX4_UNSIGNED_ALLOWED - {0}


class SigningError(UserError):
    """A key file or timestamp store that cannot be used, or a vehicle that refused the key."""


def signing_timestamp(unix_s: float | None = None) -> int:
    """The signing timestamp of ``unix_s`` (default now): 10 µs units since 2015-01-01."""
    t = time.time() if unix_s is None else unix_s
    return max(0, int((t - EPOCH_2015_UNIX_S) * 100_000))


def _check_private(path: Path, what: str) -> os.stat_result:
    try:
        st = path.stat()
    except FileNotFoundError:
        raise SigningError(f"{what} {path}: no such file") from None
    except OSError as exc:
        raise SigningError(f"{what} {path}: cannot read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise SigningError(f"{what} {path}: not a regular file")
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise SigningError(f"{what} {path}: mode {mode:04o} lets other users read or change it; "
                           f"chmod 600 {path}")
    return st


def load_key(path: str | os.PathLike[str]) -> bytes:
    """The 32-byte key in ``path`` (raw, or 64 hex digits); :class:`SigningError` otherwise."""
    p = Path(path)
    _check_private(p, "signing key file")
    data = p.read_bytes()
    key: bytes | None = data if len(data) == KEY_BYTES else None
    if key is None:
        text = data.strip()
        if len(text) == 2 * KEY_BYTES:
            with contextlib.suppress(ValueError):
                key = bytes.fromhex(text.decode("ascii", "replace"))
    if key is None:
        raise SigningError(f"signing key file {p}: expected {KEY_BYTES} raw bytes or "
                           f"{2 * KEY_BYTES} hex digits, got {len(data)} bytes")
    if not any(key):
        raise SigningError(f"signing key file {p}: the key is all zeros (PX4 reads that as "
                           f"'signing off')")
    return key


def generate_key(path: str | os.PathLike[str]) -> bytes:
    """Write a new random key (32 raw bytes, mode 0600) to ``path``, which must not exist."""
    p = Path(path)
    key = secrets.token_bytes(KEY_BYTES)
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise SigningError(f"signing key file {p}: exists already (never overwritten)") from None
    except OSError as exc:
        raise SigningError(f"signing key file {p}: cannot create: {exc.strerror or exc}") from None
    with os.fdopen(fd, "wb") as fh:
        fh.write(key)
        fh.flush()
        os.fsync(fh.fileno())
    return key


class TimestampStore:
    """The persistent, never decreasing signing timestamp of one key (see the module doc).

    ``wall``: the Unix clock (tests pass one that jumps back). Shared by every link of the key
    in a process; processes sharing the file merge their marks (the larger wins).
    """

    def __init__(self, path: str | os.PathLike[str], *, lease: int = LEASE,
                 wall: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self.lease = lease
        self._wall = wall
        self._reserved = -1  # below this every timestamp is safe to send
        self.writes = 0

    def _locked(self, fn: Callable[[int], int | None]) -> int:
        """Run ``fn(mark on disk)`` under an exclusive lock; write what it returns."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            raise SigningError(f"signing timestamp file {self.path}: cannot open: "
                               f"{exc.strerror or exc} (it lives next to the key file, whose "
                               f"directory must be writable)") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            mode = stat.S_IMODE(os.fstat(fd).st_mode)
            if mode & 0o077:
                raise SigningError(f"signing timestamp file {self.path}: mode {mode:04o} lets "
                                   f"other users change it; chmod 600 {self.path}")
            raw = os.pread(fd, 64, 0).strip()
            try:
                mark = int(raw) if raw else 0
            except ValueError:
                raise SigningError(
                    f"signing timestamp file {self.path}: not a number ({raw[:20]!r}); it must "
                    f"never go backwards: write a value above the last one sent (e.g. the "
                    f"current time's) instead of deleting it") from None
            new = fn(mark)
            if new is not None and new != mark:
                text = f"{new}\n".encode()
                os.pwrite(fd, text.ljust(21), 0)
                os.ftruncate(fd, 21)
                os.fsync(fd)
                self.writes += 1
            return mark if new is None else new
        finally:
            os.close(fd)

    def start(self) -> int:
        """The first timestamp to send: max(now, the mark on disk); reserves a lease."""
        first = 0

        def fn(mark: int) -> int:
            nonlocal first
            first = max(signing_timestamp(self._wall()), mark, self._reserved)
            return first + self.lease

        self._reserved = self._locked(fn)
        return first

    def ensure(self, timestamp: int) -> None:
        """Make ``timestamp`` safe to send (below the mark on disk); cheap unless it moves."""
        if timestamp < self._reserved:
            return
        if timestamp >= _MAX_TS:
            raise SigningError(f"signing timestamp {timestamp} exhausted the 48-bit range")
        self._reserved = self._locked(lambda mark: max(mark, timestamp + self.lease))

    def now(self) -> int:
        """The wall clock as a signing timestamp (the link never sends less than this)."""
        return signing_timestamp(self._wall())


@dataclass
class LinkSigning:
    """How one link signs: the key, the shared timestamp store, our link id, and whether
    incoming traffic must be signed (False only while provisioning a vehicle)."""

    key: bytes
    store: TimestampStore
    link_id: int = 0
    require_signed: bool = True
    key_file: str = ""

    def __post_init__(self) -> None:
        if len(self.key) != KEY_BYTES or not any(self.key):
            raise SigningError(f"a signing key is {KEY_BYTES} bytes, not all zero")
        if not 0 <= self.link_id <= 255:
            raise SigningError(f"signing link id must be 0..255, got {self.link_id}")


def mission_key_path(mission: Any, slot: int) -> Path | None:
    """The key file of ``slot`` (``signing_key_file`` relative to the mission file, ``{slot}``
    replaced), or None when the mission does not sign."""
    name = mission.config.signing_key_file
    if not name:
        return None
    p = Path(name.replace("{slot}", str(slot)))
    if not p.is_absolute():
        p = Path(mission.source).resolve().parent / p
    return p


def fleet_signing(mission: Any, count: int | None = None, *,
                  wall: Callable[[], float] = time.time) -> list[LinkSigning | None]:
    """One :class:`LinkSigning` per slot 0..count-1 (all None if the mission does not sign);
    slots that share a key file share one :class:`TimestampStore`. Keys are loaded (and
    checked) now, before anything connects."""
    n = mission.count if count is None else count
    stores: dict[Path, tuple[bytes, TimestampStore]] = {}
    out: list[LinkSigning | None] = []
    for slot in range(n):
        path = mission_key_path(mission, slot)
        if path is None:
            out.append(None)
            continue
        if path not in stores:
            stores[path] = (load_key(path), TimestampStore(f"{path}.timestamp", wall=wall))
        key, store = stores[path]
        out.append(LinkSigning(key, store, key_file=str(path)))
    return out


def slot_signing(mission: Any, slot: int, *,
                 wall: Callable[[], float] = time.time) -> LinkSigning | None:
    """The :class:`LinkSigning` of one slot only (an agent reads only its own vehicle's key
    file), None if the mission does not sign."""
    path = mission_key_path(mission, slot)
    if path is None:
        return None
    return LinkSigning(load_key(path), TimestampStore(f"{path}.timestamp", wall=wall),
                       key_file=str(path))


@dataclass(frozen=True)
class SignSetupResult:
    """One vehicle provisioned: its endpoint, system id and key file."""

    endpoint: str
    sysid: int
    key_file: str
    timestamp: int


async def _provision(endpoint: str, sysid: int | None, signing: LinkSigning,
                     timeout_s: float, current: LinkSigning | None) -> SignSetupResult:
    from vtube_fleet.link.base import LinkTimeout
    from vtube_fleet.link.mavlink import MavlinkLink

    session = current or signing
    link = MavlinkLink(endpoint, sysid, signing=LinkSigning(
        session.key, session.store, session.link_id, require_signed=False,
        key_file=session.key_file))
    try:
        await link.open()  # no stream requests: a vehicle holding another key would drop them
        try:
            await link.wait_until(lambda s: s.last_heartbeat_s is not None, timeout_s,
                                  "first HEARTBEAT")
        except LinkTimeout:
            raise SigningError(f"{link.name}: no HEARTBEAT within {timeout_s:g} s: is the "
                               f"vehicle up at {endpoint}?") from None
        st = link.state
        if st.armed:
            raise SigningError(
                f"{link.name}: vehicle {st.sysid} is armed: PX4 refuses SETUP_SIGNING while "
                f"armed; land and disarm it first")
        ts = await link.provision_signing(signing, timeout_s=timeout_s)
        return SignSetupResult(endpoint, int(link.state.sysid or 0), signing.key_file, ts)
    finally:
        await link.close()


async def sign_setup(mission: Any, endpoints: Sequence[str], *,
                     sysids: Sequence[int | None] | None = None, timeout_s: float = 10.0,
                     current_key_file: str | None = None,
                     wall: Callable[[], float] = time.time) -> list[SignSetupResult]:
    """Provision every vehicle of ``endpoints`` (slot i = endpoint i) with its mission key, one
    after another (SETUP_SIGNING, verified by a signed HEARTBEAT). ``current_key_file``: the
    key the vehicles hold now (rotation: PX4 takes a new key only signed with the current one).
    Raises :class:`SigningError` on the first vehicle that is armed or does not take it."""
    if not mission.config.signing_key_file:
        raise SigningError(f"{mission.source}: [mission].signing_key_file is not set: the "
                           f"mission does not sign, there is no key to provision")
    if len(endpoints) > mission.count:
        raise SigningError(f"{len(endpoints)} endpoints but the mission has only "
                           f"{mission.count} slots (endpoint i is slot i)")
    plan = fleet_signing(mission, len(endpoints), wall=wall)
    current = None
    if current_key_file is not None:
        current = LinkSigning(load_key(current_key_file),
                              TimestampStore(f"{current_key_file}.timestamp", wall=wall),
                              key_file=current_key_file)
    ids = list(sysids) if sysids is not None else [None] * len(endpoints)
    out = []
    for ep, sid, sg in zip(endpoints, ids, plan, strict=True):
        assert sg is not None
        out.append(await _provision(ep, sid, sg, timeout_s, current))
    return out


def run_sign_setup(mission_path: str | os.PathLike[str], endpoints: Sequence[str], *,
                   timeout_s: float = 10.0, generate: bool = False,
                   current_key_file: str | None = None) -> list[SignSetupResult]:
    """``vtube-fleet sign-setup``: load the mission, optionally create missing key files
    (``generate``), provision every vehicle (:func:`sign_setup`)."""
    from vtube_fleet.config.mission import load_mission

    mission = load_mission(mission_path)
    if generate:
        for slot in range(len(endpoints)):
            p = mission_key_path(mission, slot)
            if p is not None and not p.exists():
                generate_key(p)
    return asyncio.run(sign_setup(mission, endpoints, timeout_s=timeout_s,
                                  current_key_file=current_key_file))
