"""MAVLink 2 signing (issue 13): key files, the persistent timestamp, the mock enforcing
signing like PX4 >= 1.18 (sim_stub/signing.py), the signed ``mavlink`` link and sign-setup.

Everything on the wire is real UDP on loopback. The "attacker" and the reference sender use
pymavlink's own signing (an implementation independent of the mock's and of ours). To know
that the mock has handled the datagrams sent before, a test sends a *signed* REQUEST_MESSAGE
from the same socket and waits for its COMMAND_ACK: loopback UDP from one socket to another
keeps order, and the mock handles datagrams one after another.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import stat
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mav

from tests.gcs_wait import first_message
from tests.missions import straight_mission, write_mission
from vtube_fleet.errors import UserError
from vtube_fleet.link import LinkError, LinkTimeout, MavlinkLink, open_links
from vtube_fleet.link.signing import (
    LinkSigning,
    SigningError,
    TimestampStore,
    fleet_signing,
    generate_key,
    load_key,
    sign_setup,
    signing_timestamp,
)

sim_stub = pytest.importorskip("sim_stub")
from sim_stub import MockVehicle  # noqa: E402
from sim_stub.ports import free_port_scheme  # noqa: E402

pytestmark = pytest.mark.timeout(120)

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))
CMD_ARM, CMD_SET_MODE, CMD_REQUEST_MESSAGE = 400, 176, 512
MSG_AUTOPILOT_VERSION = 148


def vehicle(**kw) -> MockVehicle:
    kw.setdefault("boot_time_scale", 0.2)
    kw.setdefault("estimator", "ideal")
    return MockVehicle(0, ports=free_port_scheme(1), **kw)


def mav_signer(key: bytes | None, timestamp: int | None = None) -> mav.MAVLink:
    m = mav.MAVLink(None, 255, 190)
    if key is not None:
        m.signing.secret_key = key
        m.signing.sign_outgoing = True
        m.signing.link_id = 0
        m.signing.timestamp = signing_timestamp() if timestamp is None else timestamp
    return m


class Gcs(asyncio.DatagramProtocol):
    """Raw MAVLink over UDP to one mock; verifies what it receives with ``rx_key``."""

    def __init__(self, v: MockVehicle, rx_key: bytes | None) -> None:
        self.v = v
        self.rx = mav.MAVLink(None, 255, 190)
        self.rx.robust_parsing = True
        if rx_key is not None:
            self.rx.signing.secret_key = rx_key
            self.rx.signing.allow_unsigned_callback = lambda m, msgid: False
        self.msgs: list[object] = []
        self.signed_rx = 0
        self.unsigned_rx = 0
        self._new = asyncio.Event()
        self.transport: asyncio.DatagramTransport | None = None
        self.good = mav_signer(KEY)

    async def __aenter__(self) -> Gcs:
        loop = asyncio.get_running_loop()
        self.transport, _ = await loop.create_datagram_endpoint(
            lambda: self, local_addr=self.v.gcs_address)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.transport is not None
        self.transport.close()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if data[0] == 0xFD:
            if data[2] & 1:
                self.signed_rx += 1
            else:
                self.unsigned_rx += 1
        for m in self.rx.parse_buffer(data) or []:
            if m.get_type() != "BAD_DATA":
                self.msgs.append(m)
        self._new.set()

    def send(self, msg: object, signer: mav.MAVLink) -> bytes:
        buf = msg.pack(signer)  # type: ignore[attr-defined]
        signer.seq = (signer.seq + 1) & 0xFF
        assert self.transport is not None
        self.transport.sendto(buf, self.v.bind_address)
        return buf

    def raw(self, buf: bytes) -> None:
        assert self.transport is not None
        self.transport.sendto(buf, self.v.bind_address)

    async def wait(self, pred, timeout: float = 10.0, what: str = "") -> object:
        return await first_message(self.msgs, self._new, pred, since=len(self.msgs),
                                   timeout=timeout, what=what)

    async def command(self, cmd: int, *params: float, signer: mav.MAVLink | None = None
                      ) -> tuple[object, bytes]:
        p = list(params) + [0.0] * (7 - len(params))
        fut = asyncio.ensure_future(self.wait(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd, what=f"ACK {cmd}"))
        await asyncio.sleep(0)  # the waiter is registered before the answer can arrive
        buf = self.send(mav.MAVLink_command_long_message(self.v.sysid, 1, cmd, 0, *p),
                        signer or self.good)
        return await fut, buf

    async def barrier(self) -> None:
        """Everything sent before has been handled (see the module docstring)."""
        await self.command(CMD_REQUEST_MESSAGE, MSG_AUTOPILOT_VERSION)

    async def ready(self) -> None:
        await self.wait(lambda m: m.get_type() == "HEARTBEAT" and m.system_status == 3,
                        what="STANDBY HEARTBEAT")


def attacks(g: Gcs, signer: mav.MAVLink) -> None:
    """Arm, switch to OFFBOARD, stream a setpoint: what an attacker on the network would."""
    sysid = g.v.sysid
    g.send(mav.MAVLink_command_long_message(sysid, 1, CMD_ARM, 0, 1, 21196, 0, 0, 0, 0, 0),
           signer)
    g.send(mav.MAVLink_command_long_message(sysid, 1, CMD_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0),
           signer)
    g.send(mav.MAVLink_set_position_target_local_ned_message(
        0, sysid, 1, 1, 3527, 0, 0, 0, 5.0, 0, 0, 0, 0, 0, 0, 0), signer)


# ----------------------------------------------------------------------------------------------
# key files and the timestamp store
# ----------------------------------------------------------------------------------------------
def test_key_file_rules(tmp_path: Path) -> None:
    p = tmp_path / "fleet.key"
    key = generate_key(p)
    assert stat.S_IMODE(p.stat().st_mode) == 0o600 and load_key(p) == key
    with pytest.raises(SigningError, match="exists already"):
        generate_key(p)
    os.chmod(p, 0o644)
    with pytest.raises(SigningError, match=r"mode 0644 .*chmod 600"):
        load_key(p)
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    os.chmod(hexed, 0o600)
    assert load_key(hexed) == KEY
    for data, why in ((b"x" * 31, "got 31 bytes"), (bytes(32), "all zeros")):
        bad = tmp_path / "bad.key"
        bad.write_bytes(data)
        os.chmod(bad, 0o600)
        with pytest.raises(SigningError, match=why):
            load_key(bad)
    with pytest.raises(SigningError, match="no such file"):
        load_key(tmp_path / "missing.key")


def test_timestamp_store_never_goes_backwards(tmp_path: Path) -> None:
    clock = [1.8e9]
    path = tmp_path / "k.timestamp"
    a = TimestampStore(path, wall=lambda: clock[0])
    first = a.start()
    assert first == signing_timestamp(clock[0])
    last = first
    for k in range(1, 300_001, 1000):  # 3 s of packets in 10 µs steps: a few leases
        last = first + k
        a.ensure(last)
    assert 2 <= a.writes <= 6, "the mark is written once per lease, not per packet"
    clock[0] -= 3600.0  # the wall clock jumps back an hour, then the process restarts
    b = TimestampStore(path, wall=lambda: clock[0])
    assert b.start() > last
    os.chmod(path, 0o644)
    with pytest.raises(SigningError, match="chmod 600"):
        TimestampStore(path).start()


# ----------------------------------------------------------------------------------------------
# the mock enforces signing (PX4 >= 1.18)
# ----------------------------------------------------------------------------------------------
async def test_unsigned_and_wrongly_signed_commands_are_ignored() -> None:
    async with vehicle(signing=KEY) as v, Gcs(v, rx_key=KEY) as g:
        await g.ready()  # a HEARTBEAT that verified with KEY
        attacks(g, mav_signer(None))
        attacks(g, mav_signer(OTHER_KEY))
        await g.barrier()
        assert v.signing is not None
        assert v.signing.dropped["unsigned"] == 3
        assert v.signing.dropped["bad_signature"] == 3
        assert v.commands[CMD_ARM] == 0 and v.commands[CMD_SET_MODE] == 0
        assert not v.armed and not v.sp_ever and v.mode_name == "AUTO.LOITER"
        # everything the mock sent verified with the key (the rx parser refuses the rest)
        assert g.unsigned_rx == 0 and g.signed_rx > 0 and g.rx.signing.badsig_count == 0


async def test_replayed_signed_arm_is_rejected() -> None:
    async with vehicle(signing=KEY) as v, Gcs(v, rx_key=KEY) as g:
        await g.ready()
        for _ in range(40):  # PX4 refuses to arm in its first seconds (pre-arm checks)
            ack, arm_packet = await g.command(CMD_ARM, 1.0)
            if ack.result == 0:  # type: ignore[attr-defined]
                break
            await asyncio.sleep(0.25)  # back-off between attempts
        assert v.armed
        ack, _ = await g.command(CMD_ARM, 0.0)
        assert ack.result == 0 and not v.armed  # type: ignore[attr-defined]
        assert v.signing is not None
        stale = v.signing.dropped["stale"]
        g.raw(arm_packet)  # the attacker replays the recorded, validly signed ARM
        await g.barrier()
        assert not v.armed
        assert v.signing.dropped["stale"] == stale + 1


async def test_setup_signing_only_when_disarmed_and_only_once_unsigned() -> None:
    async with vehicle(signing=True) as v, Gcs(v, rx_key=None) as g:
        await g.ready()
        assert v.signing is not None and not v.signing.active
        plain = mav_signer(None)
        for _ in range(40):
            ack, _ = await g.command(CMD_ARM, 1.0, signer=plain)
            if ack.result == 0:  # type: ignore[attr-defined]
                break
            await asyncio.sleep(0.25)
        assert v.armed
        g.send(mav.MAVLink_setup_signing_message(v.sysid, 1, list(KEY), signing_timestamp()),
               plain)
        await g.command(CMD_REQUEST_MESSAGE, MSG_AUTOPILOT_VERSION, signer=plain)
        assert not v.signing.active and v.signing.dropped["setup_armed"] == 1
        await g.command(CMD_ARM, 0.0, signer=plain)
        assert not v.armed
        g.send(mav.MAVLink_setup_signing_message(v.sysid, 1, list(KEY), signing_timestamp()),
               plain)
        await g.barrier()  # signed with KEY: accepted only because the key is now set
        assert v.signing.key == KEY
        # an attacker's unsigned SETUP_SIGNING (a key of their own, or blank) is refused
        g.send(mav.MAVLink_setup_signing_message(0, 0, list(OTHER_KEY), 1), plain)
        g.send(mav.MAVLink_setup_signing_message(0, 0, [0] * 32, 0), plain)
        await g.barrier()
        assert v.signing.key == KEY and v.signing.dropped["unsigned"] == 2


# ----------------------------------------------------------------------------------------------
# the signed link, sign-setup, restarts
# ----------------------------------------------------------------------------------------------
def signed_mission(tmp_path: Path, key: bytes = KEY):
    keyfile = tmp_path / "fleet.key"
    keyfile.write_bytes(key)
    os.chmod(keyfile, 0o600)
    return write_mission(tmp_path, straight_mission(
        30.0, [[2.0, 0.0]], extra='signing_key_file = "fleet.key"\n'))


async def test_sign_setup_then_a_signed_link_flies_and_an_unsigned_one_cannot(
        tmp_path: Path) -> None:
    mission = signed_mission(tmp_path)
    async with vehicle(signing=True) as v:
        ep = f"udpin://{v.gcs_address[0]}:{v.gcs_address[1]}"
        done = await sign_setup(mission, [ep], timeout_s=10.0)
        assert v.signing is not None and v.signing.key == KEY
        assert done[0].sysid == v.sysid and done[0].key_file.endswith("fleet.key")

        async with open_links([ep]) as links:  # no signing: its commands are dropped
            plain = links[0]
            await plain.open()
            await plain.wait_until(lambda s: s.last_heartbeat_s is not None, 10.0, "HEARTBEAT")
            dropped = v.signing.dropped["unsigned"]
            with pytest.raises(LinkTimeout, match="no COMMAND_ACK"):
                await plain.arm(timeout_s=2.0)
            assert not v.armed and v.signing.dropped["unsigned"] > dropped

        sg = fleet_signing(mission)
        async with open_links([ep], signing=sg) as links:
            link = links[0]
            assert isinstance(link, MavlinkLink) and link.signing is sg[0]
            await link.connect(timeout_s=10.0)
            await link.arm(timeout_s=15.0, retry_interval_s=0.25)
            await link.wait_ready(timeout_s=20.0)
            await link.takeoff(2.0)
            await link.wait_until(lambda s: s.down_m < -1.5, 30.0, "1.5 m climb")
            assert v.armed and v.position_ned[2] < -1.5  # the truth, not the link's view
            assert link.signing_refused.total() == 0
        with pytest.raises(SigningError, match="armed"):  # flying: PX4 refuses, so do we
            await sign_setup(mission, [ep], timeout_s=5.0)
        assert v.armed and v.signing.key == KEY and v.signing.dropped["stale"] == 0


async def test_timestamp_survives_a_link_restart(tmp_path: Path) -> None:
    clock = [signing_timestamp() / 100_000 + 1420070400]
    store_file = tmp_path / "k.timestamp"
    async with vehicle(signing=KEY) as v:
        # udpout: the link speaks first (HEARTBEAT), so nothing it receives can lift its
        # timestamp before the vehicle judges it; the mock answers only a sender it accepted
        ep = f"udpout://{v.bind_address[0]}:{v.bind_address[1]}"

        async def session(store: TimestampStore) -> str:
            link = MavlinkLink(ep, message_rates_hz={}, command_tries=2,
                               signing=LinkSigning(KEY, store))
            try:
                await link.connect(timeout_s=10.0)
                return await link.command_long(CMD_REQUEST_MESSAGE, MSG_AUTOPILOT_VERSION,
                                               raise_on_reject=False)
            finally:
                await link.close()

        assert await session(TimestampStore(store_file, wall=lambda: clock[0])) == "ACCEPTED"
        clock[0] -= 600.0  # the wall clock goes back 10 minutes, the link restarts
        assert await session(TimestampStore(store_file, wall=lambda: clock[0])) == "ACCEPTED"
        assert v.signing is not None and v.signing.dropped["stale"] == 0
        # control: without the stored mark the same restart sends old timestamps, which the
        # vehicle refuses (until the allow-listed HEARTBEAT gets through, the vehicle answers
        # and the link's timestamp follows the vehicle's: MAVLink's own recovery)
        store_file.unlink()
        await session(TimestampStore(store_file, wall=lambda: clock[0]))
        assert v.signing.dropped["stale"] > 0


async def test_mavsdk_backend_refuses_a_signing_mission(tmp_path: Path) -> None:
    sg = fleet_signing(signed_mission(tmp_path))
    with pytest.raises(LinkError, match=r"mavsdk backend cannot .*--backend mavlink"):
        async with open_links(["udpin://127.0.0.1:14540"], "mavsdk", signing=sg):
            pass


def test_sign_setup_cli_refuses_cleanly(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    from vtube_fleet.cli import main

    signed_mission(tmp_path)
    os.chmod(tmp_path / "fleet.key", 0o644)
    rc = main(["sign-setup", str(tmp_path / "mission.toml"), "--endpoints",
               "udpin://127.0.0.1:1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "chmod 600" in err, err
    assert issubclass(SigningError, UserError)


async def test_key_rotation_needs_the_current_key(tmp_path: Path) -> None:
    mission = signed_mission(tmp_path)  # the new key: KEY
    old = tmp_path / "old.key"
    old.write_bytes(OTHER_KEY)
    os.chmod(old, 0o600)
    async with vehicle(signing=OTHER_KEY) as v:
        ep = f"udpin://{v.gcs_address[0]}:{v.gcs_address[1]}"
        with pytest.raises(SigningError, match="did not sign with the new key"):
            await sign_setup(mission, [ep], timeout_s=3.0)  # signed with KEY: refused
        assert v.signing is not None and v.signing.key == OTHER_KEY
        assert v.signing.dropped["bad_signature"] > 0
        await sign_setup(mission, [ep], timeout_s=10.0, current_key_file=str(old))
        assert v.signing.key == KEY


async def test_a_signed_mission_flies_through_the_tube(tmp_path: Path) -> None:
    """The whole supervisor flight (preflight, fence upload, arm, take-off, the tube, landing)
    over a signed link, against a mock that accepts nothing unsigned."""
    from vtube_fleet.fleet.launch import fly

    mission = write_mission(tmp_path, straight_mission(
        12.0, [[3.0, 0.0]], extra='signing_key_file = "fleet.key"\n'))
    keyfile = tmp_path / "fleet.key"
    keyfile.write_bytes(KEY)
    os.chmod(keyfile, 0o600)
    lat, lon, alt = (float(x) for x in mission.slot_geodetic()[0])
    async with vehicle(signing=KEY, home=(lat, lon, alt), boot_time_scale=0.3) as v:
        ep = f"udpin://{v.gcs_address[0]}:{v.gcs_address[1]}"
        result = await fly(mission, endpoints=[ep], sysids=[v.sysid], out_dir=tmp_path)
        assert v.signing is not None and v.signing.accepted_signed > 100
        assert v.signing.dropped.total() == 0
        assert any(armed for _, _, armed in v.mode_log)  # the truth: it did arm and fly,
        north, east, _ = v.position_ned
        assert math.hypot(north, east) > 8.0  # from x = 3 m past the line at x = 12 m
    assert result.outcome == "completed", result.reason
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["mavlink_signing"] == {"enabled": True, "refused": {}}


async def test_the_built_in_mock_holds_a_signing_missions_keys(tmp_path: Path) -> None:
    """`run` without endpoints flies the built-in mock: its vehicles hold the mission's keys
    (as after sign-setup), so an unsigned link is refused and the mission's signed link arms."""
    from vtube_fleet.fleet.launch import mock_fleet

    mission = write_mission(tmp_path, straight_mission(
        12.0, [[3.0, 0.0]], extra='signing_key_file = "fleet.key"\n'))
    keyfile = tmp_path / "fleet.key"
    keyfile.write_bytes(KEY)
    os.chmod(keyfile, 0o600)
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_port_scheme(1)) as fleet:
        v = fleet.vehicles[0]
        assert v.signing is not None and v.signing.key == KEY
        link = MavlinkLink(fleet.endpoints[0], sysid=v.sysid, signing=fleet_signing(mission)[0])
        try:
            await link.connect(15.0)
            await link.arm(timeout_s=15.0, retry_interval_s=0.25)
        finally:
            await link.close()
        assert v.armed and v.signing.accepted_signed > 0
