"""sim_stub's PX4 rules over real UDP, driven by a small pymavlink GCS (one vehicle per test).

These tests are about behaviour, not boot timing: they run the mock with ``boot_time_scale=0.2``
(documented option; ready ~0.9 s after start instead of ~4.3 s) and short auto-disarm/takeoff
parameters to keep the suite quick. Every wait is on a message or a state, with a timeout.
"""

from __future__ import annotations

import asyncio
import math
import random
import struct
from collections.abc import Callable

import pytest
from pymavlink.dialects.v20 import common as mav

from sim_stub import Faults, MockFleet, MockVehicle
from sim_stub.codec import DatagramParser
from sim_stub.geo import project
from sim_stub.ports import free_port_scheme
from tests.gcs_wait import first_message

pytestmark = pytest.mark.timeout(120)

SCALE = 0.2
ACCEPTED, TEMP_REJECTED, DENIED, UNSUPPORTED = 0, 1, 2, 3
VEL_ONLY = 3527  # SET_POSITION_TARGET_LOCAL_NED type_mask: velocity only, no yaw
VEL_YAW = 0xDC7 & ~0x400  # velocity + yaw


class Gcs(asyncio.DatagramProtocol):
    """Receives everything the vehicle sends (decoded), sends MAVLink as sysid 255 / compid 190."""

    def __init__(self, vehicle: MockVehicle, bind: tuple[str, int] | None = None,
                 to: tuple[str, int] | None = None, sysid: int = 255) -> None:
        self.v = vehicle
        self.bind = bind or vehicle.gcs_address
        self.to = to or vehicle.bind_address
        self.mav = mav.MAVLink(None, sysid, 190)
        self.rx = mav.MAVLink(None, sysid, 190)
        self.rx.robust_parsing = True
        self.msgs: list[tuple[float, object]] = []
        self.datagrams = 0
        self.seqs: list[int] = []  # MAVLink seq of every datagram received
        self._new = asyncio.Event()
        self.transport: asyncio.DatagramTransport | None = None

    async def __aenter__(self) -> Gcs:
        loop = asyncio.get_running_loop()
        self.transport, _ = await loop.create_datagram_endpoint(lambda: self, local_addr=self.bind)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.transport is not None
        self.transport.close()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.datagrams += 1
        self.seqs.append(data[4] if len(data) > 4 else -1)
        t = asyncio.get_running_loop().time()
        for m in self.rx.parse_buffer(data) or []:
            self.msgs.append((t, m))
        self._new.set()

    def mark(self) -> int:
        return len(self.msgs)

    async def wait(
        self, pred: Callable[[object], bool], timeout: float = 10.0, since: int = 0, what: str = ""
    ) -> object:
        """First message (at index >= since) satisfying ``pred``."""
        return await first_message(self.msgs, self._new, pred, since=since, timeout=timeout,
                                   what=what, message=lambda e: e[1])

    async def wait_type(self, name: str, pred=lambda m: True, **kw) -> object:
        return await self.wait(lambda m: m.get_type() == name and pred(m), what=name, **kw)

    async def until(self, cond: Callable[[], bool], timeout: float = 20.0, what: str = "") -> None:
        """Wait (on incoming telemetry) until ``cond()`` holds."""

        async def loop() -> None:
            while not cond():
                self._new.clear()
                await self._new.wait()

        try:
            await asyncio.wait_for(loop(), timeout)
        except TimeoutError:
            raise AssertionError(f"not reached within {timeout} s: {what}") from None

    def send(self, msg: object) -> None:
        assert self.transport is not None
        self.transport.sendto(msg.pack(self.mav), self.to)  # type: ignore[attr-defined]

    async def command(self, cmd: int, *params: float, int_: bool = False, target: int | None = None,
                      comp: int = 1) -> object:  # fmt: skip
        p = list(params) + [0.0] * (7 - len(params))
        tgt = self.v.sysid if target is None else target
        since = self.mark()
        if int_:
            lat, lon = int(p[4] * 1e7), int(p[5] * 1e7)
            self.send(
                mav.MAVLink_command_int_message(tgt, comp, 0, cmd, 0, 0, *p[:4], lat, lon, p[6])
            )
        else:
            self.send(mav.MAVLink_command_long_message(tgt, comp, cmd, 0, *p))
        return await self.wait_type("COMMAND_ACK", lambda m: m.command == cmd, since=since)

    def setpoint(self, vx=0.0, vy=0.0, vz=0.0, *, mask=VEL_ONLY, frame=1, x=0.0, y=0.0, z=0.0,
                 yaw=0.0) -> None:  # fmt: skip
        self.send(mav.MAVLink_set_position_target_local_ned_message(
            0, self.v.sysid, 1, frame, mask, x, y, z, vx, vy, vz, 0, 0, 0, yaw, 0))  # fmt: skip

    def heartbeats(self, since: int = 0) -> list[object]:
        return [m for _, m in self.msgs[since:] if m.get_type() == "HEARTBEAT"]

    def texts(self) -> list[str]:
        return [m.text for _, m in self.msgs if m.get_type() == "STATUSTEXT"]


class Streamer:
    """A 20 Hz setpoint stream (the control loop of a GCS; the sleep is its period)."""

    def __init__(self, gcs: Gcs) -> None:
        self.gcs = gcs
        self.kw: dict = {}
        self.task: asyncio.Task | None = None

    async def _run(self) -> None:
        while True:
            self.gcs.setpoint(**self.kw)
            await asyncio.sleep(0.05)

    def __enter__(self) -> Streamer:
        self.task = asyncio.get_running_loop().create_task(self._run())
        return self

    def __exit__(self, *exc: object) -> None:
        assert self.task is not None
        self.task.cancel()


def vehicle(**kw) -> MockVehicle:
    """Vehicle 0 for behaviour tests: the estimate is the truth (``estimator="ideal"``), so
    positions can be checked exactly; the error profiles have their own tests."""
    kw.setdefault("boot_time_scale", SCALE)
    kw.setdefault("estimator", "ideal")
    return MockVehicle(0, ports=free_port_scheme(1), **kw)


async def ready(gcs: Gcs) -> None:
    await gcs.wait_type("HEARTBEAT", lambda m: m.system_status == 3, timeout=10)


async def test_commands_acks_and_px4_rules() -> None:
    # PX4's own boot times (scale 1): the arm below must land in the not-yet-healthy seconds,
    # which at SCALE are 0.6 s, short enough for a loaded machine to miss
    async with vehicle(params={"COM_DISARM_PRFLT": 1.0}, boot_time_scale=1.0) as v, Gcs(v) as g:
        await g.wait_type("HEARTBEAT")
        # arming is rejected for the first seconds after boot, with PX4's 2-chunk STATUSTEXT
        ack = await g.command(400, 1)
        assert ack.result == TEMP_REJECTED and ack.target_system == 255
        assert ack.target_component == 190 and ack.progress == 0 and ack.result_param2 == 0
        assert "Arming denied: Resolve system health failures firs" in g.texts()
        await ready(g)
        for int_ in (False, True):
            assert (await g.command(31999, 1, 2, 3, 4, 5, 6, 7, int_=int_)).result == UNSUPPORTED
        assert (await g.command(400, 0)).result == ACCEPTED  # disarm while disarmed
        # OFFBOARD without setpoints: ACCEPTED, heartbeat base_mode 1 / UNINIT, not armable
        mark = g.mark()
        assert (await g.command(176, 1, 6)).result == ACCEPTED
        await g.wait_type("HEARTBEAT", lambda m: (m.base_mode, m.system_status) == (1, 0),
                          since=mark)  # fmt: skip
        assert (await g.command(400, 1)).result == TEMP_REJECTED
        # Hold: armable; armed heartbeat 157 / ACTIVE
        assert (await g.command(176, 1, 4, 3)).result == ACCEPTED
        await ready(g)
        mark = g.mark()
        assert (await g.command(400, 1)).result == ACCEPTED
        await g.wait_type("HEARTBEAT", lambda m: (m.base_mode, m.system_status) == (157, 4),
                          since=mark)  # fmt: skip
        # armed: a mode that cannot run (POSCTL needs RC) is refused with PX4's text
        assert (await g.command(176, 1, 3)).result == TEMP_REJECTED
        assert "Switching to Position is currently not available\t" in g.texts()
        assert (await g.command(176, 1, 4, 99)).result == TEMP_REJECTED
        assert "Unsupported auto mode\t" in g.texts()
        # a command for another system is not answered (the next ACK is for the next command)
        ignored = v.counters.rx_ignored
        mark = g.mark()
        g.send(mav.MAVLink_command_long_message(9, 1, 400, 0, 0, 0, 0, 0, 0, 0, 0))
        ack = await g.command(512, 148)
        assert ack.result == ACCEPTED
        assert [m.command for _, m in g.msgs[mark:] if m.get_type() == "COMMAND_ACK"] == [512]
        assert v.counters.rx_ignored == ignored + 1
        # armed on the ground without taking off: auto-disarm (COM_DISARM_PRFLT, here 1 s)
        await g.wait_type(
            "STATUSTEXT", lambda m: m.text == "Disarmed by auto preflight disarming\t"
        )
        mark = g.mark()
        await g.wait_type("HEARTBEAT", lambda m: m.base_mode == 29, since=mark)
        assert not v.armed and v.mode_name == "AUTO.LOITER"


async def test_message_requests_and_intervals() -> None:
    async with vehicle() as v, Gcs(v) as g:
        # home and origin exist from the boot's "origin" stage on (the one unsolicited
        # GPS_GLOBAL_ORIGIN); before it, PX4 denies HOME_POSITION and GPS_GLOBAL_ORIGIN requests
        await g.wait_type("GPS_GLOBAL_ORIGIN")
        for msgid, name in ((148, "AUTOPILOT_VERSION"), (242, "HOME_POSITION"),
                            (49, "GPS_GLOBAL_ORIGIN")):  # fmt: skip
            mark = g.mark()
            ack = await g.command(512, msgid)
            assert ack.result == ACCEPTED
            after = [m.get_type() for _, m in g.msgs[mark:]]
            # the requested message arrives before its ACK (capture: 1-3 ms before)
            assert name in after[: after.index("COMMAND_ACK")]
        caps = [m for _, m in g.msgs if m.get_type() == "AUTOPILOT_VERSION"][0].capabilities
        assert (
            caps & 8 and caps & 16 and caps & 8192
        )  # COMMAND_INT, PARAM_ENCODE_BYTEWISE, MAVLINK2
        assert (await g.command(512, 9999)).result == DENIED
        assert (await g.command(511, 32, 20000)).result == ACCEPTED
        assert v.stream_rates()["LOCAL_POSITION_NED"] == pytest.approx(50.0)
        mark = g.mark()
        assert (await g.command(510, 32)).result == ACCEPTED
        mi = await g.wait_type("MESSAGE_INTERVAL", since=mark)
        assert (mi.message_id, mi.interval_us) == (32, 20000)
        assert (await g.command(511, 32, -1)).result == ACCEPTED  # off
        assert v.stream_rates()["LOCAL_POSITION_NED"] == 0.0
        assert (await g.command(511, 32, 0)).result == ACCEPTED  # default again (PX4: 30 Hz)
        assert v.stream_rates()["LOCAL_POSITION_NED"] == pytest.approx(30.0)
        assert (await g.command(511, 9999, 1000)).result == DENIED
        mark = g.mark()
        ack = await g.command(511, 242, 1e6)  # like the capture: one HOME_POSITION before the ACK
        after = [m.get_type() for _, m in g.msgs[mark:]]
        assert ack.result == ACCEPTED and "HOME_POSITION" in after[: after.index("COMMAND_ACK")]


async def test_parameter_protocol() -> None:
    async with vehicle() as v, Gcs(v) as g:
        await g.wait_type("HEARTBEAT")

        async def read(name: str | None = None, index: int = -1) -> object:
            mark = g.mark()
            pid = (name or "").encode()
            g.send(mav.MAVLink_param_request_read_message(v.sysid, 1, pid, index))
            return await g.wait_type("PARAM_VALUE", since=mark)

        p = await read("COM_OBL_RC_ACT")
        assert (p.param_type, p.param_value) == (6, 0.0)
        count = p.param_count
        p = await read("COM_RC_IN_MODE")
        assert p.param_type == 6 and p.param_value == pytest.approx(1.401298464324817e-45)
        by_index = await read(index=p.param_index)
        assert by_index.param_id == "COM_RC_IN_MODE"
        # a nonexistent name gets no reply at all: the next reply is for the next request
        mark = g.mark()
        g.send(mav.MAVLink_param_request_read_message(v.sysid, 1, b"COM_DISARM_PRELAND", -1))
        p = await read("MIS_TAKEOFF_ALT")
        assert [m.param_id for _, m in g.msgs[mark:] if m.get_type() == "PARAM_VALUE"] == [
            "MIS_TAKEOFF_ALT"
        ]
        # set: REAL32 and INT32 (bytewise), echoed as PARAM_VALUE, and used by the vehicle
        mark = g.mark()
        g.send(mav.MAVLink_param_set_message(v.sysid, 1, b"COM_OF_LOSS_T", 2.5, 9))
        p = await g.wait_type("PARAM_VALUE", since=mark)
        assert (p.param_id, p.param_value) == ("COM_OF_LOSS_T", 2.5)
        assert v.params["COM_OF_LOSS_T"].value == 2.5
        mark = g.mark()
        raw = struct.unpack("<f", struct.pack("<i", 4))[0]  # PX4 packs INT32 bytewise
        g.send(mav.MAVLink_param_set_message(v.sysid, 1, b"COM_OBL_RC_ACT", raw, 6))
        p = await g.wait_type("PARAM_VALUE", since=mark)
        assert p.param_value == pytest.approx(raw) and v.params["COM_OBL_RC_ACT"].value == 4
        mark = g.mark()
        g.send(mav.MAVLink_param_set_message(v.sysid, 1, b"NO_SUCH_PARAM", 1.0, 9))
        t = await g.wait_type("STATUSTEXT", since=mark)
        assert t.text == "[pm] unknown param: NO_SUCH_PARAM\t"
        mark = g.mark()
        g.send(mav.MAVLink_param_request_list_message(v.sysid, 1))
        await g.until(
            lambda: sum(1 for _, m in g.msgs[mark:] if m.get_type() == "PARAM_VALUE") == count,
            what="the whole list",
        )
        got = [m for _, m in g.msgs[mark:] if m.get_type() == "PARAM_VALUE"]
        assert sorted(m.param_index for m in got) == list(range(count))


async def test_takeoff_offboard_frames_and_land() -> None:
    params = {"MIS_TAKEOFF_ALT": 2.0}
    async with vehicle(params=params) as v, Gcs(v) as g:
        await ready(g)
        assert (await g.command(400, 1)).result == ACCEPTED
        assert (await g.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)).result == 0
        assert v.mode_name == "AUTO.TAKEOFF"
        await g.wait_type("STATUSTEXT", lambda m: m.text == "Takeoff detected\t")
        await g.wait_type("EXTENDED_SYS_STATE", lambda m: m.landed_state == 2)
        # NaN altitude → MIS_TAKEOFF_ALT; PX4 then switches to Hold
        await g.wait_type("HEARTBEAT", lambda m: m.custom_mode == 50593792, timeout=30)
        await g.until(lambda: abs(v.position_ned[2] + 2.0) < 0.15, what="hold at 2 m")
        st = Streamer(g)
        with st:
            # heading east via a LOCAL_NED setpoint with yaw, then BODY_NED forward = east
            st.kw = {"mask": VEL_YAW, "yaw": math.pi / 2}
            # armed, PX4 only switches to OFFBOARD once setpoints are streaming
            assert (await g.command(176, 1, 6)).result == TEMP_REJECTED
            await g.until(lambda: v.sp_fresh, what="setpoints received")
            assert (await g.command(176, 1, 6)).result == ACCEPTED
            await g.until(lambda: abs(v._yaw() - math.pi / 2) < 0.05, what="yaw 90°")
            e0 = v.position_ned[1]
            st.kw = {"vx": 1.0, "frame": 8}
            await g.until(lambda: v.position_ned[1] > e0 + 1.5, what="1.5 m east in BODY_NED")
            assert abs(v.velocity_ned[0]) < 0.3
            # a position setpoint (velocity ignored): flies there
            st.kw = {"mask": 0xDF8, "x": 1.0, "y": 1.0, "z": -2.5}
            await g.until(
                lambda: math.dist(v.position_ned, (1.0, 1.0, -2.5)) < 0.4, what="position sp"
            )
            tgt = await g.wait_type("POSITION_TARGET_LOCAL_NED", since=g.mark())
            assert tgt.type_mask & 0x7 == 0 and tgt.x == pytest.approx(1.0)
            mark = g.mark()
            assert (await g.command(21)).result == ACCEPTED
            assert "Landing at current position\t" in g.texts()
        await g.wait_type("STATUSTEXT", lambda m: m.text == "Landing detected\t", since=mark,
                          timeout=30)  # fmt: skip
        await g.wait_type("STATUSTEXT", lambda m: m.text == "Disarmed by landing\t", since=mark)
        assert v.position_ned[2] == 0.0 and not v.armed
        # home was re-set to the landing point
        home = await g.wait_type("HOME_POSITION", since=g.mark(), timeout=5)
        assert home.x == pytest.approx(v.position_ned[0], abs=0.05)


async def test_offboard_loss_failsafe_and_recovery() -> None:
    async with vehicle() as v, Gcs(v) as g:
        await g.wait_type("HEARTBEAT")
        st = Streamer(g)
        with st:
            st.kw = {"vz": -1.5}
            assert (await g.command(176, 1, 6)).result == ACCEPTED
            await ready(g)
            assert (await g.command(400, 1)).result == ACCEPTED
            await g.until(lambda: v.position_ned[2] < -2.0, what="2 m climb")
            st.kw = {}
        # setpoints stop; ~COM_OF_LOSS_T later PX4's failsafe: POSCTL, CRITICAL, descent
        mark = g.mark()
        await g.wait_type("STATUSTEXT", lambda m: m.text == "Failsafe activated\t" and
                          m.severity == 2, since=mark)  # fmt: skip
        await g.wait_type("HEARTBEAT", lambda m: (m.custom_mode, m.base_mode, m.system_status)
                          == (196608, 209, 5), since=mark)  # fmt: skip
        await g.until(lambda: v.velocity_ned[2] > 0.4, what="descending")
        # the setpoints come back: the mode fallback clears, OFFBOARD again (PX4 failsafe rules)
        with Streamer(g) as st2:
            st2.kw = {}
            await g.until(lambda: v.mode_name == "OFFBOARD", what="back in OFFBOARD")
            # with COM_OBL_RC_ACT = 4 (Land) the next loss lands instead
            mark = g.mark()
            raw = struct.unpack("<f", struct.pack("<i", 4))[0]
            g.send(mav.MAVLink_param_set_message(v.sysid, 1, b"COM_OBL_RC_ACT", raw, 6))
            await g.wait_type("PARAM_VALUE", since=mark)
        await g.until(lambda: v.mode_name == "AUTO.LAND", what="failsafe Land")
        await g.wait_type("STATUSTEXT", lambda m: m.text == "Disarmed by landing\t", timeout=30)
        mark = g.mark()
        await g.wait_type("HEARTBEAT", since=mark)
        hb = await g.wait_type("HEARTBEAT", since=g.mark())
        assert (hb.custom_mode, hb.base_mode, hb.system_status) == (393216, 17, 0)


async def test_answers_whoever_last_sent() -> None:
    v = vehicle()
    async with v, Gcs(v) as a:
        other = free_port_scheme(1)
        async with Gcs(v, bind=(other.host, other.gcs_port(0))) as b:
            await a.wait_type("HEARTBEAT")
            assert (await b.command(512, 148)).result == ACCEPTED  # answered to B
            mark = b.mark()
            await b.wait_type("HEARTBEAT", since=mark)  # and the stream follows B
            assert (await a.command(512, 148)).result == ACCEPTED
            n = a.mark()
            await a.wait_type("HEARTBEAT", since=n)


async def test_malformed_truncated_and_foreign_datagrams_never_stall() -> None:
    rng = random.Random(7)
    async with vehicle() as v, Gcs(v) as g:
        await g.wait_type("HEARTBEAT")
        good = mav.MAVLink_command_long_message(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0).pack(g.mav)
        garbage = [rng.randbytes(rng.randrange(1, 300)) for _ in range(200)]
        garbage += [good[:n] for n in range(1, len(good))]  # every truncation
        bad_crc = bytearray(good)
        bad_crc[-2] ^= 0x55
        garbage.append(bytes(bad_crc))
        parser = DatagramParser()
        expect_malformed = sum(1 for d in garbage if parser.parse(d)[1])
        expect_unknown = sum(parser.parse(d)[2] for d in garbage)
        for d in garbage:
            g.transport.sendto(d, v.bind_address)
        # a foreign valid message (a heartbeat from another vehicle's id) is fine too
        ack = await g.command(512, 148)  # still answers, in order, after the junk
        assert ack.result == ACCEPTED
        c = v.counters
        assert c.rx_malformed == expect_malformed and c.rx_unknown == expect_unknown
        assert c.rx_datagrams >= len(garbage) + 1
        mark = g.mark()
        await g.wait_type("ATTITUDE", since=mark)  # streams continue
        assert rng.random() >= 0  # (the junk was seeded: reproducible)


async def test_kill_silent_and_freeze() -> None:
    async with MockFleet(2, port_scheme=free_port_scheme(2), boot_time_scale=SCALE,
                         estimator="ideal") as f:
        v0, v1 = f.vehicles
        async with Gcs(v0) as g0, Gcs(v1) as g1:
            await g0.wait_type("HEARTBEAT")
            await g1.wait_type("HEARTBEAT")
            # freeze vehicle 1 in flight: keeps streaming, holds position, ignores commands
            st = Streamer(g1)
            with st:
                st.kw = {"vz": -1.5}
                assert (await g1.command(176, 1, 6)).result == ACCEPTED
                await ready(g1)
                assert (await g1.command(400, 1)).result == ACCEPTED
                await g1.until(lambda: v1.position_ned[2] < -1.0, what="airborne")
                st.kw = {"vx": 1.0}
                await g1.until(lambda: v1.velocity_ned[0] > 0.3, what="moving north")
                f.kill(1, "freeze")
                frozen_at = v1.position_ned
                mark = g1.mark()
                g1.send(mav.MAVLink_command_long_message(2, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0))
                for _ in range(2):
                    await g1.wait_type("HEARTBEAT", since=g1.mark())
                assert not [m for _, m in g1.msgs[mark:] if m.get_type() == "COMMAND_ACK"]
                lpn = [m for _, m in g1.msgs[mark:] if m.get_type() == "LOCAL_POSITION_NED"]
                assert len(lpn) > 10 and all(
                    (m.x, m.y, m.z) == pytest.approx(frozen_at, abs=1e-3) for m in lpn[2:]
                )
                assert v1.armed and v1.position_ned == frozen_at
            # kill vehicle 0 silently: nothing it generates after the kill reaches the GCS
            f.kill(0, "silent")
            t_kill_ms = v0._tboot_ms(v0._now())
            dropped = v0.counters.rx_dropped
            g0.send(mav.MAVLink_command_long_message(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0))
            await g1.until(lambda: v0.counters.rx_dropped > dropped, what="probe dropped")
            await g1.until(lambda: v0.uptime * 1000 > t_kill_ms + 1500, what="1.5 s later")
            late = [
                m for _, m in g0.msgs
                if hasattr(m, "time_boot_ms") and m.time_boot_ms > t_kill_ms + 50
            ]  # fmt: skip
            assert not late
            assert f.vehicles[0].dead == "silent" and f.vehicles[1].dead == "freeze"


async def test_link_faults_loss_latency_and_gps_noise() -> None:
    faults = [
        Faults(loss_pct=30.0),
        Faults(latency_s=0.2, die_at_s=3.0, die_how="silent"),
        Faults(gps_noise_m=1.0),
    ]
    async with MockFleet(3, port_scheme=free_port_scheme(3), faults=faults,
                         boot_time_scale=SCALE, seed=3, estimator="ideal") as f:  # fmt: skip
        lossy, slow, noisy = f.vehicles
        async with Gcs(lossy) as gl, Gcs(slow) as gs, Gcs(noisy) as gn:
            # loss: PX4's seq still advances, so the GCS sees the gaps
            await gl.until(lambda: len(gl.msgs) > 400, what="400 packets")
            seqs = gl.seqs
            gaps = sum((b - a - 1) % 256 for a, b in zip(seqs, seqs[1:], strict=False))
            assert 0.15 < gaps / (gaps + len(seqs)) < 0.45
            assert lossy.counters.tx_dropped > 0
            # latency: the command is held by the vehicle before it is processed, then answered
            await gs.wait_type("HEARTBEAT")
            since = gs.mark()
            before = slow.counters.rx_datagrams
            t_sent = asyncio.get_running_loop().time()
            gs.send(mav.MAVLink_command_long_message(2, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0))
            ack = await gs.wait_type("COMMAND_ACK", since=since)
            (t_ack,) = [t for t, m in gs.msgs[since:] if m is ack]
            # held by the vehicle for latency_s before it was processed (a lower bound: a loaded
            # machine only adds to it), and it did arrive
            assert t_ack - t_sent >= 0.2 and slow.counters.rx_datagrams > before
            # die_at_s: the link dies by itself
            await gn.until(lambda: slow.dead == "silent", 10.0, "death at 3 s")
            # GPS noise: the reported position wanders while the vehicle sits at its origin,
            # consistently in the local and the global position
            await gn.until(lambda: len([m for _, m in gn.msgs if m.get_type() ==
                                        "GLOBAL_POSITION_INT"]) > 20, what="positions")  # fmt: skip
            lpn = {m.time_boot_ms: m for _, m in gn.msgs if m.get_type() == "LOCAL_POSITION_NED"}
            assert max(math.hypot(m.x, m.y) for m in lpn.values()) > 0.05
            assert noisy.position_ned == (0.0, 0.0, 0.0)
            lat0, lon0, _ = noisy.origin
            for _, g in gn.msgs:
                if g.get_type() == "GLOBAL_POSITION_INT" and g.time_boot_ms in lpn:
                    x, y = project(lat0, lon0, g.lat / 1e7, g.lon / 1e7)
                    m = lpn[g.time_boot_ms]
                    assert abs(x - m.x) < 0.03 and abs(y - m.y) < 0.03


async def barrier(g: Gcs, k: int) -> None:
    """A PING request answered by the vehicle: everything sent before it has been handled."""
    since = g.mark()
    g.send(mav.MAVLink_ping_message(123, k & 0xFFFFFFFF, 0, 0))
    await g.wait_type("PING", lambda m: m.target_system == 255 and m.seq == k & 0xFFFFFFFF,
                      since=since)  # fmt: skip


async def test_fuzzed_valid_messages_never_break_the_vehicle() -> None:
    """3000 well-framed messages with random/extreme fields (NaN, ±inf, 1e30, random frames,
    masks, commands, parameter names and types): no handler or tick error, still answering."""
    rng = random.Random(11)
    specials = [0.0, -0.0, 1.0, -1.0, 1e30, -1e30, math.inf, -math.inf, math.nan, 21196.0, 4.0,
                6.0, 242.0, 32.0, 1e6]  # fmt: skip

    def f() -> float:
        return rng.choice(specials) if rng.random() < 0.5 else rng.uniform(-1e3, 1e3)

    names = [b"COM_OF_LOSS_T", b"COM_OBL_RC_ACT", b"MPC_XY_VEL_MAX", b"MIS_TAKEOFF_ALT", b"X" * 16]
    commands = [400, 176, 22, 21, 20, 192, 178, 179, 510, 511, 512, 519, 31999]
    async with vehicle() as v, Gcs(v) as g:
        await ready(g)
        s = v.sysid
        for k in range(3000):
            kind = rng.randrange(6)
            cmd = rng.choice(commands) if rng.random() < 0.9 else rng.randrange(65536)
            if kind == 0:
                msg = mav.MAVLink_command_long_message(s, rng.choice([0, 1]), cmd, 0,
                                                       *(f() for _ in range(7)))  # fmt: skip
            elif kind == 1:
                ll = [rng.randrange(-(2**31), 2**31) for _ in range(2)]
                p4 = [f() for _ in range(4)]
                frame = rng.randrange(256)
                msg = mav.MAVLink_command_int_message(s, 1, frame, cmd, 0, 0, *p4, *ll, f())
            elif kind == 2:
                frame = rng.choice([1, 7, 8, 9, rng.randrange(256)])
                msg = mav.MAVLink_set_position_target_local_ned_message(
                    0, s, 1, frame, rng.randrange(65536), *(f() for _ in range(11)))  # fmt: skip
            elif kind == 3:
                ll = [rng.randrange(-(2**31), 2**31) for _ in range(2)]
                msg = mav.MAVLink_set_position_target_global_int_message(
                    0, s, 1, rng.choice([0, 3, 5, 6, 11]), rng.randrange(65536), *ll,
                    *(f() for _ in range(9)))  # fmt: skip
            elif kind == 4:
                ptype = rng.choice([6, 9, rng.randrange(256)])
                msg = mav.MAVLink_param_set_message(s, 1, rng.choice(names), f(), ptype)
            else:
                msg = mav.MAVLink_param_request_read_message(s, 1, rng.choice(names),
                                                             rng.randrange(-1, 100))  # fmt: skip
            g.send(msg)
            if k % 100 == 99:  # let the vehicle catch up: a PING round trip every 100 messages
                await barrier(g, k)
        await barrier(g, -1)
        mark = g.mark()
        assert (await g.command(520)).result == ACCEPTED
        await g.wait_type("HEARTBEAT", since=mark)  # (other streams may have been switched off)
        assert v.counters.rx_datagrams >= 3000
        assert v.counters.rx_errors == 0 and v._sched.errors == 0


async def test_gcs_link_sends_ground_truth_on_request_beside_the_estimate() -> None:
    """PX4 SITL's second MAVLink instance: the GCS link (here on free ports instead of
    18570+i → 14550). An observer there asks for HIL_STATE_QUATERNION (SET_MESSAGE_INTERVAL,
    REQUEST_MESSAGE) and gets the vehicle's TRUE state, in PX4's units; the API link meanwhile
    reports the estimate, and the reported accuracy is the profile's."""
    import dataclasses

    base = free_port_scheme(3)  # 6 free ports: API pair + GCS link pair (+ spare)
    ports = dataclasses.replace(base, gcs_link_base=base.vehicle_base + 2,
                                gcs_link_remotes=((0, base.gcs_base + 2),))
    v = MockVehicle(0, ports=ports, boot_time_scale=SCALE, estimator="px4-sih", seed=4)
    assert v.gcs_link is not None
    observer_at = ("127.0.0.1", base.gcs_base + 2)
    async with v, Gcs(v) as api, Gcs(v, bind=observer_at, to=v.gcs_link.bind_address,
                                     sysid=254) as obs:
        hb = await obs.wait_type("HEARTBEAT")  # the GCS link streams by itself (to 14550)
        assert hb.get_srcSystem() == v.sysid
        assert await obs.wait_type("GLOBAL_POSITION_INT", timeout=10)
        mark = obs.mark()
        ack = await obs.command(512, 115)  # REQUEST_MESSAGE: one truth sample before the ACK
        assert ack.result == ACCEPTED and ack.target_system == 254
        before = [m for _, m in obs.msgs[mark:] if m.get_type() == "HIL_STATE_QUATERNION"]
        assert len(before) == 1 and before[0].time_usec == 0
        assert not [m for _, m in api.msgs if m.get_type() == "HIL_STATE_QUATERNION"]
        ack = await obs.command(511, 115, 20000)  # 50 Hz, as the fleet-truth recorder asked
        assert ack.result == ACCEPTED
        # fly: the estimate (API link) wanders away from the truth (GCS link)
        st = Streamer(api)
        with st:
            st.kw = {"vz": -1.5}
            assert (await api.command(176, 1, 6)).result == ACCEPTED
            await ready(api)
            assert (await api.command(400, 1)).result == ACCEPTED
            await api.until(lambda: v.position_ned[2] < -3.0, what="airborne, 3 m up")
            st.kw = {"vx": 1.0}
            await api.until(lambda: math.hypot(*(a - b for a, b in zip(
                v.position_ned[:2], v.estimated_position_ned[:2], strict=True))) > 0.15,
                what="estimate 15 cm off the truth")  # so the estimate would fail the 6 cm
            mark_o, mark_a = obs.mark(), api.mark()
            truth = await obs.wait_type("HIL_STATE_QUATERNION", since=mark_o)
            t_recv = next(t for t, m in obs.msgs[mark_o:] if m is truth)
            # the mock's truth when the sample arrived: read now, taken back to then at its
            # true velocity (the test may read it a few ticks later on a loaded machine)
            dt = asyncio.get_running_loop().time() - t_recv
            x, y, z = (c - vc * dt for c, vc in zip(v.position_ned, v.velocity_ned, strict=True))
            lat, lon = truth.lat / 1e7, truth.lon / 1e7
            n, e = project(v.origin[0], v.origin[1], lat, lon)
            assert math.hypot(n - x, e - y) < 0.06  # 50 Hz: at most one sample behind
            assert truth.alt / 1000.0 == pytest.approx(v.origin[2] - z, abs=0.06)
            assert truth.vx / 100.0 == pytest.approx(v.velocity_ned[0], abs=0.1)
            lpn = await api.wait_type("LOCAL_POSITION_NED", since=mark_a)
            ex, ey, _ = v.estimated_position_ned
            assert math.hypot(lpn.x - ex, lpn.y - ey) < 0.06  # API link: the estimate
            # reported accuracy (px4-sih: as PX4 SIH reported it)
            es = await api.wait_type("ESTIMATOR_STATUS", since=mark_a, timeout=5)
            gps = await api.wait_type("GPS_RAW_INT", since=mark_a)
            assert es.pos_horiz_accuracy == pytest.approx(0.29)
            assert (gps.fix_type, gps.h_acc, gps.vel_acc, gps.eph) == (3, 900, 400, 70)
            # a STATUSTEXT goes out on both links; a command's ACK only on the asking one
            n_obs_acks = len([m for _, m in obs.msgs if m.get_type() == "COMMAND_ACK"])
            assert (await api.command(21)).result == ACCEPTED  # LAND
            await obs.wait_type("STATUSTEXT", lambda m: m.text.startswith("Landing at"),
                                since=mark_o)
            assert len([m for _, m in obs.msgs if m.get_type() == "COMMAND_ACK"]) == n_obs_acks
