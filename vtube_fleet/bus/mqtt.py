"""The neighbour bus over an MQTT broker (aiomqtt): one agent process per vehicle.

:class:`MqttBus` implements :class:`~vtube_fleet.bus.base.NeighbourBus` (``publish`` /
``latest``) on top of one MQTT connection owned by a background task, which:

* connects with a **last will** (``vtube/<m>/status/<id>`` = ``lost``, retained, QoS 1), so a
  vehicle whose agent dies or loses its network is marked lost for everybody within
  ~1.5 keep-alive periods (at once if its process dies and the OS closes the socket);
* publishes ``online`` (with the agent's config hash) on every (re)connect, re-publishes the
  retained messages it owns (a coordinator's config and command) and subscribes to the others'
  states, statuses, last-seen states, the mission config and the fleet commands;
* sends this vehicle's state from a **one-slot mailbox**: :meth:`publish` never blocks and never
  queues; a newer state replaces one not yet sent, a state older than ``max_publish_age_s``
  when its turn comes is dropped, and nothing is sent (or kept for later) while disconnected;
* on a lost connection sets ``connected`` to False, notifies listeners (the pilot holds its
  vehicle), and reconnects with exponential back-off (``backoff_initial_s`` doubling up to
  ``backoff_max_s``, ±20 % jitter so a fleet does not reconnect in lock-step).

A vehicle whose last will arrives stays in :meth:`latest` at its last known position with phase
``LOST``: the agent treats it as a static obstacle (same rule as a silent one). States carry the
sender's wall-clock stamp; ageing them is the agent's job (``vtube_fleet.fleet.agent``).

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
import socket
import time
import urllib.parse
import uuid
from collections.abc import Callable
from dataclasses import dataclass

import aiomqtt

from vtube_fleet.bus.codec import (
    CodecError,
    Command,
    MissionConfigMsg,
    Status,
    decode_command,
    decode_config,
    decode_state,
    decode_status,
    encode_state,
    encode_status,
)
from vtube_fleet.bus.topics import MissionTopics
from vtube_fleet.errors import UserError
from vtube_fleet.state import NeighbourState, Phase

__all__ = ["BrokerUrlError", "BusStats", "MqttBus", "parse_broker_url"]

log = logging.getLogger(__name__)

_NODELAY = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)


class BrokerUrlError(UserError):
    """A ``--broker`` URL that is not ``mqtt://HOST[:PORT]``."""


def parse_broker_url(url: str) -> tuple[str, int, str | None, str | None]:
    """``mqtt://[user[:password]@]HOST[:PORT]`` → (host, port, user, password); port 1883."""
    raw = url if "://" in url else f"mqtt://{url}"
    parsed = urllib.parse.urlsplit(raw)
    if parsed.scheme not in ("mqtt", "tcp"):
        raise BrokerUrlError(
            f"broker URL {url!r}: scheme {parsed.scheme!r} is not supported; use mqtt://HOST:PORT"
        )
    try:
        port = parsed.port or 1883
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
    left_window: int = 0  # states showing a vehicle outside our cells (it is forgotten)
    connects: int = 0
    disconnects: int = 0
    connect_failures: int = 0  # failed connection attempts (each followed by a back-off)


class MqttBus:
    """A :class:`~vtube_fleet.bus.base.NeighbourBus` over MQTT.

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
    ) -> None:
        self.url = url
        self.host, self.port, self._user, self._password = parse_broker_url(url)
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
        self._client: aiomqtt.Client | None = None
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
        self.set_cell_size(cell_m)
        self._disconnected_since: float | None = None
        self._echo_mono = -math.inf
        self._connected_mono = -math.inf
        #: Current back-off: initial after a lost connection, ×2 per failed attempt (≤ max).
        self.backoff_s = backoff_initial_s

    # -- NeighbourBus --------------------------------------------------------------------------
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

    async def _apply_window(self, client: aiomqtt.Client) -> None:
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

    async def _windower(self, client: aiomqtt.Client) -> None:
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

    async def _publish_retained(self, client: aiomqtt.Client, topic: str, payload: bytes) -> None:
        with contextlib.suppress(aiomqtt.MqttError):
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
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._changed.wait(), min(poll_s, remaining))
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
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
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
            # Cancelling aiomqtt's connect midway leaks its socket: let it finish first.
            with contextlib.suppress(TimeoutError):
                await self.wait_for(lambda: not self._connecting, self.connect_timeout_s + 1)
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
            time.time(),
            detail,
            self.stage,
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

    def _make_client(self) -> aiomqtt.Client:
        will = None
        if self.vehicle_id is not None:
            lost = Status(self.vehicle_id, "lost", self.config_hash, self.run_id, 0.0, "last will")
            will = aiomqtt.Will(
                self.topics.status(self.vehicle_id), encode_status(lost), qos=1, retain=True
            )
        bus = self

        class _DispatchQueue(asyncio.Queue):  # type: ignore[type-arg]
            """aiomqtt's incoming queue, replaced: each message is handled at once (no
            per-message task, no backlog of old states)."""

            def put_nowait(self, item: aiomqtt.Message) -> None:
                bus._on_message(item)

        return aiomqtt.Client(
            self.host,
            self.port,
            username=self._user,
            password=self._password,
            identifier=self.client_id,
            will=will,
            clean_session=True,
            keepalive=self.keepalive_s,
            timeout=self.connect_timeout_s,
            socket_options=_NODELAY,
            queue_type=_DispatchQueue,
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
            except aiomqtt.MqttError as exc:
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
                await asyncio.wait_for(self._stop.wait(), backoff * random.uniform(0.8, 1.2))
            backoff = min(backoff * 2.0, self.backoff_max_s)

    async def _serve(self, client: aiomqtt.Client) -> None:
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

    async def _on_connect(self, client: aiomqtt.Client) -> None:
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
        await client.subscribe(
            [(t.all_statuses, 1), (t.config, 1), (t.cmd, 1), (self._sync_topic, 1)]
            + [(t.last(v), 0) for v in sorted(self._want_last)]
        )
        self._state_filters = set()
        await self._apply_window(client)

    async def _sender(self, client: aiomqtt.Client) -> None:
        assert self._out_event is not None
        event = self._out_event
        self._out_slot = None
        vid = self.vehicle_id
        assert vid is not None
        last_topic = self.topics.last(vid)
        while True:
            await event.wait()
            event.clear()
            state, self._out_slot = self._out_slot, None
            if state is None:
                continue
            if state.age_s() > self.max_publish_age_s:
                self.stats.dropped_stale += 1
                continue
            payload = encode_state(state)
            cell = self.cell_of(state.x_m, state.y_m)
            await client.publish(self.topics.state(vid, cell), payload, qos=0, timeout=math.inf)
            self.stats.published += 1
            if cell != self._pub_cell:
                if self._pub_cell is not None:
                    # tell the old cell's subscribers where we went (they may not hear us again)
                    await client.publish(
                        self.topics.state(vid, self._pub_cell), payload, qos=0, timeout=math.inf
                    )
                self._pub_cell = cell
                self._window = self._window_around(cell)
                self._prune_to_window()
                self._window_changed.set()
            now = time.monotonic()
            if state.phase != self._last_phase or now - self._last_sent_mono >= self.last_period_s:
                self._last_phase = state.phase
                self._last_sent_mono = now
                await client.publish(last_topic, payload, qos=0, retain=True, timeout=math.inf)

    async def _receiver(self, client: aiomqtt.Client) -> None:
        # Messages are dispatched as paho reads them (see _make_client); this only waits for
        # the connection to end (the iterator raises MqttError then).
        async for _ in client.messages:
            pass

    def _on_message(self, message: aiomqtt.Message) -> None:
        try:
            payload = message.payload
            if isinstance(payload, bytes | bytearray):
                self._dispatch(message.topic.value, bytes(payload))
        except Exception:  # a bug here must not break paho's socket reader
            self._errors_logged += 1
            if self._errors_logged <= 5:
                log.exception(
                    "%s: failed to handle a message on %s", self._who(), message.topic.value
                )

    def _dispatch(self, topic: str, payload: bytes) -> None:
        kind, vid = self.topics.classify(topic)
        if kind == "unknown" and topic == self._sync_topic:
            self._sync_seen = payload.decode(errors="replace")
            self._notify()
            return
        try:
            if kind == "state" or kind == "last":
                if vid == self.vehicle_id:
                    if kind == "state":
                        self._echo_mono = time.monotonic()  # our own state came back
                    return
                self._on_state(decode_state(payload), from_last=kind == "last", topic_id=vid)
            elif kind == "status":
                if not payload:  # a cleared retained message
                    return
                self._on_status(decode_status(payload), vid)
            elif kind == "config":
                if payload:
                    self.config = decode_config(payload)
                    self._notify()
            elif kind == "cmd":
                if payload:
                    self._on_command(decode_command(payload))
        except CodecError as exc:
            self.stats.decode_errors += 1
            if self.stats.decode_errors <= 5 or self.stats.decode_errors % 1000 == 0:
                log.warning(
                    "%s: dropped a malformed message on %s (%s); %d so far",
                    self._who(),
                    topic,
                    exc,
                    self.stats.decode_errors,
                )

    def _on_state(self, state: NeighbourState, *, from_last: bool, topic_id: int | None) -> None:
        vid = state.vehicle_id
        if vid != topic_id:
            raise CodecError(f"vehicle id {vid} in the payload differs from the topic's {topic_id}")
        prev = self._states.get(vid)
        if prev is not None and state.seq <= prev.seq and state.stamp_s <= prev.stamp_s:
            self.stats.out_of_order += 1
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
            now = time.time()
            for cb in self._state_listeners:
                cb(state, now)
        if self._waiters:
            self._notify()

    def _on_status(self, status: Status, vid: int | None) -> None:
        if vid is None or status.vehicle_id != vid:
            raise CodecError(f"status for vehicle {status.vehicle_id} on the topic of {vid}")
        if vid == self.vehicle_id:
            if status.status == "lost" and self._connected and self._client is not None:
                # Our own previous connection's will (e.g. a session take-over after a network
                # glitch) overwrote our presence: say again that we are online.
                self.announce(*self._presence)
            return
        self.statuses[vid] = status
        if status.status == "lost":
            if vid not in self._lost:
                log.warning("%s: vehicle %d lost (its last will arrived)", self._who(), vid)
            self._lost.add(vid)
            if vid not in self._want_last:
                # where was it? its retained last-seen state (it may never have been near us)
                self._want_last.add(vid)
                client = self._client  # set while connected, also during _on_connect
                if client is not None:
                    asyncio.get_running_loop().create_task(self._subscribe_last(client, vid))
            prev = self._states.get(vid)
            if prev is not None:
                self._states[vid] = dataclasses.replace(prev, phase=Phase.LOST)
        elif status.status == "online":
            self._lost.discard(vid)
        self._notify()

    async def _subscribe_last(self, client: aiomqtt.Client, vid: int) -> None:
        with contextlib.suppress(aiomqtt.MqttError):
            await client.subscribe(self.topics.last(vid), qos=0)

    def _on_command(self, cmd: Command) -> None:
        if cmd.mission_id != self.mission_id:
            raise CodecError(f"command for mission {cmd.mission_id!r} on {self.mission_id!r}")
        if self.command is not None and cmd.seq <= self.command.seq:
            return  # a re-published retained command already handled
        self.command = cmd
        for cb in list(self._command_listeners):
            try:
                cb(cmd)
            except Exception:
                log.exception("MqttBus command listener failed")
        self._notify()
