"""The neighbour bus over an MQTT broker: one agent process per vehicle.

:class:`MqttBus` publishes this vehicle's state and keeps the others' latest (``publish`` /
``latest``) on top of one MQTT connection (:class:`~vtube_fleet.bus.client.MqttClient`, an
asyncio protocol that parses every chunk read from the socket in one go) owned by a background
task, which:

* connects with a **last will** (``vtube/<m>/status/<id>`` = ``lost``, retained, QoS 1), so a
  vehicle whose agent dies or loses its network is marked lost for everybody within
  ~1.5 keep-alive periods (at once if its process dies and the OS closes the socket);
* publishes ``online`` (with the agent's config hash) on every (re)connect, re-publishes the
  retained messages it owns (a coordinator's config and command) and subscribes to the others'
  states, statuses, last-seen states, the mission config and the fleet commands;
* sends this vehicle's state at once (:meth:`publish` writes it to the socket when all that
  was written before is in the kernel) or else from a **one-slot mailbox**: :meth:`publish`
  never blocks and never queues; a newer state replaces one not yet sent, a state older than
  ``max_publish_age_s`` when its turn comes is dropped, and nothing is sent (or kept for later)
  while disconnected;
* on a lost connection sets ``connected`` to False, notifies listeners (the pilot holds its
  vehicle), and reconnects with exponential back-off (``backoff_initial_s`` doubling up to
  ``backoff_max_s``, ±20 % jitter so a fleet does not reconnect in lock-step).

A vehicle whose last will arrives (and which publishes no newer state within
``lost_confirm_s``: a ``lost`` status is a claim, see :meth:`MqttBus._on_status`) stays in
:meth:`latest` at its last known position with phase ``LOST``: the agent treats it as a static
obstacle (same rule as a silent one). States carry the sender's wall-clock stamp; ageing them
is the tick's job (``vtube_fleet.fleet.neighbour_view``).

Security (``docs/security.md``): ``mqtts://`` URLs connect with TLS and verify the broker's
certificate; ``credentials`` name the account (a file from ``vtube-fleet bus-setup``); a
plain broker that is not on loopback is refused unless ``insecure``. Every message read is
checked (:mod:`vtube_fleet.bus.validate`: ids, region, speed, stamps, seq); a refused one is
counted in ``stats.refusals`` and logged once per sender and kind.

Use from a running event loop::

    async with MqttBus("mqtt://127.0.0.1:1883", "demo", vehicle_id=3, config_hash=h) as bus:
        await bus.wait_connected(10)
        bus.publish(state)            # every control tick
        others = bus.latest()         # {vehicle_id: NeighbourState}
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import random
import time
import urllib.parse
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from vtube_fleet.bus.client import MqttClient, MqttError, Will
from vtube_fleet.bus.codec import (
    ClockMsg,
    ClockOffset,
    CodecError,
    Command,
    MissionConfigMsg,
    Status,
    decode_clock,
    decode_command,
    decode_config,
    decode_state,
    decode_status,
    encode_clock,
    encode_state,
    encode_status,
)
from vtube_fleet.bus.security import (
    DEFAULT_TLS_PORT,
    BusCredentials,
    is_loopback,
    tls_context,
)
from vtube_fleet.bus.topics import MissionTopics
from vtube_fleet.bus.validate import StateLimits
from vtube_fleet.errors import UserError
from vtube_fleet.state import NeighbourState, Phase

__all__ = [
    "BrokerUrlError",
    "BusStats",
    "InsecureBrokerError",
    "MqttBus",
    "broker_uses_tls",
    "parse_broker_url",
]

log = logging.getLogger(__name__)

class BrokerUrlError(UserError):
    """A ``--broker`` URL that is not ``mqtt://HOST[:PORT]`` or ``mqtts://HOST[:PORT]``."""


class InsecureBrokerError(UserError):
    """A broker that is neither on loopback nor reached with TLS, without ``--insecure``."""


_TLS_SCHEMES = ("mqtts", "ssl")


def broker_uses_tls(url: str) -> bool:
    """True for ``mqtts://`` (and ``ssl://``) URLs."""
    return url.split("://", 1)[0] in _TLS_SCHEMES if "://" in url else False


def parse_broker_url(url: str) -> tuple[str, int, str | None, str | None]:
    """``mqtt[s]://[user[:password]@]HOST[:PORT]`` → (host, port, user, password); port 1883
    (``mqtts``: 8883, TLS)."""
    raw = url if "://" in url else f"mqtt://{url}"
    parsed = urllib.parse.urlsplit(raw)
    if parsed.scheme not in ("mqtt", "tcp", *_TLS_SCHEMES):
        raise BrokerUrlError(
            f"broker URL {url!r}: scheme {parsed.scheme!r} is not supported; use "
            "mqtts://HOST:PORT (TLS) or mqtt://HOST:PORT"
        )
    try:
        port = parsed.port or (DEFAULT_TLS_PORT if parsed.scheme in _TLS_SCHEMES else 1883)
    except ValueError:
        raise BrokerUrlError(f"broker URL {url!r}: the port is not a number in 1-65535") from None
    if not parsed.hostname:
        raise BrokerUrlError(f"broker URL {url!r} has no host; use mqtt://HOST:PORT")
    if parsed.path not in ("", "/"):
        raise BrokerUrlError(f"broker URL {url!r}: unexpected path {parsed.path!r}")
    return parsed.hostname, port, parsed.username, parsed.password


@dataclass
class BusStats:
    """Counters of one bus (for logs, tests and the benchmark)."""

    published: int = 0  # states handed to the broker
    superseded: int = 0  # replaced in the mailbox by a newer state before being sent
    dropped_offline: int = 0  # publish() while disconnected
    dropped_stale: int = 0  # older than max_publish_age_s when their turn came
    received: int = 0  # others' states accepted into the table
    out_of_order: int = 0  # others' states not newer than the one already held (dups too)
    decode_errors: int = 0
    #: messages refused (malformed, implausible, not in the mission, a refuted "lost"), and
    #: by kind (``malformed``, ``id_mismatch``, ``not_in_mission``, ``future``, ``region``,
    #: ``speed``, ``seq_jump``, ``wrong_mission``, ``lost_refuted``)
    refused: int = 0
    refusals: dict[str, int] = field(default_factory=dict)
    left_window: int = 0  # states showing a vehicle outside our cells (it is forgotten)
    connects: int = 0
    disconnects: int = 0
    connect_failures: int = 0  # failed connection attempts (each followed by a back-off)


class MqttBus:
    """The neighbour bus over MQTT: ``publish`` this vehicle's state, ``latest`` the others'.

    ``vehicle_id=None`` makes an *observer* (the mission coordinator): no state, no status,
    no last will; it reads everything and may own retained messages (:meth:`set_retained`).
    """

    def __init__(
        self,
        url: str,
        mission_id: str,
        vehicle_id: int | None = None,
        *,
        config_hash: str = "",
        keepalive_s: int = 2,
        connect_timeout_s: float = 5.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        max_publish_age_s: float = 0.5,
        last_period_s: float = 1.0,
        cell_m: float = math.inf,
        client_id: str | None = None,
        credentials: str | Path | BusCredentials | None = None,
        insecure: bool = False,
        limits: StateLimits | None = None,
        lost_confirm_s: float | None = None,
        wall_clock: Callable[[], float] = time.time,
        serve_clock: bool = False,
    ) -> None:
        """``credentials``: a credentials file (``vtube_fleet.bus.security``) or its contents;
        ``insecure``: allow a broker that is neither on loopback nor TLS; ``limits``: what
        states are plausible (default: any vehicle id, anywhere); ``lost_confirm_s``: how long a
        ``lost`` status waits for a contradicting fresh state (default 1.5 × ``last_period_s``;
        see :meth:`_on_status`); ``wall_clock``: this process's wall clock (stamps, ages: the
        states' clock); ``serve_clock``: answer the agents' clock round trips (the
        coordinator; :meth:`measure_clock`)."""
        self.url = url
        self.host, self.port, self._user, self._password = parse_broker_url(url)
        self.tls = broker_uses_tls(url)
        if self._password is not None:
            raise BrokerUrlError(
                f"broker URL {url.split('@')[-1]!r}: a password in the URL shows in the process "
                "list and shell history; put it in a --credentials file (vtube-fleet bus-setup)"
            )
        if not self.tls and not insecure and not is_loopback(self.host):
            raise InsecureBrokerError(
                f"broker {self.host}:{self.port} is not on this machine and the URL is not "
                "mqtts://: anyone on the network could read and forge the fleet's messages; "
                "use mqtts://HOST:8883 with --credentials (vtube-fleet bus-setup), or "
                "--insecure on a network you trust"
            )
        if isinstance(credentials, str | Path):
            credentials = BusCredentials.load(credentials)
        self.credentials: BusCredentials | None = credentials
        if credentials is not None:
            self._user, self._password = credentials.username, credentials.password
        self._tls_context = (
            tls_context(credentials.ca_file if credentials is not None else None)
            if self.tls else None
        )
        self.wall_clock = wall_clock
        self.serve_clock = serve_clock
        #: this agent's clock against the coordinator's (:meth:`measure_clock`; in its status)
        self.clock: ClockOffset | None = None
        self._clock_waiters: dict[int, tuple[float, asyncio.Future[ClockOffset]]] = {}
        self._clock_nonce = 0
        self.limits = limits if limits is not None else StateLimits()
        self._fleet_ids = self.limits.vehicle_ids  # the mission's slots (a run has fewer)
        self.lost_confirm_s = 1.5 * last_period_s if lost_confirm_s is None else lost_confirm_s
        self.topics = MissionTopics(mission_id)
        self.mission_id = mission_id
        self.vehicle_id = vehicle_id
        self.config_hash = config_hash
        #: The coordinator run this agent joined (sent in its status; see :meth:`announce`).
        self.run_id = ""
        #: Where this agent's procedure is (sent in its status; see :class:`Status`).
        self.stage = ""
        self._presence: tuple[str, str] = ("online", "")
        self.keepalive_s = max(1, int(keepalive_s))
        self.connect_timeout_s = connect_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.max_publish_age_s = max_publish_age_s
        self.last_period_s = last_period_s
        self.cell_m = math.inf
        if client_id is None:
            client_id = (
                f"vtube-{mission_id}-{vehicle_id}"
                if vehicle_id is not None
                else f"vtube-{mission_id}-obs-{uuid.uuid4().hex[:8]}"
            )
        self.client_id = client_id
        self.stats = BusStats()

        self._states: dict[int, NeighbourState] = {}
        self._lost: set[int] = set()
        self.statuses: dict[int, Status] = {}
        #: Latest retained mission announcement seen on ``vtube/<m>/config`` (None: none yet).
        self.config: MissionConfigMsg | None = None
        #: Latest fleet command seen on ``vtube/<m>/cmd`` (highest seq).
        self.command: Command | None = None

        self._retained: dict[str, bytes] = {}
        self._connected = False
        self._connecting = False
        self._closing = False
        self._task: asyncio.Task[None] | None = None
        self._client: MqttClient | None = None
        self._out_slot: NeighbourState | None = None
        self._out_event: asyncio.Event | None = None
        self._own_last: NeighbourState | None = None
        self._last_sent_mono = -math.inf
        self._last_phase: Phase | None = None
        self._changed: asyncio.Event | None = None
        self._waiters = 0
        self._listeners: list[Callable[[bool], None]] = []
        self._command_listeners: list[Callable[[Command], None]] = []
        self._state_listeners: list[Callable[[NeighbourState, float], None]] = []
        self._sync_topic = f"{self.topics.base}/sync/{self.client_id}"
        self._sync_seen = ""
        # spatial subscription: the cells around our own (None: every state)
        self._pub_cell: tuple[int, int] | None = None
        self._window: frozenset[tuple[int, int]] | None = None
        self._state_filters: set[str] = set()
        self._want_last: set[int] = set()  # lost vehicles whose retained last state we read
        self._errors_logged = 0
        #: Why the last connection attempt failed (e.g. "Not authorized", a TLS error).
        self.last_error: str | None = None
        self._refusal_counts: dict[tuple[str, str], int] = {}
        #: pending "lost" statuses: vehicle id -> (status, wall time it arrived, timer)
        self._claims: dict[int, _LostClaim] = {}
        self.set_cell_size(cell_m)
        self._disconnected_since: float | None = None
        self._echo_mono = -math.inf
        self._connected_mono = -math.inf
        #: Current back-off: initial after a lost connection, ×2 per failed attempt (≤ max).
        self.backoff_s = backoff_initial_s

    # -- the neighbour bus ----------------------------------------------------------------------
    def publish(self, state: NeighbourState) -> None:
        """Hand this vehicle's latest state to the sender (never blocks, never queues).

        Dropped (and counted) while disconnected: an old state must not reach the others late.
        """
        if self.vehicle_id is None:
            raise RuntimeError("an observer MqttBus (vehicle_id=None) cannot publish a state")
        if state.vehicle_id != self.vehicle_id:
            raise ValueError(
                f"MqttBus of vehicle {self.vehicle_id} asked to publish vehicle "
                f"{state.vehicle_id}'s state"
            )
        self._own_last = state
        if not self._connected or self._out_event is None:
            self.stats.dropped_offline += 1
            return
        client = self._client
        if self._out_slot is None and client is not None and client.writable:
            # nothing waiting and room in the socket: send it now (no wake-up of the sender)
            try:
                self._send_state(client, state)
            except MqttError:
                self.stats.dropped_offline += 1  # the connection just ended
            return
        if self._out_slot is not None:
            self.stats.superseded += 1
        self._out_slot = state
        self._out_event.set()

    def latest(self) -> dict[int, NeighbourState]:
        """Latest state of every other vehicle heard from within our cell window (all of them
        for an observer or without cells); lost ones with phase ``LOST``, wherever they are.

        A vehicle that leaves the window is forgotten (its last message, sent to the cell it
        left, says where it went), so a stale entry can never come back into the window."""
        return self._states

    def _in_window(self, state: NeighbourState) -> bool:
        window = self._window
        return (
            window is None
            or state.vehicle_id in self._lost
            or self.cell_of(state.x_m, state.y_m) in window
        )

    def _prune_to_window(self) -> None:
        for vid in [v for v, s in self._states.items() if not self._in_window(s)]:
            del self._states[vid]

    # -- spatial cells ---------------------------------------------------------------------------
    def set_cell_size(self, cell_m: float) -> None:
        """Use square cells of ``cell_m`` metres (``inf``: one cell): states are published in
        the sender's cell and an agent subscribes to its own cell and the 8 around it, so it
        hears every vehicle within ``cell_m`` of itself (choose ``cell_m`` ≥ the neighbour
        radius plus the distance a neighbour can close in ``max_publish_age_s``)."""
        if not (cell_m > 0):
            raise ValueError(f"cell size must be > 0 (or inf), got {cell_m}")
        if float(cell_m) != self.cell_m:
            self.cell_m = float(cell_m)
            self._pub_cell = None  # the next state re-computes the cell and the window

    def cell_of(self, x_m: float, y_m: float) -> tuple[int, int]:
        c = self.cell_m
        if not math.isfinite(c):
            return (0, 0)
        return (math.floor(x_m / c), math.floor(y_m / c))

    def _window_around(self, cell: tuple[int, int]) -> frozenset[tuple[int, int]]:
        if not math.isfinite(self.cell_m):
            return frozenset({(0, 0)})
        cx, cy = cell
        return frozenset((cx + i, cy + j) for i in (-1, 0, 1) for j in (-1, 0, 1))

    async def _apply_window(self, client: MqttClient) -> None:
        """Subscribe to the state filters of the current window (new ones first, then drop
        the old ones)."""
        t = self.topics
        window = self._window
        if window is not None:
            wanted = {t.cell_states(c) for c in window}
        elif self.vehicle_id is None or not math.isfinite(self.cell_m):
            wanted = {t.all_states}  # an observer, or no cells: everything
        else:
            wanted = set()  # cells, but no position of our own yet: nobody is near us
        new = wanted - self._state_filters
        old = self._state_filters - wanted
        # no timeout: a loaded process may take long to read the SUBACK; a dead broker is
        # noticed by the receiver (and a hung one by the echo), which ends this task
        if new:
            await client.subscribe([(f, 0) for f in sorted(new)], timeout=math.inf)
        self._state_filters = wanted
        if old:
            await client.unsubscribe(sorted(old), timeout=math.inf)

    async def _windower(self, client: MqttClient) -> None:
        """Follow our cell with the subscriptions, apart from the sender (which must never
        wait for a SUBACK)."""
        while True:
            await self._window_changed.wait()
            self._window_changed.clear()
            await self._apply_window(client)

    # -- state --------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while connected to the broker and subscribed."""
        return self._connected

    @property
    def lost(self) -> frozenset[int]:
        """Vehicles whose last will was received (and that have not come back since)."""
        return frozenset(self._lost)

    @property
    def echo_silence_s(self) -> float:
        """Seconds since our own state last came back from the broker (or since we connected),
        while connected and publishing: a broker that accepts the connection but stopped
        forwarding (hung, overloaded) shows here long before the keep-alive ends it."""
        if not self._connected or self._own_last is None or self._pub_cell is None:
            return 0.0
        since = max(self._echo_mono, self._connected_mono)
        return time.monotonic() - since

    def add_connection_listener(self, callback: Callable[[bool], None]) -> None:
        """``callback(connected)`` on every connect and disconnect (called in the loop)."""
        self._listeners.append(callback)

    def add_state_listener(self, callback: Callable[[NeighbourState, float], None]) -> None:
        """``callback(state, received_wall_s)`` for every live state accepted from another
        vehicle (not for retained last-seen states): for measuring ages."""
        self._state_listeners.append(callback)

    async def sync(self, timeout_s: float = 5.0) -> None:
        """Return once every message the broker had for us when this was called has arrived.

        Publishes a nonce to this client's own sync topic and waits for it: the broker delivers
        in order, so the retained messages of our subscriptions come first (used to read the
        retained state of a mission, e.g. ``vtube-fleet mission status``).
        """
        await self.wait_connected(timeout_s)
        client = self._client
        assert client is not None
        nonce = uuid.uuid4().hex
        await client.publish(self._sync_topic, nonce.encode(), qos=1)
        await self.wait_for(lambda: self._sync_seen == nonce, timeout_s)

    def add_command_listener(self, callback: Callable[[Command], None]) -> None:
        """``callback(command)`` for every new fleet command (higher seq than before)."""
        self._command_listeners.append(callback)

    def set_retained(self, topic: str, payload: bytes) -> None:
        """Own a retained QoS-1 message: published now if connected and after every reconnect
        (a restarted broker without persistence forgets retained messages)."""
        self._retained[topic] = payload
        client = self._client
        if self._connected and client is not None:
            asyncio.get_running_loop().create_task(self._publish_retained(client, topic, payload))

    async def _publish_retained(self, client: MqttClient, topic: str, payload: bytes) -> None:
        with contextlib.suppress(MqttError):
            await client.publish(topic, payload, qos=1, retain=True)

    async def wait_for(
        self, predicate: Callable[[], bool], timeout_s: float | None, *, poll_s: float = 0.05
    ) -> None:
        """Wait until ``predicate()`` holds: re-checked after every message and connection
        change, and every ``poll_s`` (for conditions on counters); :class:`TimeoutError`
        after ``timeout_s``."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        self._waiters += 1
        try:
            while not predicate():
                remaining = math.inf if deadline is None else deadline - loop.time()
                if remaining <= 0:
                    raise TimeoutError
                if self._changed is None:
                    self._changed = asyncio.Event()
                # (asyncio.timeout, not wait_for: Python 3.11's wait_for drops a cancellation
                # that arrives together with a change, and the waiting task flies on)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(min(poll_s, remaining)):
                        await self._changed.wait()
        finally:
            self._waiters -= 1

    async def wait_connected(self, timeout_s: float | None = None) -> None:
        await self.wait_for(lambda: self._connected, timeout_s)

    async def wait_disconnected(self, timeout_s: float | None = None) -> None:
        await self.wait_for(lambda: not self._connected, timeout_s)

    def _notify(self) -> None:
        if self._waiters and self._changed is not None:
            self._changed.set()
            self._changed = None

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the background connection task (needs a running event loop)."""
        if self._task is not None:
            return
        self._closing = False
        self._stop = asyncio.Event()
        self._window_changed = asyncio.Event()
        self._out_event = asyncio.Event()
        self._task = asyncio.get_running_loop().create_task(
            self._run(), name=f"mqtt-bus-{self.client_id}"
        )

    async def close(self, *, timeout_s: float = 2.0) -> None:
        """Say goodbye (last state and ``offline`` retained, so no will fires) and disconnect."""
        if self._task is None:
            return
        self._closing = True
        client = self._client
        # a refusal stays readable after we leave; anything else becomes "offline"
        goodbye = "refused" if self._presence[0] == "refused" else "offline"
        if client is not None and self._connected and self.vehicle_id is not None:
            with contextlib.suppress(MqttError, TimeoutError):
                async with asyncio.timeout(timeout_s):
                    if self._own_last is not None:
                        await client.publish(
                            self.topics.last(self.vehicle_id),
                            encode_state(self._own_last),
                            qos=1,
                            retain=True,
                        )
                    await client.publish(
                        self.topics.status(self.vehicle_id),
                        encode_status(self._status(goodbye, self._presence[1])),
                        qos=1,
                        retain=True,
                    )
        if self._connecting:
            # Let a connect in progress finish (then leave cleanly), never cut it midway.
            with contextlib.suppress(TimeoutError):
                await self.wait_for(lambda: not self._connecting, self.connect_timeout_s + 1)
        for claim in self._claims.values():
            claim.timer.cancel()
        self._claims.clear()
        task, self._task = self._task, None
        self._stop.set()  # the task disconnects cleanly (no last will) and ends
        try:
            await asyncio.wait_for(asyncio.shield(task), timeout_s + self.connect_timeout_s)
        except TimeoutError:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._set_connected(False)

    async def __aenter__(self) -> MqttBus:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- internals ------------------------------------------------------------------------------
    def _status(self, status: str, detail: str = "") -> Status:
        assert self.vehicle_id is not None
        return Status(
            self.vehicle_id,
            status,
            self.config_hash,
            self.run_id,
            self.wall_clock(),
            detail,
            self.stage,
            self.clock,
        )

    def announce(
        self, status: str = "online", detail: str = "", *, stage: str | None = None
    ) -> None:
        """Set this agent's retained presence (``online`` with the current ``run_id`` and
        ``stage``, or ``refused`` with the reason); published now if connected and on every
        reconnect."""
        if self.vehicle_id is None:
            raise RuntimeError("an observer MqttBus has no presence")
        if stage is not None:
            self.stage = stage
        self._presence = (status, detail)
        payload = encode_status(self._status(status, detail))
        client = self._client
        if self._connected and client is not None:
            asyncio.get_running_loop().create_task(
                self._publish_retained(client, self.topics.status(self.vehicle_id), payload)
            )

    def _set_connected(self, value: bool) -> None:
        if value == self._connected:
            return
        self._connected = value
        if value:
            self.stats.connects += 1
            self._disconnected_since = None
            self._connected_mono = time.monotonic()
        else:
            self.stats.disconnects += 1
            self._disconnected_since = time.monotonic()
            self._out_slot = None  # never send an old state after reconnecting
        for cb in list(self._listeners):
            try:
                cb(value)
            except Exception:  # a listener bug must not kill the bus
                log.exception("MqttBus connection listener failed")
        self._notify()

    def _make_client(self) -> MqttClient:
        will = None
        if self.vehicle_id is not None:
            lost = Status(self.vehicle_id, "lost", self.config_hash, self.run_id, 0.0, "last will")
            will = Will(self.topics.status(self.vehicle_id), encode_status(lost), qos=1,
                        retain=True)
        # clean session, TCP_NODELAY; every message handled as it is parsed (no per-message
        # task, no backlog of old states)
        return MqttClient(
            self.host,
            self.port,
            client_id=self.client_id,
            on_message=self._on_message,
            username=self._user,
            password=self._password,
            will=will,
            tls_context=self._tls_context,
            keepalive_s=self.keepalive_s,
            timeout_s=self.connect_timeout_s,
        )

    def _who(self) -> str:
        return f"vehicle {self.vehicle_id}" if self.vehicle_id is not None else "coordinator"

    async def _run(self) -> None:
        backoff = self.backoff_initial_s
        attempts = 0
        while not self._closing:
            attempts += 1
            try:
                client = self._make_client()
                self._connecting = True
                async with client:
                    self._connecting = False
                    if self._closing:
                        return  # close() waited for this connect: leave cleanly, say nothing
                    self._client = client
                    await self._on_connect(client)
                    if self._disconnected_since is not None:
                        log.warning(
                            "%s: reconnected to the MQTT broker %s:%d after %.1f s (%d attempts)",
                            self._who(),
                            self.host,
                            self.port,
                            time.monotonic() - self._disconnected_since,
                            attempts,
                        )
                    attempts = 0
                    backoff = self.backoff_initial_s
                    self._set_connected(True)
                    await self._serve(client)
            except MqttError as exc:
                if self._connected:
                    log.warning(
                        "%s: lost the MQTT broker %s:%d (%s); reconnecting with back-off",
                        self._who(),
                        self.host,
                        self.port,
                        exc,
                    )
                else:
                    self.stats.connect_failures += 1
                    self.last_error = str(exc)
                    log.log(
                        logging.WARNING if attempts == 1 else logging.DEBUG,
                        "%s: cannot reach the MQTT broker %s:%d (%s); retrying with back-off",
                        self._who(),
                        self.host,
                        self.port,
                        exc,
                    )
            except Exception:  # a bug must not silently end the bus: log, reconnect
                log.exception("%s: MQTT bus task failed; reconnecting", self._who())
            finally:
                self._connecting = False
                self._client = None
                self._set_connected(False)
            if self._closing:
                break
            self.backoff_s = backoff
            with contextlib.suppress(TimeoutError):  # the back-off wait; close() ends it early
                async with asyncio.timeout(backoff * random.uniform(0.8, 1.2)):
                    await self._stop.wait()
            backoff = min(backoff * 2.0, self.backoff_max_s)

    async def _serve(self, client: MqttClient) -> None:
        """Run the sender and the receiver until the connection fails (their MqttError is
        raised) or :meth:`close` asks to stop (return; the caller disconnects cleanly)."""
        workers = [asyncio.ensure_future(self._receiver(client))]
        if self.vehicle_id is not None:
            workers.append(asyncio.ensure_future(self._sender(client)))
            workers.append(asyncio.ensure_future(self._windower(client)))
        tasks = [*workers, asyncio.ensure_future(self._stop.wait())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for t in workers:
            if t in done and not t.cancelled() and t.exception() is not None:
                raise t.exception()  # type: ignore[misc]
        if not self._stop.is_set():
            raise RuntimeError("MQTT bus worker ended unexpectedly")

    async def _on_connect(self, client: MqttClient) -> None:
        if self.vehicle_id is not None:
            await client.publish(
                self.topics.status(self.vehicle_id),
                encode_status(self._status(*self._presence)),
                qos=1,
                retain=True,
            )
        for topic, payload in list(self._retained.items()):
            await client.publish(topic, payload, qos=1, retain=True)
        t = self.topics
        clock = ([(t.all_clock_asks, 0)] if self.serve_clock else []) + (
            [(t.clock_echo(self.vehicle_id), 0)] if self.vehicle_id is not None else [])
        await client.subscribe(
            [(t.all_statuses, 1), (t.config, 1), (t.cmd, 1), (self._sync_topic, 1)]
            + [(t.last(v), 0) for v in sorted(self._want_last)] + clock
        )
        self._state_filters = set()
        await self._apply_window(client)

    async def _sender(self, client: MqttClient) -> None:
        """Send what :meth:`publish` left in the mailbox (while the socket was full)."""
        assert self._out_event is not None
        event = self._out_event
        self._out_slot = None
        while True:
            await event.wait()
            event.clear()
            await client.wait_writable()
            state, self._out_slot = self._out_slot, None
            if state is not None:
                self._send_state(client, state)

    def _send_state(self, client: MqttClient, state: NeighbourState) -> None:
        """Write our state to its cell's topic (QoS 0, no waiting), plus the notice to the cell
        it left and the retained last-seen state when due; drop it if it is too old."""
        if state.age_s(self.wall_clock()) > self.max_publish_age_s:
            self.stats.dropped_stale += 1
            return
        vid = state.vehicle_id
        payload = encode_state(state)
        cell = self.cell_of(state.x_m, state.y_m)
        client.publish_nowait(self.topics.state(vid, cell), payload)
        self.stats.published += 1
        if cell != self._pub_cell:
            if self._pub_cell is not None:
                # tell the old cell's subscribers where we went (they may not hear us again)
                client.publish_nowait(self.topics.state(vid, self._pub_cell), payload)
            self._pub_cell = cell
            self._window = self._window_around(cell)
            self._prune_to_window()
            self._window_changed.set()
        now = time.monotonic()
        if state.phase != self._last_phase or now - self._last_sent_mono >= self.last_period_s:
            self._last_phase = state.phase
            self._last_sent_mono = now
            client.publish_nowait(self.topics.last(vid), payload, retain=True)

    async def _receiver(self, client: MqttClient) -> None:
        # Messages are dispatched as the client parses them (on_message, see _make_client);
        # this only waits for the connection to end (MqttError says why).
        await client.wait_closed()

    def _on_message(self, topic: str, payload: bytes) -> None:
        try:
            self._dispatch(topic, payload)
        except Exception:  # a bug here must not break the client's socket reader
            self._errors_logged += 1
            if self._errors_logged <= 5:
                log.exception("%s: failed to handle a message on %s", self._who(), topic)

    # -- what is accepted (docs/mqtt.md, "What an agent accepts") ---------------------------
    def set_limits(self, limits: StateLimits) -> None:
        """Accept only states within ``limits`` from now on (e.g. the run's vehicles once
        joined); vehicles no longer allowed are forgotten."""
        self.limits = limits
        for vid in [v for v in self._states if limits.id_problem(v) is not None]:
            del self._states[vid]

    def refusal_counts(self) -> dict[tuple[str, str], int]:
        """``{(sender, kind): count}`` of the refused messages (at most 1024 senders)."""
        return dict(self._refusal_counts)

    def _refuse(self, kind: str, sender: str, topic: str, reason: str) -> None:
        """Count a refused message; log it once per sender and kind."""
        self.stats.refused += 1
        self.stats.refusals[kind] = self.stats.refusals.get(kind, 0) + 1
        key = (sender, kind)
        n = self._refusal_counts.get(key)
        if n is not None:
            self._refusal_counts[key] = n + 1
            return
        if len(self._refusal_counts) >= _MAX_REFUSAL_SENDERS:
            return  # counted in stats only: a flood of made-up senders fills neither
        self._refusal_counts[key] = 1
        logged = len(self._refusal_counts)
        if logged <= _MAX_LOGGED_SENDERS:
            log.warning(
                "%s: refused a message from %s on %s (%s): %s [logged once per sender; %d "
                "refused so far]", self._who(), sender, topic, kind, reason, self.stats.refused,
            )
        if logged == _MAX_LOGGED_SENDERS:
            log.warning("%s: refusals from %d senders; further senders are only counted "
                        "(stats.refusals)", self._who(), logged)

    def _dispatch(self, topic: str, payload: bytes) -> None:
        kind, vid = self.topics.classify(topic)
        if kind == "unknown" and topic == self._sync_topic:
            self._sync_seen = payload.decode(errors="replace")
            self._notify()
            return
        if vid is not None and vid != self.vehicle_id:
            why = self.limits.id_problem(vid)
            if why is not None:
                if payload:  # (clearing a retained message is not a claim)
                    self._refuse("not_in_mission", f"vehicle {vid}", topic, why)
                return
        try:
            if kind == "state" or kind == "last":
                if vid == self.vehicle_id:
                    if kind == "state":
                        self._echo_mono = time.monotonic()  # our own state came back
                    return
                self._on_state(decode_state(payload), from_last=kind == "last", topic_id=vid,
                               topic=topic)
            elif kind == "status":
                if not payload:  # a cleared retained message
                    return
                self._on_status(decode_status(payload), vid, topic)
            elif kind == "config":
                if payload:
                    self._on_config(decode_config(payload), topic)
            elif kind == "cmd":
                if payload:
                    self._on_command(decode_command(payload), topic)
            elif kind == "clock_ask":
                if self.serve_clock:
                    self._answer_clock(decode_clock(payload), vid, topic)
            elif kind == "clock_echo":
                if vid == self.vehicle_id:
                    self._on_clock_echo(decode_clock(payload))
        except CodecError as exc:
            self.stats.decode_errors += 1
            sender = f"vehicle {vid}" if vid is not None else kind if kind != "unknown" else topic
            self._refuse("malformed", sender, topic, str(exc))

    def _on_state(self, state: NeighbourState, *, from_last: bool, topic_id: int | None,
                  topic: str = "") -> None:
        vid = state.vehicle_id
        if vid != topic_id:
            self._refuse("id_mismatch", f"vehicle {topic_id}", topic,
                         f"the payload says vehicle {vid}, the topic vehicle {topic_id}")
            return
        prev = self._states.get(vid)
        claim = self._claims.get(vid)
        bad = self.limits.problem(state, prev if prev is not None else
                                  (claim.last if claim is not None else None),
                                  self.wall_clock())
        if bad is not None:
            self._refuse(bad[0], f"vehicle {vid}", topic, bad[1])
            return
        if prev is not None and state.seq <= prev.seq and state.stamp_s <= prev.stamp_s:
            self.stats.out_of_order += 1
            return
        if claim is not None:
            if state.stamp_s > claim.since_wall_s:
                self._refute(vid, claim, state, topic)
            elif from_last and not self._in_window(state):
                # where it was, kept for the moment its silence confirms the claim
                if claim.last is None or state.stamp_s > claim.last.stamp_s:
                    claim.last = state
                return
        if not self._in_window(state):
            # it left our cells (its notice to the cell it left), or a late message of a cell
            # we left: forget it
            self._states.pop(vid, None)
            self.stats.left_window += 1
            return
        if vid in self._lost:
            if from_last:
                state = dataclasses.replace(state, phase=Phase.LOST)
            else:
                self._lost.discard(vid)  # a live state: its agent is back
        self._states[vid] = state
        self.stats.received += 1
        if not from_last and self._state_listeners:
            now = self.wall_clock()
            for cb in self._state_listeners:
                cb(state, now)
        if self._waiters:
            self._notify()

    def _on_status(self, status: Status, vid: int | None, topic: str = "") -> None:
        """A presence message. ``lost`` (a last will, or anybody's claim) is a *claim*: the
        vehicle counts as lost only if no state stamped after the claim arrived comes from it
        within ``lost_confirm_s`` (live states at the control rate in our cells, its retained
        ``last/<id>`` at ~1 Hz wherever it is). A vehicle still publishing is not lost,
        whatever a retained status says; a dead one is silent and confirmed. Its status stays
        what it was until then."""
        if vid is None or status.vehicle_id != vid:
            self._refuse("id_mismatch", f"vehicle {vid}", topic,
                         f"status of vehicle {status.vehicle_id} on the topic of {vid}")
            return
        if vid == self.vehicle_id:
            if status.status == "lost" and self._connected and self._client is not None:
                # Our own previous connection's will (e.g. a session take-over after a network
                # glitch) overwrote our presence: say again that we are online.
                self.announce(*self._presence)
            return
        if status.status == "lost":
            if vid in self._lost:
                self.statuses[vid] = status
            elif vid not in self._claims:
                loop = asyncio.get_running_loop()
                self._claims[vid] = _LostClaim(
                    status, self.wall_clock(), loop.call_later(self.lost_confirm_s,
                                                         self._confirm_lost, vid))
                if vid not in self._want_last:
                    # where is it? its retained last-seen state (it may never have been near
                    # us), and the evidence of a vehicle that is still there (~1 Hz)
                    self._want_last.add(vid)
                    client = self._client  # set while connected, also during _on_connect
                    if client is not None:
                        loop.create_task(self._subscribe_last(client, vid))
            self._notify()
            return
        claim = self._claims.pop(vid, None)
        if claim is not None:  # it spoke for itself after the claim
            claim.timer.cancel()
        self.statuses[vid] = status
        if status.status == "online":
            self._lost.discard(vid)
        self._notify()

    def _confirm_lost(self, vid: int) -> None:
        claim = self._claims.pop(vid, None)
        if claim is None or self._closing:
            return
        self.statuses[vid] = claim.status
        self._lost.add(vid)
        log.warning("%s: vehicle %d lost (its last will arrived and no newer state from it "
                    "within %.1f s)", self._who(), vid, self.lost_confirm_s)
        prev = self._states.get(vid, claim.last)
        if prev is not None:
            self._states[vid] = dataclasses.replace(prev, phase=Phase.LOST)
        self._notify()

    def _refute(self, vid: int, claim: _LostClaim, state: NeighbourState, topic: str) -> None:
        """A fresh state contradicts a pending ``lost``: drop the claim (counted, logged)."""
        del self._claims[vid]
        claim.timer.cancel()
        self._refuse("lost_refuted", f"vehicle {vid}", self.topics.status(vid),
                     f"status 'lost' ignored: the vehicle published a state (on {topic}) "
                     f"stamped {state.stamp_s - claim.since_wall_s:.2f} s after it arrived")
        if vid not in self._lost and vid in self._want_last:
            self._want_last.discard(vid)
            client = self._client
            if client is not None:
                asyncio.get_running_loop().create_task(self._unsubscribe(client,
                                                                         self.topics.last(vid)))
        self._notify()

    async def _subscribe_last(self, client: MqttClient, vid: int) -> None:
        with contextlib.suppress(MqttError):
            await client.subscribe([(self.topics.last(vid), 0)])

    async def _unsubscribe(self, client: MqttClient, topic: str) -> None:
        with contextlib.suppress(MqttError):
            await client.unsubscribe([topic])

    # -- clocks (docs/mqtt.md, "Clocks") -------------------------------------------------------
    def _answer_clock(self, ask: ClockMsg, vid: int | None, topic: str) -> None:
        """The coordinator: echo an agent's clock round trip with its own two stamps, at
        once (in the parser's callback: what it adds to the trip is measured, t3 − t2)."""
        t2 = self.wall_clock()
        client = self._client
        if vid is None or ask.vehicle_id != vid or client is None or not self._connected:
            if vid is not None and ask.vehicle_id != vid:
                self._refuse("id_mismatch", f"vehicle {vid}", topic,
                             f"clock ask of vehicle {ask.vehicle_id} on the topic of {vid}")
            return
        echo = dataclasses.replace(ask, t2_s=t2, t3_s=self.wall_clock())
        with contextlib.suppress(MqttError):
            client.publish_nowait(self.topics.clock_echo(vid), encode_clock(echo))

    def _on_clock_echo(self, echo: ClockMsg) -> None:
        t4 = self.wall_clock()
        waiter = self._clock_waiters.pop(echo.nonce, None)
        if waiter is None or waiter[1].done() or echo.t1_s != waiter[0]:
            return  # late, or not ours
        waiter[1].set_result(ClockOffset.from_stamps(echo.t1_s, echo.t2_s, echo.t3_s, t4))

    async def clock_round_trip(self, timeout_s: float) -> ClockOffset:
        """One clock round trip to the coordinator (:class:`~vtube_fleet.bus.codec.ClockMsg`,
        QoS 0: a lost one times out, never comes back late as a retransmission);
        :class:`TimeoutError` after ``timeout_s``."""
        if self.vehicle_id is None:
            raise RuntimeError("an observer MqttBus has no clock to measure")
        client = self._client
        if client is None or not self._connected:
            raise TimeoutError
        self._clock_nonce += 1
        nonce = self._clock_nonce
        fut: asyncio.Future[ClockOffset] = asyncio.get_running_loop().create_future()
        t1 = self.wall_clock()
        self._clock_waiters[nonce] = (t1, fut)
        try:
            client.publish_nowait(self.topics.clock_ask(self.vehicle_id),
                                  encode_clock(ClockMsg(self.vehicle_id, nonce, t1)))
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            self._clock_waiters.pop(nonce, None)

    async def measure_clock(self, samples: int, timeout_s: float) -> ClockOffset:
        """``samples`` round trips one after the other (:meth:`clock_round_trip`, each at most
        ``timeout_s``); the one of least delay (its two legs the most alike: NTP's choice),
        kept in :attr:`clock` and sent in this agent's status from now on.
        :class:`TimeoutError` when none came back."""
        got: list[ClockOffset] = []
        for _ in range(samples):
            with contextlib.suppress(TimeoutError, MqttError):
                got.append(await self.clock_round_trip(timeout_s))
        if not got:
            raise TimeoutError
        best = min(got, key=lambda c: c.delay_s)
        self.clock = dataclasses.replace(best, samples=len(got))
        return self.clock

    def _control_problem(self, mission_id: str, stamp_s: float) -> tuple[str, str] | None:
        if mission_id != self.mission_id:
            return "wrong_mission", f"for mission {mission_id!r}, this is {self.mission_id!r}"
        why = self.limits.future_problem(stamp_s, self.wall_clock())
        return None if why is None else ("future", why)

    def _on_config(self, cfg: MissionConfigMsg, topic: str) -> None:
        bad = self._control_problem(cfg.mission_id, cfg.stamp_s)
        ids = self._fleet_ids
        if bad is None and ids is not None and not 1 <= cfg.vehicles <= len(ids):
            bad = ("not_in_mission", f"a run of {cfg.vehicles} vehicles; the mission has "
                                     f"{len(ids)}")
        if bad is not None:
            self._refuse(bad[0], "config", topic, bad[1])
            return
        self.config = cfg
        self._notify()

    def _on_command(self, cmd: Command, topic: str = "") -> None:
        bad = self._control_problem(cmd.mission_id, cmd.stamp_s)
        if bad is None:
            ahead_s = cmd.seq / 1000.0 - self.wall_clock()
            if ahead_s > self.limits.max_future_s:
                bad = ("future", f"seq {cmd.seq} is {ahead_s:.3g} s in the future (ms since "
                                 "the epoch)")
        if bad is not None:
            self._refuse(bad[0], "cmd", topic, bad[1])
            return
        if self.command is not None and cmd.seq <= self.command.seq:
            return  # a re-published retained command already handled
        self.command = cmd
        for cb in list(self._command_listeners):
            try:
                cb(cmd)
            except Exception:
                log.exception("MqttBus command listener failed")
        self._notify()


#: Distinct (sender, kind) pairs counted per sender (:meth:`MqttBus.refusal_counts`) ...
_MAX_REFUSAL_SENDERS = 1024
#: ... and logged (once each).
_MAX_LOGGED_SENDERS = 32


@dataclass
class _LostClaim:
    """A ``lost`` status waiting for confirmation (:meth:`MqttBus._on_status`)."""

    status: Status
    since_wall_s: float  # our clock when it arrived
    timer: asyncio.TimerHandle
    last: NeighbourState | None = None  # its last-seen state, if outside our cells
