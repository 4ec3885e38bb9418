"""Bus security against a real mosquitto: what agents accept (the attacks of issue 13 replayed
at bus level), and the secured broker ``vtube-fleet bus-setup`` writes (TLS, passwords, ACL).

Synchronisation is by markers, never by sleeping: a message published at QoS 1 has been routed
by the broker when its PUBACK returns, so a later :meth:`MqttBus.sync` (or a later marker from
the same client) arrives after it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import random
import ssl
import struct
import subprocess
import sys
import time
from pathlib import Path

import aiomqtt
import pytest
from broker import LocalBroker, free_port, require_tool
from missions import MOCK_FLEET

from vtube_fleet.bus.codec import (
    Command,
    Status,
    encode_command,
    encode_state,
    encode_status,
)
from vtube_fleet.bus.mqtt import BrokerUrlError, InsecureBrokerError, MqttBus
from vtube_fleet.bus.security import (
    BusCredentials,
    CredentialsError,
    SetupError,
    bus_setup,
    mosquitto_acl,
    mosquitto_hash,
    tls_context,
)
from vtube_fleet.bus.validate import StateLimits, mission_state_limits
from vtube_fleet.cli import main as cli_main
from vtube_fleet.state import NeighbourState, Phase


@pytest.fixture(autouse=True)
def _needs_mosquitto() -> None:
    """Every test here runs against a real mosquitto: skipped without it, FAILED under CI=true
    (tests/broker.py, require_tool)."""
    require_tool("mosquitto", "the secured-bus test")


MISSION = "sec"
#: A fleet of 8 in a 100 m square: what the observers and agents below accept.
LIMITS = StateLimits(vehicle_ids=frozenset(range(8)), region=(-100.0, 100.0, -100.0, 100.0))


def st(vid: int, seq: int, x: float = 1.0, y: float = 1.0, *, stamp: float | None = None,
       vx: float = 0.5, phase: Phase = Phase.IN_TUBE) -> NeighbourState:
    return NeighbourState(vid, x, y, vx, 0.0, phase, time.time() if stamp is None else stamp, seq)


@pytest.fixture
def broker():
    with LocalBroker(kind="mosquitto") as b:
        yield b


async def connected(*buses: MqttBus) -> None:
    for b in buses:
        await b.wait_connected(10)
        await b.sync()


async def put_real(bus: MqttBus, peer: MqttBus, state: NeighbourState) -> None:
    """Publish ``state`` (fresh stamps; QoS 0 may drop) until ``peer`` holds its seq."""
    import dataclasses

    vid = state.vehicle_id

    def has() -> bool:
        s = peer.latest().get(vid)
        return s is not None and s.seq >= state.seq

    loop = asyncio.get_running_loop()
    deadline = loop.time() + 10
    while not has():
        assert loop.time() < deadline, f"state {state} never reached the peer"
        bus.publish(dataclasses.replace(state, stamp_s=time.time()))
        with contextlib.suppress(TimeoutError):
            await peer.wait_for(has, 0.2)


# ------------------------------------------------------------------------------------------
# what an agent accepts (plain loopback broker: the bus's own checks, no ACL to help)
# ------------------------------------------------------------------------------------------
NOW = time.time


@pytest.mark.parametrize(
    "topic_id, payload, kind",
    [
        (1, lambda: encode_state(st(2, 1)), "id_mismatch"),  # vehicle 2's state on 1's topic
        (42, lambda: encode_state(st(42, 1)), "not_in_mission"),  # a fake vehicle 42
        (1, lambda: encode_state(st(1, 1, x=5000.0)), "region"),  # kilometres away
        (1, lambda: encode_state(st(1, 1, vx=900.0)), "speed"),
        (1, lambda: encode_state(st(1, 2**32 - 1, stamp=NOW() + 1e6)), "future"),
        (1, lambda: encode_state(st(1, 1))[:16] + struct.pack("<ffff", math.nan, 0, 0, 0),
         "malformed"),
        (1, lambda: encode_state(st(1, 1)) + b"x", "malformed"),
    ],
    ids=["id-mismatch", "vehicle-42", "km-away", "speed", "future-stamp", "nan", "size"],
)
async def test_implausible_states_are_refused_and_counted(broker, topic_id, payload, kind):
    async with MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me:
        await connected(me)
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            for _ in range(3):
                await raw.publish(me.topics.state(topic_id), payload(), qos=1)
        await me.sync()
        assert me.stats.refusals == {kind: 3} and me.stats.refused == 3
        assert me.latest() == {} and me.stats.received == 0
        sender = f"vehicle {topic_id}"
        assert me.refusal_counts() == {(sender, kind): 3}


async def test_a_seq_jump_is_refused_the_real_sequence_goes_on(broker):
    async with (MqttBus(broker.url, MISSION, 1, limits=LIMITS) as one,
                MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me):
        await connected(one, me)
        await put_real(one, me, st(1, 17))
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            await raw.publish(me.topics.state(1), encode_state(st(1, 2**32 - 1, x=-50.0)), qos=1)
        await me.sync()
        assert me.stats.refusals == {"seq_jump": 1}
        await put_real(one, me, st(1, 18, x=2.0))
        assert me.latest()[1].x_m == 2.0


async def test_spoofed_states_do_not_freeze_a_vehicle(broker, caplog):
    """Issue 13, attack 3: states for vehicle 1 with seq 2³²−1 and a stamp +10⁶ s at a fake
    spot, between its real ones. Every real state replaces the previous one; the fake ones are
    refused, and logged once."""
    caplog.set_level(logging.WARNING, logger="vtube_fleet.bus.mqtt")
    async with (MqttBus(broker.url, MISSION, 1, limits=LIMITS) as one,
                MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me,
                aiomqtt.Client(broker.host, broker.port) as raw):
        await connected(one, me)
        for k in range(1, 11):
            fake = st(1, 2**32 - 1, x=30.0, y=-3.0, stamp=time.time() + 1e6)
            await raw.publish(me.topics.state(1), encode_state(fake), qos=1)
            await put_real(one, me, st(1, k, x=0.5 * k))
            assert me.latest()[1].x_m == 0.5 * k and me.latest()[1].seq == k
        assert me.stats.refusals == {"future": 10}
    logged = [r for r in caplog.records if "refused" in r.getMessage()]
    assert len(logged) == 1 and "vehicle 1" in logged[0].getMessage()


async def test_a_fake_vehicle_42_is_never_flown_around(broker, caplog):
    """Issue 13, attack 5: a vehicle that is not in the mission, 2 m ahead of the leader."""
    caplog.set_level(logging.WARNING, logger="vtube_fleet.bus.mqtt")
    async with MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me:
        await connected(me)
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            for seq in range(1, 6):
                await raw.publish(me.topics.state(42), encode_state(st(42, seq, x=3.0)), qos=1)
            await raw.publish(me.topics.status(42), encode_status(Status(42, "online")),
                              qos=1, retain=True)
            await raw.publish(me.topics.last(42), encode_state(st(42, 9)), qos=1, retain=True)
            await raw.publish(me.topics.status(42), encode_status(Status(42, "lost")), qos=1)
        await me.sync()
        assert 42 not in me.latest() and 42 not in me.statuses and 42 not in me.lost
        assert me.stats.refusals == {"not_in_mission": 7}
    assert len([r for r in caplog.records if "vehicle 42" in r.getMessage()]) == 1


async def test_limits_follow_the_run(broker):
    """Once joined to a run of 3, vehicle 5 of the mission's 8 is no longer accepted."""
    async with MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me:
        await connected(me)
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            await raw.publish(me.topics.state(5), encode_state(st(5, 1)), qos=1)
            await me.sync()
            assert 5 in me.latest()
            me.set_limits(me.limits.with_vehicles(3))
            assert 5 not in me.latest()
            await raw.publish(me.topics.state(5), encode_state(st(5, 2)), qos=1)
        await me.sync()
        assert 5 not in me.latest() and me.stats.refusals == {"not_in_mission": 1}


async def _publish_forever(bus: MqttBus, vid: int, x: float) -> None:
    """A live agent: its state at 20 Hz (last-seen at ~1 Hz, by the bus)."""
    seq = 0
    while True:
        seq += 1
        bus.publish(st(vid, seq, x=x))
        await asyncio.sleep(0.05)  # the agent's control period (a publisher, not a wait)


async def _mute_agent(broker: LocalBroker, vid: int, x: float, online: asyncio.Event) -> None:
    """An agent that publishes like one (online, states at 20 Hz, last-seen at 2 Hz) but
    never reads its own status, so it cannot answer a forged ``lost`` with ``online``."""
    topics = MqttBus(broker.url, MISSION).topics
    async with aiomqtt.Client(broker.host, broker.port) as c:
        await c.publish(topics.status(vid), encode_status(Status(vid, "online")), qos=1,
                        retain=True)
        online.set()
        seq = 0
        while True:
            seq += 1
            payload = encode_state(st(vid, seq, x=x))
            await c.publish(topics.state(vid, (0, 0)), payload)
            if seq % 10 == 0:
                await c.publish(topics.last(vid), payload, retain=True)
            await asyncio.sleep(0.05)  # its control period (a publisher, not a wait)


@pytest.mark.parametrize("who", ["agent", "mute"])
async def test_a_retained_lost_for_a_live_vehicle_does_not_split_the_fleet(broker, who):
    """Issue 13, attack 4: one retained ``status/2 = lost`` while agent 2 is fine. An agent
    that hears 2's states (same cell), one that does not (2 is outside its cells: it hears only
    2's last-seen state) and one that connects later all keep 2 as a live vehicle. A real
    agent answers the forged status with ``online`` at once; one that cannot ("mute") is kept
    alive by its states: a claim of ``lost`` is refuted by any state stamped after it
    arrived."""
    async with (
        MqttBus(broker.url, MISSION, 2, cell_m=10.0, limits=LIMITS) as two,
        MqttBus(broker.url, MISSION, 0, cell_m=10.0, limits=LIMITS) as near,
        MqttBus(broker.url, MISSION, 1, cell_m=10.0, limits=LIMITS) as far,
    ):
        await connected(two, near, far)
        near.publish(st(0, 1, x=2.0))
        far.publish(st(1, 1, x=80.0))  # 2 (at x = 3) is 7 cells away
        online = asyncio.Event()
        if who == "agent":
            pub = asyncio.ensure_future(_publish_forever(two, 2, 3.0))
        else:
            await two.close()
            pub = asyncio.ensure_future(_mute_agent(broker, 2, 3.0, online))
            await online.wait()
        try:
            await near.wait_for(lambda: 2 in near.latest(), 10)
            await far.wait_for(lambda: getattr(far.statuses.get(2), "status", "") == "online",
                               10)
            async with aiomqtt.Client(broker.host, broker.port) as raw:
                await raw.publish(two.topics.status(2), encode_status(Status(2, "lost")),
                                  qos=1, retain=True)
            async with MqttBus(broker.url, MISSION, 3, limits=LIMITS) as late:
                buses = (near, far, late)
                if who == "mute":
                    for bus in buses:
                        await bus.wait_for(lambda b=bus: b.stats.refusals.get("lost_refuted"), 10)
                else:  # its own answer, retained: the late one reads only that
                    await late.sync()
                    for bus in (near, far):
                        await bus.wait_for(lambda b=bus: 2 not in b._claims, 10)  # noqa: SLF001
                for bus in buses:
                    assert 2 not in bus.lost, bus.vehicle_id
                    # (the mute one's only retained status is the forged one: the late agent
                    # knows no status of it, which is not "lost")
                    expect = None if (bus is late and who == "mute") else "online"
                    assert getattr(bus.statuses.get(2), "status", None) == expect
                    if who == "mute":
                        assert bus.stats.refusals == {"lost_refuted": 1}
                assert near.latest()[2].phase == Phase.IN_TUBE
                assert 2 not in far.latest()  # still outside its cells: not an obstacle
        finally:
            pub.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await pub


async def test_a_lost_vehicle_is_confirmed_by_its_silence(broker):
    """The same claim for a vehicle that stays silent: lost, at its last position, once
    ``lost_confirm_s`` has passed without a newer state."""
    async with (
        MqttBus(broker.url, MISSION, 2, limits=LIMITS) as two,
        MqttBus(broker.url, MISSION, 0, limits=LIMITS, lost_confirm_s=0.5) as me,
    ):
        await connected(two, me)
        await put_real(two, me, st(2, 1, x=4.0))
        await two.close()  # it goes silent (its goodbye says offline)
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            await raw.publish(me.topics.status(2), encode_status(Status(2, "lost")), qos=1)
        await me.wait_for(lambda: 2 in me.lost, 10)
        assert me.latest()[2].phase == Phase.LOST and me.latest()[2].x_m == 4.0
        assert me.statuses[2].status == "lost" and me.stats.refused == 0


async def test_commands_from_the_future_cannot_shadow_the_coordinator(broker):
    """A forged command with a huge seq would make every later real command look old."""
    async with MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me:
        await connected(me)
        now = time.time()
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            fake = Command("abort", MISSION, "r1", "h", int(now * 1000) + 10**9, now)
            await raw.publish(me.topics.cmd, encode_command(fake), qos=1)
            other = Command("abort", "other-mission", "r1", "h", int(now * 1000), now)
            await raw.publish(me.topics.cmd, encode_command(other), qos=1)
            real = Command("start", MISSION, "r1", "h", int(time.time() * 1000), time.time())
            await raw.publish(me.topics.cmd, encode_command(real), qos=1)
        await me.sync()
        assert me.command == real
        assert me.stats.refusals == {"future": 1, "wrong_mission": 1}


async def test_garbage_leaves_the_bus_working(broker):
    """Issue 13: 500 random, truncated, oversized payloads on every topic of the mission."""
    rng = random.Random(13)
    topics = ["state/0/0/1", "state/0/0/3", "last/1", "status/1", "config", "cmd",
              "state/x/0/1", "status/99999", "state/0/0/-1"]
    async with (MqttBus(broker.url, MISSION, 1, limits=LIMITS) as one,
                MqttBus(broker.url, MISSION, 0, limits=LIMITS) as me):
        await connected(one, me)
        async with aiomqtt.Client(broker.host, broker.port) as raw:
            for i in range(500):
                size = (1 << 20) if i % 100 == 0 else rng.choice([0, 1, 31, 32, 33, 64, 200])
                body = bytes(rng.getrandbits(8) for _ in range(min(size, 64)))
                body = body * (size // 64) if size > 64 else body  # 1 MB: 16 384 × 64 B
                await raw.publish(f"vtube/{MISSION}/{rng.choice(topics)}", body, qos=1)
        await me.sync()
        assert me.stats.refused > 0 and me.connected
        await put_real(one, me, st(1, 1))
        assert me.latest()[1].seq == 1


def test_mission_limits_cover_the_tube_and_the_slots():
    from vtube_fleet.config.mission import load_mission

    m = load_mission(MOCK_FLEET)
    lim = mission_state_limits(m)
    assert lim.vehicle_ids == frozenset(range(m.count))
    x0, x1, y0, y1 = lim.region
    for x, y in m.slots:
        assert x0 + 99 < x < x1 - 99 and y0 + 99 < y < y1 - 99
    far = st(0, 1, x=x1 + 1.0)
    assert lim.problem(far, None, time.time())[0] == "region"
    assert lim.problem(st(0, 1, x=float(m.slots[0][0]), y=float(m.slots[0][1])), None,
                       time.time()) is None


# ------------------------------------------------------------------------------------------
# broker URLs and credentials files
# ------------------------------------------------------------------------------------------
def test_a_plain_broker_on_the_network_is_refused_unless_insecure():
    with pytest.raises(InsecureBrokerError, match="not on this machine.*mqtts://.*--insecure"):
        MqttBus("mqtt://10.0.0.5:1883", MISSION, 0)
    MqttBus("mqtt://10.0.0.5:1883", MISSION, 0, insecure=True)
    MqttBus("mqtt://localhost:1883", MISSION, 0)
    MqttBus("mqtt://[::1]:1883", MISSION, 0)
    assert MqttBus("mqtts://10.0.0.5", MISSION, 0).port == 8883
    with pytest.raises(BrokerUrlError, match="--credentials"):
        MqttBus("mqtts://u:secret@10.0.0.5", MISSION, 0)


def test_credentials_files_are_checked(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('username = "vehicle-1"\npassword = "pw"\nca = "ca.crt"\n')
    os.chmod(f, 0o644)
    with pytest.raises(CredentialsError, match="readable by other users.*chmod 600"):
        BusCredentials.load(f)
    os.chmod(f, 0o600)
    with pytest.raises(CredentialsError, match="CA file .* not found"):
        BusCredentials.load(f)
    (tmp_path / "ca.crt").write_text("x")
    c = BusCredentials.load(f)
    assert (c.username, c.password, c.ca_file) == ("vehicle-1", "pw", tmp_path / "ca.crt")
    with pytest.raises(CredentialsError, match="cannot load the CA file"):
        tls_context(c.ca_file)
    f.write_text('username = "vehicle-1"\n')
    with pytest.raises(CredentialsError, match="needs username"):
        BusCredentials.load(f)
    with pytest.raises(CredentialsError, match="cannot read"):
        BusCredentials.load(tmp_path / "missing.toml")


def test_the_agent_command_refuses_a_plain_remote_broker(capsys):
    code = cli_main(["agent", str(MOCK_FLEET), "--vehicle", "0", "--broker",
                     "mqtt://192.0.2.7:1883", "--no-rerun"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error: broker 192.0.2.7:1883")


# ------------------------------------------------------------------------------------------
# bus-setup and the secured broker
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    return bus_setup(tmp_path_factory.mktemp("bus") / "setup", MISSION, 3, port=free_port(),
                     bind="127.0.0.1", hosts=["broker.test"])


@pytest.fixture
def secured(setup):
    with LocalBroker(config=setup.conf, ca_file=setup.ca_file) as b:
        yield b


def test_bus_setup_writes_private_keys_and_a_verifiable_certificate(setup):
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

    out = setup.out
    for name in ("ca.key", "server.key", "passwd", *(f"credentials/{u}.toml" for u in
                                                    ("coordinator", "vehicle-0", "vehicle-2"))):
        assert (out / name).stat().st_mode & 0o077 == 0, name
    ca = x509.load_pem_x509_certificate((out / "ca.crt").read_bytes())
    srv = x509.load_pem_x509_certificate((out / "server.crt").read_bytes())
    ca.public_key().verify(srv.signature, srv.tbs_certificate_bytes,
                           ec.ECDSA(srv.signature_hash_algorithm))
    san = srv.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {"localhost", "broker.test"} <= set(san.get_values_for_type(x509.DNSName))
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    conf = setup.conf.read_text()
    assert "allow_anonymous false" in conf and f"listener {setup.port} 127.0.0.1" in conf
    assert "listener" not in conf.split("certfile")[1]  # no plain listener unless asked
    users = [line.split(":")[0] for line in setup.passwd.read_text().splitlines()]
    assert users == ["coordinator", "vehicle-0", "vehicle-1", "vehicle-2"]
    assert BusCredentials.load(setup.vehicle_credentials(1)).ca_file == setup.ca_file


def test_the_acl_gives_each_vehicle_its_own_topics_only():
    acl = mosquitto_acl("m", 2)
    blocks = {b.splitlines()[0]: b.splitlines()[1:] for b in acl.split("\n\n")[1:]}
    assert [x for x in blocks["user vehicle-1"] if "write" in x] == [
        "topic write vtube/m/state/+/+/1", "topic write vtube/m/status/1",
        "topic write vtube/m/last/1", "topic write vtube/m/clock/ask/1"]
    assert "topic read vtube/m/clock/echo/1" in blocks["user vehicle-1"]
    assert not any("clock/echo/0" in x for x in blocks["user vehicle-1"])
    writes = [x for x in blocks["user coordinator"] if "write" in x]
    assert writes == ["topic readwrite vtube/m/config", "topic readwrite vtube/m/cmd",
                      "topic write vtube/m/clock/echo/+"]
    assert "topic read vtube/m/clock/ask/+" in blocks["user coordinator"]


def test_bus_setup_never_overwrites_and_offers_plain_loopback_only(tmp_path, capsys):
    out = tmp_path / "b"
    assert cli_main(["bus-setup", str(MOCK_FLEET), "--out", str(out), "--vehicles", "2",
                     "--plain-loopback", "1884"]) == 0
    assert "listener 1884 127.0.0.1" in (out / "mosquitto.conf").read_text()
    assert (out / "credentials" / "vehicle-1.toml").is_file()
    assert not (out / "credentials" / "vehicle-2.toml").exists()
    capsys.readouterr()
    assert cli_main(["bus-setup", str(MOCK_FLEET), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "never overwrites keys" in err[0]
    with pytest.raises(SetupError, match="cannot go into a certificate"):
        bus_setup(tmp_path / "c", "m", 1, hosts=["a b"])


async def test_the_builtin_password_hash_is_accepted_by_mosquitto(tmp_path):
    s = bus_setup(tmp_path / "b", MISSION, 1, port=free_port(), bind="127.0.0.1",
                  passwd_tool=None)
    assert s.hashed_by.endswith("mosquitto_hash")
    creds = BusCredentials.load(s.vehicle_credentials(0))
    with LocalBroker(config=s.conf, ca_file=s.ca_file) as b:
        ctx = tls_context(s.ca_file)
        async with aiomqtt.Client(b.host, b.port, username=creds.username,
                                  password=creds.password, tls_context=ctx):
            pass
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(b.host, b.port, username=creds.username,
                                      password=creds.password + "x", tls_context=ctx):
                pass
    assert mosquitto_hash("pw", salt=b"\0" * 12).startswith("$7$101$AAAAAAAAAAAAAAAA$")


def test_the_builtin_hash_verifies_like_mosquitto_passwd(tmp_path):
    """mosquitto_passwd's own hash of a password, recomputed with its salt."""
    passwd = require_tool("mosquitto_passwd", "comparing the hash with mosquitto_passwd's")
    import base64

    f = tmp_path / "pw"
    f.write_text("u:secret\n")
    subprocess.run([passwd, "-U", str(f)], check=True)
    _, _, it, salt, _ = f.read_text().strip().split(":", 1)[1].split("$")
    assert mosquitto_hash("secret", salt=base64.b64decode(salt), iterations=int(it)) == \
        f.read_text().strip().split(":", 1)[1]


async def test_clients_without_valid_credentials_or_trust_cannot_connect(setup, secured):
    creds = BusCredentials.load(setup.vehicle_credentials(0))
    ctx = tls_context(setup.ca_file)
    attempts = {
        "anonymous": dict(tls_context=ctx),
        "wrong password": dict(username=creds.username, password="guess", tls_context=ctx),
        "plain TCP to the TLS port": dict(username=creds.username, password=creds.password),
        "a CA that did not sign it": dict(username=creds.username, password=creds.password,
                                          tls_context=ssl.create_default_context()),
    }
    for what, kw in attempts.items():
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(secured.host, secured.port, timeout=5, **kw):
                pytest.fail(f"{what}: connected")
    async with aiomqtt.Client(secured.host, secured.port, username=creds.username,
                              password=creds.password, tls_context=ctx):
        pass
    rogue = MqttBus(secured.url, MISSION, 1)  # verifies with the system's CAs: refused
    async with rogue:
        with pytest.raises(TimeoutError):
            await rogue.wait_connected(1.0)
        assert "CERTIFICATE_VERIFY_FAILED" in (rogue.last_error or "")


async def test_an_agent_cannot_publish_for_another_vehicle_or_the_coordinator(setup, secured):
    """The ACL: vehicle 1's client publishes vehicle 2's state, status and last-seen state, a
    start command and a config, then its own state as a marker. The coordinator, subscribed
    to everything, receives the marker and nothing before it."""
    ctx = tls_context(setup.ca_file)
    c1 = BusCredentials.load(setup.vehicle_credentials(1))
    co = BusCredentials.load(setup.coordinator_credentials)
    base = f"vtube/{MISSION}"
    now = time.time()
    start = encode_command(Command("start", MISSION, "r", "h", int(now * 1000), now))
    forged = [
        (f"{base}/state/0/0/2", encode_state(st(2, 1))),
        (f"{base}/status/2", encode_status(Status(2, "lost"))),
        (f"{base}/last/2", encode_state(st(2, 1))),
        (f"{base}/cmd", start),
        (f"{base}/config", b'{"v":1}'),
        (f"{base}/other", b"x"),
    ]
    async with (
        aiomqtt.Client(secured.host, secured.port, username=co.username, password=co.password,
                       tls_context=ctx, identifier="watcher") as watcher,
        aiomqtt.Client(secured.host, secured.port, username=c1.username, password=c1.password,
                       tls_context=ctx) as one,
    ):
        await watcher.subscribe(f"{base}/#", qos=1)
        for topic, payload in forged:
            await one.publish(topic, payload, qos=1)
        marker = encode_state(st(1, 99))
        await one.publish(f"{base}/state/0/0/1", marker, qos=1)
        got = []
        async with asyncio.timeout(10):
            async for msg in watcher.messages:
                got.append(msg.topic.value)
                if msg.payload == marker:
                    break
        assert got == [f"{base}/state/0/0/1"]
        # and the coordinator may command: vehicle 1 hears it
        await one.subscribe(f"{base}/cmd", qos=1)
        await watcher.publish(f"{base}/cmd", start, qos=1)
        async with asyncio.timeout(10):
            async for msg in one.messages:
                assert msg.topic.value == f"{base}/cmd" and msg.payload == start
                break


async def test_mqtt_buses_fly_over_tls_with_credentials(setup, secured):
    """Agents and the coordinator through the secured broker: states, presence, commands."""
    async with (
        MqttBus(secured.url, MISSION, 0, credentials=setup.vehicle_credentials(0),
                limits=LIMITS) as a,
        MqttBus(secured.url, MISSION, 1, credentials=setup.vehicle_credentials(1),
                limits=LIMITS) as b,
        MqttBus(secured.url, MISSION, credentials=setup.coordinator_credentials,
                limits=LIMITS) as co,
    ):
        await connected(a, b, co)
        await put_real(a, b, st(0, 1))
        await put_real(b, a, st(1, 1))
        await put_real(a, co, st(0, 2))
        await co.wait_for(lambda: {0, 1} <= set(co.statuses), 10)
        now = time.time()
        cmd = Command("start", MISSION, "r", "h", int(now * 1000), now)
        co.set_retained(co.topics.cmd, encode_command(cmd))
        await a.wait_for(lambda: a.command == cmd, 10)
        await b.wait_for(lambda: b.command == cmd, 10)


def test_the_bus_setup_command_prints_how_to_use_it(tmp_path):
    r = subprocess.run([sys.executable, "-m", "vtube_fleet", "bus-setup", str(MOCK_FLEET),
                        "--out", str(tmp_path / "x"), "--vehicles", "1", "--host", "gw.lan"],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    assert r.returncode == 0, r.stderr
    assert "--broker mqtts://gw.lan:8883 --credentials" in r.stdout


# ------------------------------------------------------------------------------------------
# the attacks during a flight (agent processes, mock vehicles, truth; slow)
# ------------------------------------------------------------------------------------------
async def _attack_in_flight(run, n: int, client: aiomqtt.Client, stop: asyncio.Event,
                            sent: dict[str, int]) -> None:
    """Issue 13's bus attacks, 10 times a second, 2 m ahead of the lead vehicle: vehicle 1's
    state with seq 2³²−1 and stamp +10⁶ s, a fake vehicle 42, vehicle 2's state on vehicle 1's
    topic, a state kilometres away, garbage; once, a retained ``status/2 = lost``."""
    from vtube_fleet.bus.topics import MissionTopics
    from vtube_fleet.fleet.distributed.coordinator import (
        default_max_age_s,
        default_mission_id,
        run_cell_m,
    )

    t = MissionTopics(default_mission_id(run.path))
    cell = run_cell_m(run.mission, default_max_age_s(run.mission))
    await client.publish(t.status(2), encode_status(Status(2, "lost")), qos=1, retain=True)
    sent["lost"] = 1
    rng = random.Random(13)
    k = 0
    while not stop.is_set():
        k += 1
        latest = run.observer.latest()
        lead = max((s for v, s in latest.items() if v < n), key=lambda s: s.x_m)
        fx, fy = lead.x_m + 2.0, lead.y_m
        c = (math.floor(fx / cell), math.floor(fy / cell))
        now = time.time()
        for topic, payload in (
            (t.state(1, c), encode_state(st(1, 2**32 - 1, fx, fy, stamp=now + 1e6, vx=0.0))),
            (t.state(42, c), encode_state(st(42, k, fx, fy, vx=0.0))),
            (t.state(1, c), encode_state(st(2, k, fx, fy, vx=0.0))),
            (t.state(3, c), encode_state(st(3, k, 5000.0, fy))),
            (t.state(3, c), bytes(rng.getrandbits(8) for _ in range(rng.choice([3, 32, 40])))),
        ):
            await client.publish(topic, payload)
            sent["states"] = sent.get("states", 0) + 1
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 0.1)  # the attack's period


@pytest.mark.slow
@pytest.mark.timeout(300)
async def test_bus_attacks_during_a_flight_leave_it_unchanged(tmp_path):
    """On a plain broker (no ACL to help: the agents' own checks), the attacks from the lead
    vehicle's first 5 m in the tube to the end: every vehicle exits and lands, nobody is
    lost, and the TRUE clearances hold; the agents log the refusals once per sender."""
    from test_agent_process import (
        all_in_tube_past,
        check_safety,
        finish,
        fleet_run,
        short_mock_fleet,
        start_coordinator,
        summary,
        until,
    )

    n = 4
    sent: dict[str, int] = {}
    async with fleet_run(tmp_path, n, short_mock_fleet(tmp_path)) as run:
        coord = await start_coordinator(run, n)
        await until(lambda: all_in_tube_past(run, n, 5.0), 120, "all vehicles in the tube")
        stop = asyncio.Event()
        async with aiomqtt.Client(run.broker.host, run.broker.port) as attacker:
            attack = asyncio.ensure_future(_attack_in_flight(run, n, attacker, stop, sent))
            try:
                code, err = await finish(coord)
            finally:
                stop.set()
                await attack
        codes = [await p.wait() for p in run.agents]
    assert code == 0, err
    assert codes == [0] * n, [run.log_text(i)[-1500:] for i, c in enumerate(codes) if c]
    s = summary(run)
    assert s["outcome"] == "completed" and s["exited"] == n and s["lost"] == []
    assert s["violations"] == 0
    assert sent["states"] > 50
    logs = [run.log_text(i) for i in range(n)]
    assert any("refused a message from vehicle 42" in g for g in logs)
    for g in logs:
        assert g.count("refused a message from vehicle 42 ") <= 1  # once per sender
        assert "vehicle 2 lost" not in g
    worst = check_safety(run)
    print(f"\nunder attack ({sent['states']} forged messages): pair {worst['pair']:.3f} m, "
          f"obstacle clearance {worst['obstacle']:.3f} m, legs {worst['leg']:.3f} m")


@pytest.mark.slow
@pytest.mark.timeout(300)
async def test_a_compromised_agent_account_cannot_steer_the_secured_fleet(tmp_path):
    """Through the secured broker: a client with vehicle 3's credentials, before any
    coordinator runs, announces a rogue run (the mission's real id and config hash) and
    starts it, to idle agents; then, in flight, reads the run id and hash from the retained
    config and publishes an abort, a fake config, vehicle 1's state 2 m ahead of the leader and
    ``status/2 = lost``. The ACL drops all of it: no agent joins the rogue run, the real run
    completes."""
    from test_agent_process import (
        all_in_tube_past,
        check_safety,
        finish,
        fleet_run,
        short_mock_fleet,
        start_coordinator,
        summary,
        until,
    )

    from vtube_fleet.bus.codec import MissionConfigMsg, decode_config, encode_config
    from vtube_fleet.fleet.distributed.coordinator import default_mission_id

    n = 4
    async with fleet_run(tmp_path, n, short_mock_fleet(tmp_path), secured=True) as run:
        three = BusCredentials.load(run.setup.vehicle_credentials(3))
        t = run.observer.topics
        # every agent subscribed and idle, waiting for a run: a rogue run would reach them now
        await until(lambda: all("waiting for `vtube-fleet mission start" in run.log_text(i)
                                for i in range(n)), 60, "every agent waiting for a run")
        async with aiomqtt.Client(run.broker.host, run.broker.port, username=three.username,
                                  password=three.password, identifier="intruder-idle",
                                  tls_context=tls_context(three.ca_file)) as c:
            now = time.time()
            rogue_cfg = MissionConfigMsg(default_mission_id(run.path), "rogue",
                                         run.mission.config_hash, n, now, run.path.name)
            await c.publish(t.config, encode_config(rogue_cfg), qos=1, retain=True)
            start = Command("start", rogue_cfg.mission_id, "rogue", rogue_cfg.config_hash,
                            int(now * 1000), now)
            await c.publish(t.cmd, encode_command(start), qos=1, retain=True)
        coord = await start_coordinator(run, n)
        await until(lambda: all_in_tube_past(run, n, 5.0), 120, "all vehicles in the tube")
        async with aiomqtt.Client(run.broker.host, run.broker.port, username=three.username,
                                  password=three.password, identifier="intruder",
                                  tls_context=tls_context(three.ca_file)) as c:
            await c.subscribe(t.config, qos=1)
            async with asyncio.timeout(10):
                async for msg in c.messages:
                    cfg = decode_config(bytes(msg.payload))
                    break
            now = time.time()
            abort = Command("abort", cfg.mission_id, cfg.run_id, cfg.config_hash,
                            int(now * 1000), now)
            await c.publish(t.cmd, encode_command(abort), qos=1, retain=True)
            import dataclasses

            rogue = dataclasses.replace(cfg, run_id="rogue", stamp_s=now)
            await c.publish(t.config, encode_config(rogue), qos=1, retain=True)
            await c.publish(t.status(2), encode_status(Status(2, "lost")), qos=1, retain=True)
            lead = max(run.observer.latest().values(), key=lambda s: s.x_m)
            for k in range(20):
                await c.publish(t.state(1, (0, 0)),
                                encode_state(st(1, 10**6 + k, lead.x_m + 2, lead.y_m)), qos=1)
        code, err = await finish(coord)
        codes = [await p.wait() for p in run.agents]
    assert code == 0, err
    assert codes == [0] * n, [run.log_text(i)[-1500:] for i, c in enumerate(codes) if c]
    s = summary(run)
    assert s["outcome"] == "completed" and s["exited"] == n and s["lost"] == []
    for i in range(n):  # each agent joined the coordinator's run only, never the rogue one
        log = run.log_text(i)
        assert "joined run rogue" not in log and f"joined run {s['run_id']}" in log, log[-1500:]
    check_safety(run)


async def test_the_mission_command_takes_credentials(tmp_path, capsys):
    """``mission status --broker mqtts://… --credentials FILE``; without the file it is a
    one-line error naming why the broker refused."""
    s = bus_setup(tmp_path / "bus", "mock_fleet", 2, port=free_port(), bind="127.0.0.1")
    with LocalBroker(config=s.conf, ca_file=s.ca_file) as b:
        args = ["mission", "status", str(MOCK_FLEET), "--broker", b.url, "--listen", "0.1"]
        code = await asyncio.to_thread(
            cli_main, [*args, "--credentials", str(s.coordinator_credentials)])
        out = capsys.readouterr().out
        assert code == 0 and "no run announced" in out
        code = await asyncio.to_thread(cli_main, [*args, "--broker-timeout", "2"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and err[-1].startswith("error: cannot reach the MQTT broker")
        assert "CERTIFICATE_VERIFY_FAILED" in err[-1]
