"""MqttBus against a real broker process: states, last will, broker loss, retained control."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import aiomqtt
import pytest
from broker import LocalBroker, find_mosquitto

from vtube_fleet.bus.codec import MissionConfigMsg, decode_state, encode_config
from vtube_fleet.bus.mqtt import BrokerUrlError, MqttBus, parse_broker_url
from vtube_fleet.state import NeighbourState, Phase

KINDS = ["mosquitto", "amqtt"] if find_mosquitto() else ["amqtt"]
MISSION = "unit"


@pytest.fixture
def broker():
    with LocalBroker() as b:
        yield b


def state(vid: int, seq: int, x: float = 0.0, *, phase: Phase = Phase.IN_TUBE, age_s: float = 0.0):
    return NeighbourState(vid, x, 1.0, 2.0, 0.0, phase, time.time() - age_s, seq)


async def publish_until(bus: MqttBus, peer: MqttBus, vid: int, seq: int, timeout_s: float = 10):
    """Publish ``seq`` (QoS 0 may drop, so repeat with new stamps) until ``peer`` has it."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not (vid in peer.latest() and peer.latest()[vid].seq >= seq):
        assert loop.time() < deadline, f"vehicle {vid} seq {seq} never reached the peer"
        bus.publish(state(vid, seq, x=float(seq)))
        try:
            await peer.wait_for(lambda: vid in peer.latest() and peer.latest()[vid].seq >= seq, 0.2)
        except TimeoutError:
            pass


@pytest.mark.parametrize("kind", KINDS)
async def test_states_flow_between_agents_and_to_an_observer(kind):
    with LocalBroker(kind=kind) as b:
        async with (
            MqttBus(b.url, MISSION, 0) as a,
            MqttBus(b.url, MISSION, 1) as c,
            MqttBus(b.url, MISSION) as obs,
        ):
            for bus in (a, c, obs):
                await bus.wait_connected(10)
            await publish_until(a, c, 0, 1)
            await publish_until(c, a, 1, 1)
            await obs.wait_for(lambda: set(obs.latest()) == {0, 1}, 10)
            assert set(a.latest()) == {1} and set(c.latest()) == {0}  # never itself
            got = c.latest()[0]
            assert (got.x_m, got.y_m, got.vx_m_s, got.phase) == (1.0, 1.0, 2.0, Phase.IN_TUBE)
            await obs.wait_for(lambda: {0, 1} <= set(obs.statuses), 10)
            assert obs.statuses[0].status == "online"


async def test_older_states_never_replace_newer(broker):
    async with MqttBus(broker.url, MISSION, 0) as a, MqttBus(broker.url, MISSION, 1) as c:
        await a.wait_connected(10)
        await c.wait_connected(10)
        await publish_until(a, c, 0, 5)
        newest = c.latest()[0]
        # Inject an old state directly (as a late, reordered message would arrive).
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            from vtube_fleet.bus.codec import encode_state

            old = NeighbourState(0, -9.0, 0, 0, 0, Phase.IN_TUBE, newest.stamp_s - 1, 2)
            await raw.publish(a.topics.state(0), encode_state(old))
            await raw.publish(a.topics.state(0), b"garbage")
            await c.wait_for(lambda: c.stats.decode_errors >= 1, 10)
        assert c.latest()[0] == newest
        assert c.stats.out_of_order >= 1


AGENT_SCRIPT = textwrap.dedent(
    """
    import asyncio, sys, time
    from vtube_fleet.state import NeighbourState, Phase
    from vtube_fleet.bus.mqtt import MqttBus

    async def main(url, mission, vid):
        async with MqttBus(url, mission, vid) as bus:
            await bus.wait_connected(10)
            seq = 0
            while True:
                seq += 1
                bus.publish(NeighbourState(vid, 10.0 + 0.01 * seq, -1.0, 0.2, 0.0,
                                           Phase.IN_TUBE, time.time(), seq))
                await asyncio.sleep(0.05)  # the agent's 20 Hz control period

    asyncio.run(main(sys.argv[1], sys.argv[2], int(sys.argv[3])))
    """
)


@pytest.mark.parametrize("kind", KINDS)
async def test_killed_agent_is_marked_lost_at_its_last_position(kind):
    with LocalBroker(kind=kind) as broker:
        await _killed_agent_is_lost(broker)


async def _killed_agent_is_lost(broker: LocalBroker) -> None:
    proc = subprocess.Popen([sys.executable, "-c", AGENT_SCRIPT, broker.url, MISSION, "7"])
    try:
        async with MqttBus(broker.url, MISSION, 0) as me:
            await me.wait_for(lambda: 7 in me.latest() and me.latest()[7].seq >= 3, 30)
            assert 7 not in me.lost
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            await me.wait_for(lambda: 7 in me.lost, 15)
            lost = me.latest()[7]
            assert lost.phase == Phase.LOST
            assert lost.x_m > 10.0 and lost.y_m == -1.0  # where it was last heard
            assert me.statuses[7].status == "lost"
            # A late joiner learns it from the retained status and last-seen state.
            async with MqttBus(broker.url, MISSION, 1) as late:
                await late.wait_for(lambda: 7 in late.lost and 7 in late.latest(), 10)
                assert late.latest()[7].phase == Phase.LOST
                assert abs(late.latest()[7].x_m - lost.x_m) < 1.0  # ≤ 1 s of travel older
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


async def test_clean_close_is_offline_not_lost(broker):
    async with MqttBus(broker.url, MISSION, 0) as me:
        await me.wait_connected(10)
        async with MqttBus(broker.url, MISSION, 4) as other:
            await other.wait_connected(10)
            await publish_until(other, me, 4, 1)
            other.publish(state(4, 2, phase=Phase.LANDED))
        await me.wait_for(lambda: me.statuses.get(4) and me.statuses[4].status == "offline", 10)
        assert 4 not in me.lost
        assert me.latest()[4].phase != Phase.LOST


async def test_broker_loss_drops_connected_and_recovers_with_backoff(broker):
    events: list[bool] = []
    bus = MqttBus(broker.url, MISSION, 0, backoff_initial_s=0.05, backoff_max_s=0.4)
    bus.add_connection_listener(events.append)
    async with bus, MqttBus(broker.url, MISSION, 1) as peer:
        await bus.wait_connected(10)
        await peer.wait_connected(10)
        await publish_until(bus, peer, 0, 1)

        broker.kill()
        await bus.wait_disconnected(10)
        assert not bus.connected and events == [True, False]
        # Every failed attempt doubles the wait, up to the maximum.
        await bus.wait_for(lambda: bus.stats.connect_failures >= 4, 30)
        assert bus.backoff_s == min(0.05 * 2**bus.stats.connect_failures, 0.4)
        # While disconnected a state is dropped, not queued for later.
        bus.publish(state(0, 100))
        assert bus.stats.dropped_offline == 1

        broker.restart(wait=False)
        await broker.wait_ready_async()
        await bus.wait_connected(30)
        await peer.wait_connected(30)
        assert events == [True, False, True]
        seen: list[int] = []
        got_101 = asyncio.Event()
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            await raw.subscribe(bus.topics.state(0))

            async def record():
                async for m in raw.messages:
                    seen.append(decode_state(m.payload).seq)
                    if seen[-1] == 101:
                        got_101.set()

            rec = asyncio.create_task(record())
            await publish_until(bus, peer, 0, 101)
            # the raw subscriber's copy may still be on its way when the peer has it
            await asyncio.wait_for(got_101.wait(), 10)
            rec.cancel()
        assert 100 not in seen and 101 in seen
        assert peer.latest()[0].seq == 101


async def test_stale_state_is_dropped_not_sent(broker):
    async with MqttBus(broker.url, MISSION, 0, max_publish_age_s=0.5) as bus:
        await bus.wait_connected(10)
        bus.publish(state(0, 1, age_s=2.0))
        await bus.wait_for(lambda: bus.stats.dropped_stale == 1, 10)
        assert bus.stats.published == 0


async def test_retained_config_survives_a_broker_restart(broker):
    cfg = MissionConfigMsg(MISSION, "run-1", "hash-1", 2, time.time(), "x.toml")
    async with MqttBus(broker.url, MISSION) as coord:
        await coord.wait_connected(10)
        coord.set_retained(coord.topics.config, encode_config(cfg))
        async with MqttBus(broker.url, MISSION, 0) as agent:
            await agent.wait_for(lambda: agent.config == cfg, 10)
        broker.kill()
        broker.restart(wait=False)  # mosquitto without persistence: retained messages gone
        await broker.wait_ready_async()
        await coord.wait_connected(30)
        async with MqttBus(broker.url, MISSION, 1) as late:
            await late.wait_for(lambda: late.config == cfg, 10)


async def test_wrong_vehicle_and_observer_publish_are_refused(broker):
    async with MqttBus(broker.url, MISSION, 0) as bus, MqttBus(broker.url, MISSION) as obs:
        with pytest.raises(ValueError, match="vehicle 3"):
            bus.publish(state(3, 1))
        with pytest.raises(RuntimeError, match="observer"):
            obs.publish(state(0, 1))


@pytest.mark.parametrize(
    "url, expected",
    [
        ("mqtt://127.0.0.1:1884", ("127.0.0.1", 1884, None, None)),
        ("mqtt://broker.local", ("broker.local", 1883, None, None)),
        ("10.0.0.2:1999", ("10.0.0.2", 1999, None, None)),
        ("mqtt://u:p@h:2", ("h", 2, "u", "p")),
    ],
)
def test_parse_broker_url(url, expected):
    assert parse_broker_url(url) == expected


@pytest.mark.parametrize(
    "url, match",
    [("http://h:1", "scheme 'http'"), ("mqtt://h:99999", "port"), ("mqtt://:1", "no host")],
)
def test_bad_broker_urls(url, match):
    with pytest.raises(BrokerUrlError, match=match):
        parse_broker_url(url)


def test_sanity_env():
    assert os.environ.get("MAVLINK20") == "1"


async def test_cells_limit_what_an_agent_hears(broker):
    """Square cells of 5 m: an agent hears the 3×3 cells around its own, a vehicle leaving
    them says so once, and a lost vehicle is known wherever it was last seen."""

    def at(vid: int, seq: int, x: float) -> NeighbourState:
        return NeighbourState(vid, x, 0.0, 1.0, 0.0, Phase.IN_TUBE, time.time(), seq)

    async with (
        MqttBus(broker.url, MISSION, 0, cell_m=5.0) as a,
        MqttBus(broker.url, MISSION, 1, cell_m=5.0) as b,
        MqttBus(broker.url, MISSION) as obs,
    ):
        for bus in (a, b, obs):
            await bus.wait_connected(10)

        async def put(bus: MqttBus, st: NeighbourState) -> None:
            # publish until the observer (subscribed to every cell) has it: then the broker
            # has routed it to every subscriber, and a sync shows what `a` got.
            while not (st.vehicle_id in obs.latest() and obs.latest()[st.vehicle_id].seq >= st.seq):
                bus.publish(dataclasses.replace(st, stamp_s=time.time()))
                with contextlib.suppress(TimeoutError):
                    await obs.wait_for(
                        lambda: (
                            obs.latest().get(st.vehicle_id) is not None
                            and obs.latest()[st.vehicle_id].seq >= st.seq
                        ),
                        0.2,
                    )
            await a.sync()

        await put(a, at(0, 1, 0.5))  # cell (0, 0): a's window is cells -1..1
        await put(b, at(1, 1, 100.0))  # cell (20, 0): far away
        assert 1 not in a.latest() and a.stats.received == 0
        await put(b, at(1, 2, 6.0))  # cell (1, 0): a neighbour cell
        assert a.latest()[1].x_m == 6.0
        await put(b, at(1, 3, 100.0))  # leaves: one copy goes to the old cell
        assert a.stats.received == 1 and a.stats.left_window == 1 and 1 not in a.latest()
        # b's agent is lost far away: a learns where it was last seen (retained)
        await b.close()  # (quietly: a live agent would answer a "lost" status with "online")
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            from vtube_fleet.bus.codec import Status, encode_status

            await raw.publish(a.topics.status(1), encode_status(Status(1, "lost")), qos=1)
        await a.wait_for(lambda: 1 in a.latest(), 10)
        assert a.latest()[1].phase == Phase.LOST and a.latest()[1].x_m == 100.0


async def test_a_hung_broker_shows_as_echo_silence_before_the_keepalive(broker):
    """SIGSTOP the broker: the TCP connection stays up, but our own states stop coming back."""
    async with MqttBus(broker.url, MISSION, 0, keepalive_s=30) as bus:
        await bus.wait_connected(10)
        stop = asyncio.Event()

        async def tick() -> None:  # the agent's 20 Hz publishing
            seq = 0
            while not stop.is_set():
                seq += 1
                bus.publish(state(0, seq))
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 0.05)

        ticker = asyncio.create_task(tick())
        try:
            await bus.wait_for(lambda: bus._echo_mono > -math.inf, 10)
            os.kill(broker.pid, signal.SIGSTOP)
            try:
                await bus.wait_for(lambda: bus.echo_silence_s > 0.5, 10)
                assert bus.connected  # the 30 s keep-alive has not noticed anything yet
            finally:
                os.kill(broker.pid, signal.SIGCONT)
            await bus.wait_for(lambda: bus.echo_silence_s < 0.2, 10)
        finally:
            stop.set()
            await ticker


async def test_a_waiter_cancelled_as_the_bus_changes_stays_cancelled():
    """A task waiting in ``wait_for`` that is cancelled in the same loop iteration as a bus
    change wakes it (an agent's barrier when the coordinator's abort arrives with a teammate's
    status) ends cancelled: it must not fly on. Python 3.11's ``asyncio.wait_for`` returned
    normally there and dropped the cancellation (an agent then flew the tube after an abort)."""
    bus = MqttBus("mqtt://127.0.0.1:1", MISSION)  # never connected: only its waiters
    done = {"v": False}
    waiter = asyncio.ensure_future(bus.wait_for(lambda: done["v"], None, poll_s=60.0))
    while bus._changed is None:  # the waiter is parked on its change event
        await asyncio.sleep(0)
    bus._changed.set()  # a change and the cancellation, in the same iteration
    waiter.cancel()
    done["v"] = True
    with pytest.raises(asyncio.CancelledError):
        await waiter
