"""PX4 conventions of sim_stub (modes, parameters, STATUSTEXT, ports, faults, homes, projection)
checked against the values the captures show."""

from __future__ import annotations

import math
import socket

import pytest

from sim_stub import (
    DEFAULT_HOME,
    Faults,
    MockFleet,
    MockVehicle,
    SimStubError,
    grid_homes,
    load_homes,
    px4,
)
from sim_stub.captures import CAPTURE_DIR, load_capture
from sim_stub.faults import parse_fault_spec
from sim_stub.geo import project, reproject
from sim_stub.ports import PX4, WIDE, PortScheme, free_port_scheme, resolve_port_scheme

needs_captures = pytest.mark.skipif(
    not (CAPTURE_DIR / "README.md").exists(), reason=f"captures not found in {CAPTURE_DIR}"
)


def test_custom_and_base_modes_as_captured() -> None:
    m = px4.MODE_BY_NAME
    assert m["AUTO.LOITER"].custom_mode == 50593792
    assert m["OFFBOARD"].custom_mode == 393216
    assert m["POSCTL"].custom_mode == 196608
    assert px4.base_mode(m["AUTO.LOITER"], False) == 29
    assert px4.base_mode(m["AUTO.LOITER"], True) == 157
    assert px4.base_mode(m["OFFBOARD"], False) == 17
    assert px4.base_mode(m["OFFBOARD"], True) == 145
    assert px4.base_mode(m["OFFBOARD"], False, offboard_has_setpoint=False) == 1
    assert px4.base_mode(m["POSCTL"], True) == 209
    assert px4.mode_from_custom(50593792) is m["AUTO.LOITER"]
    assert px4.mode_from_set_mode(6, 0) is m["OFFBOARD"]
    assert px4.mode_from_set_mode(4, 3) is m["AUTO.LOITER"]
    assert px4.mode_from_set_mode(4, 0) is m["AUTO.MISSION"]
    assert px4.mode_from_set_mode(4, 99) is None
    assert m["POSCTL"].standard_mode == 1  # capture: CURRENT_MODE during the failsafe


def test_int_parameters_are_sent_bytewise_in_the_float() -> None:
    p = px4.Param("COM_RC_IN_MODE", 1, px4.PARAM_INT32)
    assert px4.param_to_wire(p) == pytest.approx(1.401298464324817e-45)  # capture
    p = px4.Param("CAL_BARO0_ID", 6620172, px4.PARAM_INT32)
    assert px4.param_to_wire(p) == pytest.approx(9.276836857166153e-39)  # capture
    assert px4.param_from_wire(px4.param_to_wire(p), px4.PARAM_INT32) == 6620172
    f = px4.Param("COM_OF_LOSS_T", 1.0, px4.PARAM_REAL32)
    assert px4.param_to_wire(f) == 1.0


@needs_captures
def test_parameter_defaults_match_the_capture() -> None:
    table = px4.param_table()
    for name in ("offboard_loss", "rejections"):
        for pname, raw in load_capture(name).params.items():
            if pname == "CAL_BARO0_OFF":
                continue  # varies per PX4 run
            assert px4.param_to_wire(table[pname]) == pytest.approx(raw, rel=1e-6), pname
    assert "COM_DISARM_PRELAND" not in table  # does not exist in this PX4 version
    with pytest.raises(KeyError, match="unknown parameter 'NOPE'"):
        px4.param_table({"NOPE": 1})
    assert px4.param_table({"COM_OF_LOSS_T": 3})["COM_OF_LOSS_T"].value == 3.0
    assert list(table) == sorted(table)


def test_statustext_chunks_like_px4() -> None:
    text = "Arming denied: Resolve system health failures first\t"
    chunks = px4.statustext_chunks(text)
    assert chunks == [b"Arming denied: Resolve system health failures firs", b"t\t"]
    assert px4.statustext_chunks("Armed by external command\t") == [b"Armed by external command\t"]
    assert px4.statustext_chunks("x" * 100) == [b"x" * 50, b"x" * 50, b""]


def test_port_schemes() -> None:
    assert (PX4.vehicle_port(0), PX4.gcs_port(0), PX4.endpoint(2)) == (
        14580,
        14540,
        "udpin://127.0.0.1:14542",
    )
    PX4.check(40)
    with pytest.raises(SimStubError, match="at most 40 vehicles, 41 requested.*wide"):
        PX4.check(41)
    WIDE.check(500)
    WIDE.check(4000)
    assert resolve_port_scheme("wide") is WIDE
    with pytest.raises(SimStubError, match="unknown port scheme"):
        resolve_port_scheme("nope")
    with pytest.raises(SimStubError, match="holds at most 40"):
        MockFleet(41)
    s = free_port_scheme(3)
    for port in (s.vehicle_port(0), s.gcs_port(2)):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind((s.host, port))
    assert PortScheme("x", 100, 50).capacity() == 50
    # ≥ 500 vehicles: the wide scheme, sysids wrap (8-bit) but every vehicle has its own ports
    big = MockFleet(500, port_scheme="wide")
    assert len({v.bind_address for v in big.vehicles}) == 500
    assert big.vehicles[253].sysid == 254 and big.vehicles[254].sysid == 1
    assert big.endpoints[499] == "udpin://127.0.0.1:20499"
    with pytest.raises(SimStubError, match="pass sysid= explicitly"):
        MockVehicle(254)


def test_fault_specs() -> None:
    assert parse_fault_spec("2:loss=5,latency=0.05,die_at=30,die_how=freeze") == (
        2,
        Faults(loss_pct=5.0, latency_s=0.05, die_at_s=30.0, die_how="freeze"),
    )
    assert parse_fault_spec("gps_noise=0.5") == (None, Faults(gps_noise_m=0.5))
    for bad, msg in (
        ("loss=150", "loss_pct must be in"),
        ("x:loss=1", "not an integer"),
        ("loss=abc", "not a number"),
        ("speed=3", "expected key=value"),
        ("die_how=explode", "die_how must be one of"),
    ):
        with pytest.raises(SimStubError, match=msg):
            parse_fault_spec(bad)


def test_homes(tmp_path) -> None:
    g = grid_homes(DEFAULT_HOME, 4, 10.0)
    x, y = project(DEFAULT_HOME[0], DEFAULT_HOME[1], g[3][0], g[3][1])
    assert (x, y) == (pytest.approx(5.0, abs=1e-6), pytest.approx(5.0, abs=1e-6))
    f = tmp_path / "homes.csv"
    f.write_text("# lat,lon,alt\n47.0,8.0,400\n\n47.1, 8.1, 410  # second\n")
    assert load_homes(f) == [(47.0, 8.0, 400.0), (47.1, 8.1, 410.0)]
    j = tmp_path / "homes.json"
    j.write_text("[[47.0, 8.0, 400], [47.1, 8.1, 410]]")
    assert load_homes(j) == [(47.0, 8.0, 400.0), (47.1, 8.1, 410.0)]
    f.write_text("47.0,8.0\n")
    with pytest.raises(SimStubError, match=r"homes.csv:1: expected 'lat,lon,alt'"):
        load_homes(f)
    f.write_text("97.0,8.0,1\n")
    with pytest.raises(SimStubError, match=r"homes.csv:1: home latitude must be in"):
        load_homes(f)
    with pytest.raises(SimStubError, match="cannot read homes file"):
        load_homes(tmp_path / "missing.csv")
    with pytest.raises(SimStubError, match="count=3 but 2 homes"):
        MockFleet(3, homes=[DEFAULT_HOME, DEFAULT_HOME])


@needs_captures
def test_projection_is_px4s_on_captured_positions() -> None:
    """The README's check: GLOBAL_POSITION_INT projected about GPS_GLOBAL_ORIGIN (R = 6371 km,
    azimuthal equidistant) gives LOCAL_POSITION_NED x/y within ±0.02 m."""
    from pymavlink.dialects.v20 import common as mav

    cap = load_capture("offboard_flight_i0")
    m = mav.MAVLink(None, 255, 190)
    origin = None
    lpn: dict[int, tuple[float, float]] = {}
    pairs = []
    for _, pkt in cap.vehicle:
        msg = m.decode(bytearray(pkt)) if pkt[7] not in (8,) else None
        if msg is None or msg.get_type().startswith("UNKNOWN"):
            continue
        t = msg.get_type()
        if t == "GPS_GLOBAL_ORIGIN":
            origin = (msg.latitude / 1e7, msg.longitude / 1e7)
        elif t == "LOCAL_POSITION_NED":
            lpn[msg.time_boot_ms] = (msg.x, msg.y)
        elif t == "GLOBAL_POSITION_INT" and origin and msg.time_boot_ms in lpn:
            pairs.append((project(*origin, msg.lat / 1e7, msg.lon / 1e7), lpn[msg.time_boot_ms]))
    assert len(pairs) > 50
    for (px, py), (x, y) in pairs:
        assert abs(px - x) < 0.03 and abs(py - y) < 0.03
    lat, lon = reproject(47.0, 8.0, 100.0, -50.0)
    assert project(47.0, 8.0, lat, lon) == (pytest.approx(100.0), pytest.approx(-50.0))
    assert math.isclose(reproject(47.0, 8.0, 0.0, 0.0)[0], 47.0)
