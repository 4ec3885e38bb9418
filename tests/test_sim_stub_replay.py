"""Replay fidelity: the captures' GCS command sequences against the mock, compared with real PX4.

All six captures (offboard flight, offboard loss, rejections, three vehicles at once) are replayed
concurrently, once per module (~40 s: PX4's real boot and flight timing), over real UDP sockets
on loopback. Each replay re-sends the capture's GCS datagrams byte for byte (and the three garbage
datagrams of the rejections capture), waiting where the capture program waited for the vehicle
(first heartbeat, 5 m climbed, disarmed; see :mod:`sim_stub.captures`). The mock's answer is
then compared with what PX4 sent in the same capture. The mock runs with the ``ideal`` estimator:
these are open-loop flights (velocity setpoints), whose end points the px4-sih estimate error
would move by metres; the estimate errors are checked in ``test_sim_stub_estimator.py``.
"""

from __future__ import annotations

import asyncio
import math
import re
import struct
from dataclasses import dataclass, field

import pytest
from pymavlink.dialects.v20 import all as mavall

from sim_stub import MockFleet, MockVehicle, PortScheme, px4
from sim_stub.captures import CAPTURE_DIR, CAPTURE_NAMES, Capture, load_capture, replay
from sim_stub.geo import project
from sim_stub.ports import free_port_scheme

pytestmark = [pytest.mark.timeout(240)]
assert (CAPTURE_DIR / "README.md").is_file(), f"captures not found in {CAPTURE_DIR}"

# event-driven messages: compared by count over the run, not by rate between first and last
EVENT_DRIVEN = {"COMMAND_ACK", "STATUSTEXT", "PARAM_VALUE", "GPS_GLOBAL_ORIGIN", "UNKNOWN_410"}
THREE_I2_HOME = (47.397842, 8.545594, 489.4)  # capture 1b: instance 2 ran with PX4_HOME_LAT


@dataclass
class Stream:
    """Decoded datagrams of one direction: (time [s], pymavlink message)."""

    msgs: list[tuple[float, object]] = field(default_factory=list)
    bad: int = 0

    def of(self, name: str) -> list[tuple[float, object]]:
        return [(t, m) for t, m in self.msgs if m.get_type() == name]

    def types(self) -> set[str]:
        return {m.get_type() for _, m in self.msgs}

    def rate(self, name: str) -> float:
        ts = [t for t, _ in self.of(name)]
        if len(ts) < 2 or ts[-1] == ts[0]:
            return 0.0
        return (len(ts) - 1) / (ts[-1] - ts[0])

    def span(self) -> float:
        return self.msgs[-1][0] - self.msgs[0][0]


def decode(records: list[tuple[float, bytes]]) -> Stream:
    mav = mavall.MAVLink(None, 255, 190)
    mav.robust_parsing = True
    out = Stream()
    for t, data in records:
        for m in mav.parse_buffer(data) or []:
            if m.get_type() == "BAD_DATA":
                out.bad += 1
            else:
                out.msgs.append((t, m))
    return out


@dataclass
class Run:
    capture: Capture
    px4: Stream
    mock: Stream
    vehicle: MockVehicle
    anchors: dict[str, float]
    raw: list[tuple[float, bytes]]


async def _replay_all() -> dict[str, Run]:
    caps = {n: load_capture(n) for n in CAPTURE_NAMES}
    base = free_port_scheme(len(caps))

    def scheme(k: int, instance: int) -> PortScheme:
        # capture k's vehicle binds base.vehicle_base + k whatever its instance number
        return PortScheme(
            "replay", base.vehicle_base + k - instance, base.gcs_base + k - instance, base.host
        )

    singles = ["offboard_flight_i0", "offboard_loss", "rejections"]
    vehicles: dict[str, MockVehicle] = {}
    for k, name in enumerate(singles):
        vehicles[name] = MockVehicle(caps[name].instance, ports=scheme(k, caps[name].instance),
                                     estimator="ideal")
    k3 = len(singles)
    fleet = MockFleet(
        3,
        homes=[MockVehicle(0).origin, MockVehicle(0).origin, THREE_I2_HOME],
        port_scheme=PortScheme("replay3", base.vehicle_base + k3, base.gcs_base + k3, base.host),
        estimator="ideal",
    )
    for i in range(3):
        vehicles[f"three_vehicles_i{i}"] = fleet.vehicles[i]

    async def one(name: str, start: bool) -> tuple[str, object]:
        v = vehicles[name]
        if start:
            await v.start()
        try:
            res = await replay(caps[name], v.bind_address, v.gcs_address)
        finally:
            if start:
                await v.stop()
        return name, res

    async def three() -> list[tuple[str, object]]:
        async with fleet:
            return await asyncio.gather(*(one(f"three_vehicles_i{i}", False) for i in range(3)))

    results = await asyncio.gather(*(one(n, True) for n in singles), three())
    flat = list(results[:3]) + list(results[3])
    runs = {}
    for name, res in flat:
        cap = caps[name]
        runs[name] = Run(
            capture=cap,
            px4=decode(cap.vehicle),
            mock=decode(res.received),  # type: ignore[attr-defined]
            vehicle=vehicles[name],
            anchors=res.anchors,  # type: ignore[attr-defined]
            raw=res.received,  # type: ignore[attr-defined]
        )
    return runs


@pytest.fixture(scope="module")
def runs() -> dict[str, Run]:
    return asyncio.run(_replay_all())


def _phases(stream: Stream, name: str, key) -> list:
    out: list = []
    for _, m in stream.of(name):
        k = key(m)
        if not out or out[-1] != k:
            out.append(k)
    return out


def _hb(m) -> tuple[int, int, int]:
    return (m.base_mode, m.custom_mode, m.system_status)


def _texts(stream: Stream) -> list[tuple[int, int, str]]:
    out = []
    for _, m in stream.of("STATUSTEXT"):
        text = re.sub(r"\d{4}-\d\d-\d\d/\d\d_\d\d_\d\d", "DATE/TIME", m.text)
        out.append((m.severity, m.chunk_seq, text))
    return out


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_link_code_parses_the_capture_without_errors(runs: dict[str, Run], name: str) -> None:
    run = runs[name]
    assert run.px4.bad == 0 and run.mock.bad == 0
    # the mock's own datagram parser accepts every GCS datagram of the capture
    from sim_stub.codec import DatagramParser

    parser = DatagramParser()
    for _, data in run.capture.gcs:
        pk, malformed, unknown = parser.parse(data)
        assert (len(pk), malformed, unknown) == (1, 0, 0)


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_same_message_types_and_rates(runs: dict[str, Run], name: str) -> None:
    run = runs[name]
    px4_types, mock_types = run.px4.types(), run.mock.types()
    assert mock_types == px4_types, (
        f"missing {sorted(px4_types - mock_types)}, extra {sorted(mock_types - px4_types)}"
    )
    bad = []
    for t in sorted(px4_types):
        if t in EVENT_DRIVEN:  # a count: the mock's flight may last longer than PX4's
            ref, got, unit = len(run.px4.of(t)), len(run.mock.of(t)), ""
        else:
            ref, got, unit = run.px4.rate(t), run.mock.rate(t), " Hz"
        if not 0.75 * ref <= got <= 1.25 * ref:
            bad.append(f"{t}: PX4 {ref:.3f}{unit}, mock {got:.3f}{unit}")
    assert not bad, "; ".join(bad)


def _event_ids(stream: Stream) -> list[int]:
    """EVENT (410) ids in order (pymavlink keeps the undecoded frame: the id follows the 10-byte
    MAVLink 2 header)."""
    return [struct.unpack_from("<I", bytes(m.data), 10)[0] for _, m in stream.of("UNKNOWN_410")]


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_same_events_in_the_same_order(runs: dict[str, Run], name: str) -> None:
    """The mock's EVENT ids are PX4's, in PX4's order. The run may end just before or after the
    health burst PX4 sends ~3.9 s after a landing (px4.HEALTH_AFTER_LANDING_S): a replay lasts
    as long as the mock's flight, so the two may differ by that last burst (five events)."""
    run = runs[name]
    px4_ids, mock_ids = _event_ids(run.px4), _event_ids(run.mock)
    short, long_ = sorted((px4_ids, mock_ids), key=len)
    assert long_[: len(short)] == short, f"PX4 {px4_ids}, mock {mock_ids}"
    assert len(long_) - len(short) in (0, len(px4.HEALTH_BURST_NO_OFFBOARD))
    assert long_[len(short):] in ([], [e.event_id for e in px4.HEALTH_BURST_NO_OFFBOARD])


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_same_command_acks(runs: dict[str, Run], name: str) -> None:
    run = runs[name]

    def acks(s: Stream) -> list[tuple[int, int, int, int, int, int]]:
        return [
            (m.command, m.result, m.progress, m.result_param2, m.target_system, m.target_component)
            for _, m in s.of("COMMAND_ACK")
        ]

    assert acks(run.mock) == acks(run.px4)


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_same_mode_heartbeat_and_landed_sequences(runs: dict[str, Run], name: str) -> None:
    run = runs[name]
    assert _phases(run.mock, "HEARTBEAT", _hb) == _phases(run.px4, "HEARTBEAT", _hb)
    landed = lambda m: m.landed_state  # noqa: E731
    assert _phases(run.mock, "EXTENDED_SYS_STATE", landed) == _phases(
        run.px4, "EXTENDED_SYS_STATE", landed
    )
    cm = lambda m: (m.custom_mode, m.intended_custom_mode, m.standard_mode)  # noqa: E731
    assert _phases(run.mock, "CURRENT_MODE", cm) == _phases(run.px4, "CURRENT_MODE", cm)
    # one MAVLink 2 packet per datagram, unsigned, flags 0, sysid i+1 / compid 1, seq contiguous
    frames = {(d[0], d[2], d[3], d[5], d[6]) for _, d in run.raw}
    assert frames == {(0xFD, 0, 0, run.capture.sysid, 1)}
    assert all(len(d) == 12 + d[1] for _, d in run.raw)
    seqs = [d[4] for _, d in run.raw]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:], strict=False))
    hb = {(m.type, m.autopilot, m.mavlink_version) for _, m in run.mock.of("HEARTBEAT")}
    assert hb == {(2, 12, 3)}


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_same_statustexts(runs: dict[str, Run], name: str) -> None:
    run = runs[name]
    assert _texts(run.mock) == _texts(run.px4)


def test_boot_order(runs: dict[str, Run]) -> None:
    """Capture: streams start before the first HEARTBEAT, GPS_GLOBAL_ORIGIN comes with it, the
    global position only later (checked by order and by the vehicle's own time_boot_ms)."""
    for run in runs.values():
        order: list[str] = []
        for _, m in run.mock.msgs:
            if m.get_type() not in order:
                order.append(m.get_type())
        assert order.index("GPS_RAW_INT") < order.index("HEARTBEAT")
        assert order.index("LOCAL_POSITION_NED") < order.index("HEARTBEAT")
        assert order.index("HEARTBEAT") < order.index("GLOBAL_POSITION_INT")
        assert order.index("GPS_GLOBAL_ORIGIN") < order.index("GLOBAL_POSITION_INT")
        first_gpi = run.mock.of("GLOBAL_POSITION_INT")[0][1].time_boot_ms
        first_px4 = run.px4.of("GLOBAL_POSITION_INT")[0][1].time_boot_ms
        assert first_gpi >= 2600 and first_px4 >= 2600  # ms after boot (PX4: 2.70-2.98 s)


def test_parameters_as_px4_sends_them(runs: dict[str, Run]) -> None:
    for name in ("offboard_loss", "rejections"):
        run = runs[name]

        def values(s: Stream) -> list[tuple[str, int, float]]:
            out = []
            for _, m in s.of("PARAM_VALUE"):
                if m.param_id == "CAL_BARO0_OFF":  # differs from run to run on real PX4 too
                    continue
                out.append((m.param_id, m.param_type, m.param_value))
            return out

        assert values(run.mock) == values(run.px4)
        # the nonexistent COM_DISARM_PRELAND got no answer at all, from either
        assert not [m for _, m in run.mock.of("PARAM_VALUE") if m.param_id == "COM_DISARM_PRELAND"]
        # int parameters bytewise in the float (capture: COM_RC_IN_MODE = 1 → 1.4e-45)
    loss = runs["offboard_loss"].mock
    (rc,) = [m for _, m in loss.of("PARAM_VALUE") if m.param_id == "COM_RC_IN_MODE"]
    assert rc.param_type == 6 and rc.param_value == pytest.approx(1.401298464324817e-45)


def test_garbage_datagrams_counted_and_dropped(runs: dict[str, Run]) -> None:
    run = runs["rejections"]
    c = run.vehicle.counters
    assert c.rx_malformed == 3  # the three garbage datagrams, nothing else
    assert c.rx_datagrams == len(run.capture.gcs) + 3
    # the streams continued around t = 11.05 s: ATTITUDE on both sides within 1 s (its 100 Hz
    # rate is test_same_message_types_and_rates'; here a loose count, since a loaded machine's
    # scheduler drops what falls more than 0.25 s behind, and never more than 100 Hz + 25 %)
    shift = run.anchors["first heartbeat"] - run.capture.event_time("first heartbeat")
    t_garbage = run.capture.garbage[0][0] + shift
    near = [t for t, _ in run.mock.of("ATTITUDE") if abs(t - t_garbage) < 1.0]
    assert any(t < t_garbage for t in near) and any(t > t_garbage for t in near)
    assert 50 <= len(near) <= 250


def _interp(ts: list[float], xs: list[float], t: float) -> float:
    for k in range(1, len(ts)):
        if ts[k] >= t:
            a = (t - ts[k - 1]) / (ts[k] - ts[k - 1]) if ts[k] != ts[k - 1] else 0.0
            return xs[k - 1] + a * (xs[k] - xs[k - 1])
    return xs[-1]


def _bracket(ts: list[float], xs: list[float], t: float) -> tuple[float, float]:
    """min/max of the two samples around ``t`` (velocities may jump, e.g. at touchdown)."""
    for k in range(1, len(ts)):
        if ts[k] >= t:
            return min(xs[k - 1], xs[k]), max(xs[k - 1], xs[k])
    return xs[-1], xs[-1]


@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_local_global_origin_relations(runs: dict[str, Run], name: str) -> None:
    """README "Local/global frames": local is relative to GPS_GLOBAL_ORIGIN (0,0,0 at boot),
    global = projection about the origin, alt = origin.alt - z, relative_alt = alt - home.alt."""
    s = runs[name].mock
    origins = s.of("GPS_GLOBAL_ORIGIN")
    assert len(origins) == len(runs[name].px4.of("GPS_GLOBAL_ORIGIN")) == 2
    o = origins[0][1]
    olat, olon, oalt = o.latitude / 1e7, o.longitude / 1e7, o.altitude / 1000.0
    lpn = [m for _, m in s.of("LOCAL_POSITION_NED")]
    assert (lpn[0].x, lpn[0].y, lpn[0].z) == (0.0, 0.0, 0.0)
    tb = [m.time_boot_ms for m in lpn]
    homes = s.of("HOME_POSITION")
    checked = 0
    for t, g in s.of("GLOBAL_POSITION_INT"):
        if not tb[0] <= g.time_boot_ms <= tb[-1]:
            continue
        x = _interp(tb, [m.x for m in lpn], g.time_boot_ms)
        y = _interp(tb, [m.y for m in lpn], g.time_boot_ms)
        z = _interp(tb, [m.z for m in lpn], g.time_boot_ms)
        vz_lo, vz_hi = _bracket(tb, [m.vz for m in lpn], g.time_boot_ms)
        px, py = project(olat, olon, g.lat / 1e7, g.lon / 1e7)
        assert abs(px - x) < 0.03 and abs(py - y) < 0.03
        assert abs((oalt - z) - g.alt / 1000.0) < 0.02
        assert vz_lo - 0.011 <= g.vz / 100.0 <= vz_hi + 0.011  # cm/s quantization
        home = [h for th, h in homes if th <= t]
        if home:
            assert abs(g.relative_alt / 1000.0 - (g.alt - home[-1].altitude) / 1000.0) < 0.002
        checked += 1
    assert checked > 100


def test_home_reset_at_arming_and_at_disarm_after_landing(runs: dict[str, Run]) -> None:
    s = runs["offboard_flight_i0"].mock
    homes = [(t, (h.latitude, h.longitude, h.altitude)) for t, h in s.of("HOME_POSITION")]
    changes = [homes[0]] + [b for a, b in zip(homes, homes[1:], strict=False) if a[1] != b[1]]
    assert len(changes) >= 2
    final = s.of("HOME_POSITION")[-1][1]
    last_lpn = s.of("LOCAL_POSITION_NED")[-1][1]
    # home is the landing point, ~12 m from the start (capture: local (9.56, 7.49))
    assert math.hypot(final.x, final.y) > 5.0
    assert abs(final.x - last_lpn.x) < 0.05 and abs(final.y - last_lpn.y) < 0.05


def test_three_vehicles_have_their_own_origins(runs: dict[str, Run]) -> None:
    """Capture 1b: same local NED coordinates on different vehicles are ~11 m apart."""
    o = {}
    for i in range(3):
        m = runs[f"three_vehicles_i{i}"].mock.of("GPS_GLOBAL_ORIGIN")[0][1]
        o[i] = (m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
    assert o[0] == o[1]
    north, east = project(o[0][0], o[0][1], o[2][0], o[2][1])
    assert north == pytest.approx(11.1, abs=0.3) and abs(east) < 0.1  # PX4: 10.91 m, 0.05 m
    for i in range(3):  # every vehicle reports (0,0,0) at boot
        first = runs[f"three_vehicles_i{i}"].mock.of("LOCAL_POSITION_NED")[0][1]
        assert (first.x, first.y, first.z) == (0.0, 0.0, 0.0)
        assert runs[f"three_vehicles_i{i}"].vehicle.sysid == i + 1


def test_offboard_loss_failsafe_sequence(runs: dict[str, Run]) -> None:
    """Capture 1c: ~1 s after the last setpoint "Failsafe activated" (CRITICAL), POSCTL with
    base_mode 209 and status CRITICAL, a descent setpoint (type_mask 31, vz 0.7), landing,
    auto-disarm 2 s after "Landing detected", and OFFBOARD/17/UNINIT again."""
    run = runs["offboard_loss"]
    s = run.mock
    sps = [t for t, _ in decode([(t, d) for t, d in run.capture.gcs]).of("HEARTBEAT")]
    assert sps  # (the GCS heartbeat kept running in the capture and in the replay)
    texts = [(t, m.text) for t, m in s.of("STATUSTEXT")]
    (t_fs,) = [t for t, x in texts if x == "Failsafe activated\t"]
    (t_land,) = [t for t, x in texts if x == "Landing detected\t"]
    (t_dis,) = [t for t, x in texts if x == "Disarmed by landing\t"]
    assert t_fs < t_land < t_dis
    # COM_DISARM_LAND = 2 s, on the vehicle's own clock (never earlier)
    texts_v = {x: t for t, _, x in run.vehicle.statustexts}
    assert texts_v["Disarmed by landing\t"] - texts_v["Landing detected\t"] >= 2.0
    targets = [(t, m) for t, m in s.of("POSITION_TARGET_LOCAL_NED") if t_fs < t < t_land]
    assert targets and all(m.type_mask == 31 for _, m in targets[3:])
    assert targets[-1][1].vz == pytest.approx(0.7) and math.isnan(targets[-1][1].vx)
    vz = [m.vz for t, m in s.of("LOCAL_POSITION_NED") if t_fs + 3 < t < t_land - 2]
    assert 0.45 <= sum(vz) / len(vz) <= 0.66  # capture: 0.45-0.62 m/s descent
