"""Endpoint URLs (MAVSDK syntax) and the PX4 SITL port scheme."""

from __future__ import annotations

import pytest

from vtube_fleet.errors import UserError
from vtube_fleet.link.endpoints import (
    Endpoint,
    EndpointError,
    endpoint_sysid,
    parse_endpoint,
    px4_sitl_endpoints,
    px4_sitl_sysid,
)


@pytest.mark.parametrize(
    "url, expected",
    [
        ("udpin://127.0.0.1:14540", Endpoint("udpin", "127.0.0.1", 14540)),
        ("udpin://0.0.0.0:14541", Endpoint("udpin", "0.0.0.0", 14541)),
        ("udpin://:14542", Endpoint("udpin", "0.0.0.0", 14542)),
        ("udpout://192.168.1.20:14550", Endpoint("udpout", "192.168.1.20", 14550)),
        ("udpout://drone-3.local:14550", Endpoint("udpout", "drone-3.local", 14550)),
        # MAVSDK's deprecated udp://: empty / 0.0.0.0 host listens, any other host sends
        ("udp://:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp://0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp://10.0.0.5:14540", Endpoint("udpout", "10.0.0.5", 14540)),
        ("UDPIN://127.0.0.1:1", Endpoint("udpin", "127.0.0.1", 1)),
        ("udpin://[::1]:14540", Endpoint("udpin", "::1", 14540)),
    ],
)
def test_parse_valid(url: str, expected: Endpoint) -> None:
    ep = parse_endpoint(url)
    assert ep == expected
    assert parse_endpoint(ep.url) == ep  # canonical URL round-trips
    assert ep.listens == (ep.scheme == "udpin")


@pytest.mark.parametrize(
    "url, fragment",
    [
        ("127.0.0.1:14540", "missing scheme"),
        ("tcp://127.0.0.1:5760", "unsupported scheme 'tcp'"),
        ("serial:///dev/ttyUSB0:57600", "unsupported scheme 'serial'"),
        ("udpin://127.0.0.1", "missing ':PORT'"),
        ("udpin://127.0.0.1:abc", "port 'abc' is not a number"),
        ("udpin://127.0.0.1:0", "port 0 outside 1..65535"),
        ("udpin://127.0.0.1:70000", "port 70000 outside 1..65535"),
        ("udpout://0.0.0.0:14540", "udpout needs the vehicle's address"),
        ("udpout://:14540", "udpout needs the vehicle's address"),
        ("udpin://bad host!:14540", "invalid host"),
    ],
)
def test_parse_errors_are_one_line_user_errors(url: str, fragment: str) -> None:
    with pytest.raises(EndpointError) as info:
        parse_endpoint(url)
    msg = str(info.value)
    assert fragment in msg and url in msg
    assert "\n" not in msg
    assert isinstance(info.value, UserError)


def test_parse_rejects_non_string() -> None:
    with pytest.raises(EndpointError, match="must be a string"):
        parse_endpoint(14540)  # type: ignore[arg-type]


def test_px4_sitl_endpoints_scheme() -> None:
    eps = px4_sitl_endpoints(3)
    assert eps == [
        "udpin://127.0.0.1:14540",
        "udpin://127.0.0.1:14541",
        "udpin://127.0.0.1:14542",
    ]
    assert [px4_sitl_sysid(parse_endpoint(e).port) for e in eps] == [1, 2, 3]
    assert px4_sitl_endpoints(2, host="0.0.0.0", first_instance=5) == [
        "udpin://0.0.0.0:14545",
        "udpin://0.0.0.0:14546",
    ]
    assert len(px4_sitl_endpoints(40)) == 40
    assert px4_sitl_sysid(14550) == 11
    assert px4_sitl_sysid(14580) is None and px4_sitl_sysid(14539) is None


def test_px4_sitl_endpoints_collision_from_instance_40() -> None:
    with pytest.raises(EndpointError) as info:
        px4_sitl_endpoints(41)
    msg = str(info.value)
    assert "instance 40" in msg and "14580" in msg and "at most 40" in msg
    with pytest.raises(EndpointError, match="instance 40"):
        px4_sitl_endpoints(2, first_instance=39)


@pytest.mark.parametrize("n", [0, -1, 2.5, True])
def test_px4_sitl_endpoints_bad_count(n: object) -> None:
    with pytest.raises(EndpointError, match="integer >= 1"):
        px4_sitl_endpoints(n)  # type: ignore[arg-type]


# -- ?sysid=N: the vehicle's id (issue 33) ------------------------------------------------------
def test_an_endpoint_may_name_its_vehicles_system_id() -> None:
    ep = parse_endpoint("udpin://0.0.0.0:14600?sysid=7")
    assert ep == Endpoint("udpin", "0.0.0.0", 14600, 7)
    assert ep.url == "udpin://0.0.0.0:14600?sysid=7" and parse_endpoint(ep.url) == ep
    assert ep.transport_url == "udpin://0.0.0.0:14600"  # what MAVSDK gets
    assert parse_endpoint("udp://:14540?sysid=254").sysid == 254


@pytest.mark.parametrize(("url", "fragment"), [
    ("udpin://:14540?sysid=0", "sysid must be 1..254"),
    ("udpin://:14540?sysid=255", "sysid must be 1..254"),
    ("udpin://:14540?sysid=x", "sysid must be 1..254"),
    ("udpin://:14540?id=3", "unknown option 'id=3'"),
    ("udpin://:14540?sysid", "unknown option 'sysid'"),
])
def test_bad_endpoint_options_are_one_line_errors(url: str, fragment: str) -> None:
    with pytest.raises(EndpointError) as info:
        parse_endpoint(url)
    assert fragment in str(info.value) and url in str(info.value)


def test_the_fleet_pins_every_link_to_one_id() -> None:
    assert endpoint_sysid("udpin://127.0.0.1:14543", 0) == 4  # PX4 SITL's scheme
    assert endpoint_sysid("udpin://127.0.0.1:14550", 10) == 11  # (the GCS port: instance 10)
    assert endpoint_sysid("udpin://0.0.0.0:20005", 5) == 6  # the slot's own id
    assert endpoint_sysid("udpin://0.0.0.0:20005", 300) == 47  # (ids repeat past 254)
    assert endpoint_sysid("udpin://127.0.0.1:14543?sysid=9", 0) == 9  # the URL's wins


def test_the_built_in_mock_moves_its_gcs_link_off_the_fleets_api_ports() -> None:
    """PX4 SITL's GCS link sends to 14550 (instances 0-9), which is instance 10's API port:
    with 11 vehicles or more, the built-in mock sends it to 34550 instead (docs/links.md)."""
    from sim_stub.ports import PX4
    from vtube_fleet.fleet.launch import MOCK_GCS_LINK_MOVED_PORT, _gcs_link_off_api_ports

    assert _gcs_link_off_api_ports(PX4, 10) is PX4  # API ports 14540..14549: no clash
    moved = _gcs_link_off_api_ports(PX4, 12)
    assert moved.gcs_link_remotes == ((0, MOCK_GCS_LINK_MOVED_PORT), (10, 34650), (20, 34750))
    assert MOCK_GCS_LINK_MOVED_PORT == 34550
    assert {moved.gcs_link_remote(i) for i in range(12)}.isdisjoint(
        {moved.gcs_port(i) for i in range(12)})
    moved.check(12)
