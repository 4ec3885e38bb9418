"""Read the PX4 SITL captures and replay their GCS side against a mock (or any vehicle).

A capture ``NAME`` in the capture directory has ``NAME_gcs_to_vehicle.tlog`` and
``NAME_vehicle_to_gcs.tlog`` (records: 8-byte big-endian µs UNIX time + one raw MAVLink packet)
and ``NAME_events.json`` (``t0_wall`` = t 0, the moment the GCS socket was bound and PX4 was
launched; the capture program's phase events).

:func:`replay` re-sends the capture's GCS datagrams byte for byte with their original timing
relative to t 0, except at the points where the original capture program waited for the vehicle
(so a vehicle that climbs or lands a little slower is driven the same way the real one was):

* ``first heartbeat``: nothing after it is sent before the vehicle's first HEARTBEAT,
* ``climb target reached``: the climb setpoint is repeated until LOCAL_POSITION_NED z has risen
  5.0 m above its value when the climb began (capture program: z <= z0 - 5.0),
* ``disarmed`` (followed by ``setpoint stream stop``): the last setpoint keeps being repeated at
  20 Hz until a HEARTBEAT shows the vehicle disarmed.

While waiting, the last SET_POSITION_TARGET packet is repeated every 50 ms and the last GCS
HEARTBEAT every second, as the capture program did.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import struct
from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "CAPTURE_DIR",
    "Capture",
    "load_capture",
    "read_tlog",
    "ReplayResult",
    "replay",
    "CAPTURE_NAMES",
]

#: The real PX4 SITL captures this mock is checked against (in the source tree's
#: ``tests/data/px4_sitl``; ``PX4_SITL_CAPTURES`` points elsewhere).
CAPTURE_DIR = Path(os.environ.get(
    "PX4_SITL_CAPTURES", Path(__file__).resolve().parents[1] / "tests" / "data" / "px4_sitl"))
CAPTURE_NAMES = (
    "offboard_flight_i0",
    "offboard_loss",
    "rejections",
    "three_vehicles_i0",
    "three_vehicles_i1",
    "three_vehicles_i2",
)


def read_tlog(path: str | Path) -> list[tuple[float, bytes]]:
    """(UNIX time [s], raw packet) records of a .tlog whose records hold one MAVLink packet each."""
    data = Path(path).read_bytes()
    out = []
    i = 0
    n = len(data)
    while i + 8 < n:
        (us,) = struct.unpack(">Q", data[i : i + 8])
        i += 8
        magic = data[i]
        plen = data[i + 1]
        if magic == 0xFD:
            total = 12 + plen + (13 if data[i + 2] & 1 else 0)
        elif magic == 0xFE:
            total = 8 + plen
        else:
            raise ValueError(f"{path}: record at byte {i - 8} does not start a MAVLink packet")
        out.append((us / 1e6, data[i : i + total]))
        i += total
    return out


@dataclass
class Capture:
    """One capture: times are seconds after ``t0_wall`` (GCS bound / PX4 launched)."""

    name: str
    instance: int
    sysid: int
    t0_wall: float
    events: list[dict]
    params: dict[str, float]
    gcs: list[tuple[float, bytes]]
    vehicle: list[tuple[float, bytes]]
    garbage: list[tuple[float, bytes]] = field(default_factory=list)

    def event_time(self, what: str) -> float | None:
        for e in self.events:
            if e["what"] == what:
                return float(e["t"])
        return None


def load_capture(name: str, directory: str | Path = CAPTURE_DIR) -> Capture:
    d = Path(directory)
    ev = json.loads((d / f"{name}_events.json").read_text())
    t0 = float(ev["t0_wall"])
    gcs = [(t - t0, b) for t, b in read_tlog(d / f"{name}_gcs_to_vehicle.tlog")]
    veh = [(t - t0, b) for t, b in read_tlog(d / f"{name}_vehicle_to_gcs.tlog")]
    garbage: list[tuple[float, bytes]] = []
    gpath = d / f"{name.split('_i')[0]}_garbage_datagrams.json"
    if name == "rejections" and gpath.exists():
        g = json.loads(gpath.read_text())
        garbage = [(float(g["t"]), bytes.fromhex(h)) for h in g["datagrams_hex"]]
    return Capture(
        name=name,
        instance=int(ev["instance"]),
        sysid=int(ev["sysid"]),
        t0_wall=t0,
        events=ev["events"],
        params=ev.get("params", {}),
        gcs=gcs,
        vehicle=veh,
        garbage=garbage,
    )


@dataclass
class ReplayResult:
    """What the vehicle sent during a replay: (seconds after the replay start, raw datagram)."""

    received: list[tuple[float, bytes]]
    sent: int
    anchors: dict[str, float]  # anchor name → replay time it fired


class _Rx(asyncio.DatagramProtocol):
    def __init__(self, state: dict, loop: asyncio.AbstractEventLoop, t0: float) -> None:
        self.s = state
        self.loop = loop
        self.t0 = t0

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        s = self.s
        t = self.loop.time() - self.t0
        s["rx"].append((t, data))
        s["addr"] = addr
        if len(data) < 12 or data[0] != 0xFD:
            return
        msgid = data[7] | (data[8] << 8) | (data[9] << 16)
        plen = data[1]
        payload = data[10 : 10 + plen]
        if msgid == 0:  # HEARTBEAT: custom_mode I, type, autopilot, base_mode, ...
            p = payload + bytes(9 - len(payload))
            s["hb"] = True
            s["armed"] = bool(p[6] & 0x80)
        elif msgid == 32:  # LOCAL_POSITION_NED: time_boot_ms, x, y, z, ...
            p = payload + bytes(28 - len(payload))
            s["z"] = struct.unpack_from("<f", p, 12)[0]


async def replay(
    capture: Capture,
    vehicle_addr: tuple[str, int],
    gcs_addr: tuple[str, int],
    *,
    margin_s: float = 0.5,
    climb_m: float = 5.0,
    max_wait_s: float = 30.0,
) -> ReplayResult:
    """Replay ``capture``'s GCS side from a UDP socket bound at ``gcs_addr`` to ``vehicle_addr``.

    Call it right after starting the vehicle (its t 0). Returns every datagram received until
    the capture's last vehicle packet time (shifted by the anchors) plus ``margin_s``.
    """
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    state: dict = {"rx": [], "hb": False, "armed": False, "z": 0.0, "addr": None}
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
    sock.bind(gcs_addr)
    sock.setblocking(False)
    transport, _ = await loop.create_datagram_endpoint(lambda: _Rx(state, loop, t0), sock=sock)
    sent = 0
    anchors_fired: dict[str, float] = {}

    # anchors: (capture time, name, condition)
    anchors: list[tuple[float, str]] = []
    t_hb = capture.event_time("first heartbeat")
    if t_hb is not None:
        anchors.append((t_hb, "first heartbeat"))
    t_climb = capture.event_time("climb target reached")
    if t_climb is not None:
        anchors.append((t_climb, "climb target reached"))
    t_dis = capture.event_time("disarmed")
    if t_dis is not None:
        anchors.append((t_dis, "disarmed"))
    anchors.sort()
    t_climb_start = next(
        (
            float(e["t"])
            for e in capture.events
            if e["what"] == "setpoint" and e.get("phase") == "climb"
        ),
        None,
    )
    z0: list[float | None] = [None]

    def condition(name: str) -> bool:
        if name == "first heartbeat":
            return bool(state["hb"])
        if name == "climb target reached":
            return z0[0] is not None and state["z"] <= z0[0] - climb_m
        if name == "disarmed":
            return state["hb"] and not state["armed"]
        return True

    packets = sorted(capture.gcs + capture.garbage, key=lambda x: x[0])
    last_sp: bytes | None = None
    last_hb: bytes | None = None
    offset = 0.0
    ai = 0

    def send(data: bytes) -> None:
        nonlocal sent
        transport.sendto(data, vehicle_addr)
        sent += 1

    async def wait_anchor(name: str, t_anchor: float) -> None:
        nonlocal offset
        start = loop.time()
        next_sp = next_hb = loop.time()
        while not condition(name):
            now = loop.time()
            if now - start > max_wait_s:
                raise TimeoutError(
                    f"replay {capture.name}: vehicle did not reach {name!r} within {max_wait_s} s"
                )
            if last_sp is not None and now >= next_sp and name != "first heartbeat":
                send(last_sp)
                next_sp = now + 0.05
            if last_hb is not None and now >= next_hb + 1.0:
                send(last_hb)
                next_hb = now
            await asyncio.sleep(0.01)
        offset = (loop.time() - t0) - t_anchor
        anchors_fired[name] = loop.time() - t0

    try:
        skip_until = float("-inf")
        for tc, data in packets:
            if tc < skip_until:
                continue
            while ai < len(anchors) and anchors[ai][0] <= tc:
                await wait_anchor(anchors[ai][1], anchors[ai][0])
                ai += 1
            target = t0 + tc + offset
            early = False
            while loop.time() < target:
                if (
                    ai < len(anchors)
                    and anchors[ai][1] != "first heartbeat"
                    and condition(anchors[ai][1])
                ):
                    early = True  # the vehicle got there first: the capture program moved on
                    break
                await asyncio.sleep(min(0.005, max(0.0, target - loop.time())))
            if early:
                t_anchor, name = anchors[ai]
                offset = (loop.time() - t0) - t_anchor
                anchors_fired[name] = loop.time() - t0
                ai += 1
                skip_until = t_anchor
                if tc < t_anchor:
                    continue
            if t_climb_start is not None and z0[0] is None and tc >= t_climb_start:
                z0[0] = state["z"]
            if len(data) >= 10 and data[0] == 0xFD:
                msgid = data[7] | (data[8] << 8) | (data[9] << 16)
                if msgid == 84:
                    last_sp = data
                elif msgid == 0:
                    last_hb = data
            send(data)
        end = capture.vehicle[-1][0] + offset + margin_s
        while loop.time() - t0 < end:
            await asyncio.sleep(min(0.05, max(0.0, end - (loop.time() - t0))))
    finally:
        transport.close()
    return ReplayResult(received=state["rx"], sent=sent, anchors=anchors_fired)
