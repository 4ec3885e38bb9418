"""Endpoint URLs (MAVSDK syntax) and the PX4 SITL port scheme."""

from __future__ import annotations

import pytest

from vtube_fleet.errors import UserError
from vtube_fleet.link.endpoints import (
    Endpoint,
    EndpointError,
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
