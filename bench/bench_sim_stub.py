"""Benchmark: N mock PX4 vehicles at PX4's telemetry rates, the CPU they take.

    python bench/bench_sim_stub.py [--count 200] [--seconds 30] [--profile full|lite]
                                   [--no-requests | --lean] [--setpoint-hz HZ] [--fly]
                                   [--fence] [--processes N] [--tick-hz HZ]

The mock fleet runs in a child process (one asyncio loop, one scheduler tick), or with
``--processes N`` split over N grandchildren as ``mock-fleet --processes N`` does
(:class:`~sim_stub.processes.ProcessFleet`). A receiver in this process binds the N GCS ports
(one epoll), sends each vehicle stream requests once its first HEARTBEAT arrives and counts every
datagram per vehicle and message id:

* default: the same four SET_MESSAGE_INTERVAL commands the capture GCS sent (LOCAL_POSITION_NED
  50 Hz, GLOBAL_POSITION_INT 10 Hz, EXTENDED_SYS_STATE 5 Hz, HOME_POSITION 1 Hz);
* ``--lean``: what the fleet's mavlink link asks for with ``bench_fleet.py --lean-streams``
  (its default rates, ``UNUSED_STREAMS_OFF`` and ``LEAN_STREAMS_HZ``: LOCAL_POSITION_NED 25 Hz,
  GLOBAL_POSITION_INT 2, GPS_RAW_INT 1, SYS_STATUS 2, the high-rate streams and BATTERY off);
* ``--no-requests``: PX4's default rates.

``--setpoint-hz HZ`` streams SET_POSITION_TARGET_LOCAL_NED (velocity) to every vehicle;
``--fly`` (setpoints at 20 Hz unless given, a GCS HEARTBEAT at 1 Hz) also switches every vehicle
to OFFBOARD and arms it once it is ready: it climbs at 1 m/s for 6 s, then flies north at
0.5 m/s, so the measurement window is steady offboard flight (the warm-up is then 18 s);
``--fence`` first uploads a geofence to each vehicle like the fleet does (an inclusion polygon of
8 vertices around its path and an exclusion circle beside it: PX4's breach check runs at 50 Hz
while armed). After the warm-up (boot), it compares each vehicle's per-message rate over the
window with the nominal rate and prints the minimum ratio. CPU is the user + system time of the
mock process and its children (/proc) over the same window: ``cores = cpu_seconds /
wall_seconds`` (1.0 = one core fully busy), and per vehicle in ms of CPU per vehicle-second.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import select
import socket
import statistics
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pymavlink.dialects.v20 import common as mav  # noqa: E402

from sim_stub import MockFleet, PortScheme  # noqa: E402
from sim_stub.codec import SPECS, Encoder, MsgSpec  # noqa: E402
from sim_stub.fleet import grid_homes  # noqa: E402
from sim_stub.geo import reproject  # noqa: E402
from sim_stub.ports import free_port_scheme  # noqa: E402
from sim_stub.processes import ProcessFleet  # noqa: E402
from sim_stub.telemetry import STREAM_CATALOG  # noqa: E402
from sim_stub.vehicle import DEFAULT_HOME  # noqa: E402

WARMUP_S = 8.0  # boot (~5.6 s) plus the interval requests
FLY_WARMUP_S = 18.0  # boot, OFFBOARD + arm, spool-up 1 s, take-off ramp 2 s, the 6 s climb
CLIMB_S = 6.0
REQUESTS = {32: 50.0, 33: 10.0, 245: 5.0, 242: 1.0}  # msgid -> Hz (capture GCS)
#: --lean: vtube_fleet.link.mavlink.DEFAULT_MESSAGE_RATES_HZ updated with
#: vtube_fleet.link.mavlink.UNUSED_STREAMS_OFF and bench_fleet.LEAN_STREAMS_HZ (0 = off)
LEAN_REQUESTS = {32: 25.0, 33: 2.0, 245: 5.0, 242: 1.0, 230: 2.0, 30: 0.0, 31: 0.0, 105: 0.0,
                 331: 0.0, 85: 0.0, 24: 1.0, 1: 2.0, 147: 0.0}  # fmt: skip
#: --fence: (north, east) m from each vehicle's home, an inclusion polygon around its path (the
#: fleet's tube fence has 8 vertices too) and an exclusion circle (north, east, radius) beside it
FENCE_POLYGON_NE = ((-20.0, -10.0), (-20.0, 10.0), (-10.0, 20.0), (300.0, 20.0), (310.0, 10.0),
                    (310.0, -10.0), (300.0, -20.0), (-10.0, -20.0))
FENCE_CIRCLE_NER = (5.0, 12.0, 0.8)
_HB = struct.Struct("<IBBBBB")  # custom_mode, type, autopilot, base_mode, system_status, version


def nominal_rates(profile: str, requests: dict[int, float]) -> dict[int, float]:
    rates = {}
    for sd in STREAM_CATALOG:
        hz = sd.full_hz if profile == "full" else sd.lite_hz
        if hz > 0:
            rates[SPECS[sd.name].msgid] = hz
    for msgid, hz in requests.items():
        if hz > 0:
            rates[msgid] = hz
        else:
            rates.pop(msgid, None)
    return rates


def tree_cpu_s(pid: int) -> tuple[float, float]:
    """(user, system) CPU seconds of ``pid`` and its descendants (Linux /proc; 0 if gone)."""
    user, system, todo = 0.0, 0.0, [pid]
    tick = os.sysconf("SC_CLK_TCK")
    while todo:
        p = todo.pop()
        try:
            stat = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            user += int(stat[11]) / tick
            system += int(stat[12]) / tick
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return user, system


def mock_process(count, scheme_args, profile, processes, tick_hz, ready, results, stop) -> None:
    async def run() -> None:
        scheme = PortScheme(*scheme_args)
        kw = dict(port_scheme=scheme, profile=profile, spacing_m=5.0, tick_hz=tick_hz)
        fleet = (ProcessFleet(count, processes=processes, **kw) if processes
                 else MockFleet(count, **kw))  # fmt: skip
        async with fleet:
            ready.set()
            await asyncio.get_running_loop().run_in_executor(None, stop.wait)
            if isinstance(fleet, MockFleet):
                sched = fleet.scheduler
                results.put({
                    "late_ticks": sched.late_ticks, "skipped_msgs": sched.skipped_msgs,
                    "ticks": sched._ticks,
                    "tx_errors": sum(v.counters.tx_errors for v in fleet.vehicles),
                })  # fmt: skip
            else:
                results.put({})

    asyncio.run(run())


def _spec(cls: type) -> tuple[struct.Struct, MsgSpec]:
    st = struct.Struct(cls.unpacker.format)  # type: ignore[attr-defined]
    n = len(cls.ordered_fieldnames)  # type: ignore[attr-defined]
    return st, MsgSpec(cls.__name__, cls.id, cls.crc_extra, st,  # type: ignore[attr-defined]
                       tuple(cls.ordered_fieldnames), (1,) * n)  # type: ignore[attr-defined]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=30.0, help="measurement window")
    ap.add_argument("--profile", choices=("full", "lite"), default="full")
    req = ap.add_mutually_exclusive_group()
    req.add_argument("--no-requests", action="store_true", help="keep PX4's default rates")
    req.add_argument("--lean", action="store_true",
                     help="the fleet link's lean stream requests (bench_fleet --lean-streams)")
    ap.add_argument("--setpoint-hz", type=float, default=None,
                    help="also send each vehicle SET_POSITION_TARGET_LOCAL_NED at this rate, "
                    "like a fleet controller (e.g. 20; --fly: 20 unless given)")  # fmt: skip
    ap.add_argument("--fly", action="store_true",
                    help="OFFBOARD + arm every vehicle, measure steady offboard flight")
    ap.add_argument("--fence", action="store_true",
                    help="with --fly: upload a geofence to every vehicle before arming")
    ap.add_argument("--tick-hz", type=float, default=100.0, metavar="HZ",
                    help="the mock's scheduler tick (MockFleet tick_hz; default 100: dynamics at "
                    "100 Hz, each vehicle's PX4 logic at 50 Hz)")  # fmt: skip
    ap.add_argument("--processes", type=int, default=0, metavar="N",
                    help="split the fleet over N mock processes (ProcessFleet; default: one "
                    "MockFleet in one process)")  # fmt: skip
    args = ap.parse_args()
    n = args.count
    sp_hz = args.setpoint_hz if args.setpoint_hz is not None else (20.0 if args.fly else 0.0)
    if not 0 <= args.processes <= n:
        print(f"error: --processes must be in 0..{n}", file=sys.stderr)
        return 2
    scheme = free_port_scheme(n)
    requests = {} if args.no_requests else (LEAN_REQUESTS if args.lean else REQUESTS)
    nominal = nominal_rates(args.profile, requests)
    what = ("default rates" if args.no_requests else
            "lean requests" if args.lean else "capture GCS interval requests")  # fmt: skip
    print(
        f"bench_sim_stub: {n} vehicles in {args.processes or 1} process(es), tick "
        f"{args.tick_hz:g} Hz, profile "
        f"{args.profile}, {what}, setpoints {sp_hz:g} Hz{', offboard flight' if args.fly else ''};"
        f" nominal {sum(nominal.values()):.1f} msg/s per vehicle, "
        f"{n * sum(nominal.values()):.0f} msg/s total; ports {scheme.vehicle_base}+i -> "
        f"{scheme.gcs_base}+i",
        flush=True,
    )
    # receiver sockets first, so nothing is lost at boot
    ep = select.epoll()
    socks = []
    fd_index: dict[int, int] = {}
    for i in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.bind((scheme.host, scheme.gcs_port(i)))
        s.setblocking(False)
        ep.register(s.fileno(), select.EPOLLIN)
        fd_index[s.fileno()] = i
        socks.append(s)
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    results = ctx.Queue()
    proc = ctx.Process(
        target=mock_process,
        args=(n, (scheme.name, scheme.vehicle_base, scheme.gcs_base, scheme.host), args.profile,
              args.processes, args.tick_hz, ready, results, stop),
    )  # fmt: skip
    proc.start()
    if not ready.wait(120.0):
        print("error: mock process did not start", file=sys.stderr)
        proc.kill()
        return 2
    t0 = time.monotonic()
    enc = Encoder(255, 190)
    cl_struct, cl_spec = _spec(mav.MAVLink_command_long_message)
    sp_struct, sp_spec = _spec(mav.MAVLink_set_position_target_local_ned_message)
    hb_spec = SPECS["HEARTBEAT"]
    hb_frame_payload = hb_spec.struct.pack(0, 6, 8, 0, 0, 3)  # a GCS
    sysids = [i % 254 + 1 for i in range(n)]  # MockFleet's sysids wrap beyond 254 vehicles
    requested = [False] * n
    addrs: list[tuple[str, int] | None] = [None] * n
    status = [(0, 0, 0)] * n  # custom_mode, base_mode, system_status of the last HEARTBEAT
    landed = [0] * n
    climb_until: list[float | None] = [None] * n
    last_cmd = [0.0] * n
    fenced = [not args.fence] * n
    fence_items: list[list[bytes]] = []
    if args.fence:
        mi = SPECS["MISSION_ITEM_INT"]
        for i, (lat0, lon0, _) in enumerate(grid_homes(DEFAULT_HOME, n, 5.0)):
            pts = [(5001, float(len(FENCE_POLYGON_NE)), reproject(lat0, lon0, no, ea))
                   for no, ea in FENCE_POLYGON_NE]
            pts.append((5004, FENCE_CIRCLE_NER[2], reproject(lat0, lon0, *FENCE_CIRCLE_NER[:2])))
            fence_items.append([
                mi.pack(param1=p1, x=round(lat * 1e7), y=round(lon * 1e7), z=0.0, seq=k,
                        command=cmd, target_system=sysids[i], target_component=1, frame=5,
                        mission_type=1)
                for k, (cmd, p1, (lat, lon)) in enumerate(pts)])  # fmt: skip
    next_sp = next_hb = time.monotonic()
    setpoints_sent = 0
    counts: list[dict[int, int]] = [dict() for _ in range(n)]
    warmup = FLY_WARMUP_S if args.fly else WARMUP_S
    t_meas0 = t0 + warmup
    t_meas1 = t_meas0 + args.seconds
    cpu0 = cpu1 = (0.0, 0.0)
    w0 = w1 = 0.0
    measuring = False
    flying_at_start = 0

    def command(i: int, cmd: int, p1: float, p2: float = 0.0, p3: float = 0.0) -> None:
        payload = cl_struct.pack(p1, p2, p3, 0, 0, 0, 0, cmd, sysids[i], 1, 0)
        socks[i].sendto(enc.frame(cl_spec, payload), addrs[i])  # type: ignore[arg-type]

    def offboard(i: int) -> bool:
        cm, base, _ = status[i]
        return bool(base & 0x80) and (cm >> 16) & 0xFF == 6

    while True:
        now = time.monotonic()
        if now >= t_meas1:
            cpu1, w1 = tree_cpu_s(proc.pid), time.monotonic()
            break
        if not measuring and now >= t_meas0:
            measuring = True
            cpu0, w0 = tree_cpu_s(proc.pid), time.monotonic()
            flying_at_start = sum(offboard(i) and landed[i] == 2 for i in range(n))
        if args.fly and now >= next_hb:
            next_hb += 1.0
            for i, a in enumerate(addrs):
                if a is not None:
                    socks[i].sendto(enc.frame(hb_spec, hb_frame_payload), a)
        if sp_hz > 0 and now >= next_sp:
            next_sp += 1.0 / sp_hz
            for i, a in enumerate(addrs):
                if a is None:
                    continue
                vx, vz = 0.0, -1.0 if args.fly else 0.0
                if not args.fly:
                    vx = 0.5
                elif offboard(i):
                    cu = climb_until[i]
                    if cu is None:
                        climb_until[i] = cu = now + CLIMB_S
                    if now >= cu:
                        vx, vz = 0.5, 0.0
                elif fenced[i] and status[i][2] == 3 and now - last_cmd[i] >= 1.0:  # ready
                    last_cmd[i] = now
                    command(i, 176, 1.0, 6.0)  # DO_SET_MODE custom OFFBOARD
                    command(i, 400, 1.0)  # ARM
                # time_boot_ms, x..yaw_rate (11 f), type_mask, target, frame
                payload = sp_struct.pack(0, 0, 0, 0, vx, 0, vz, 0, 0, 0, 0, 0, 3527,
                                         sysids[i], 1, 1)  # fmt: skip
                socks[i].sendto(enc.frame(sp_spec, payload), a)
                setpoints_sent += 1
        for fd, _ in ep.poll(0.005):
            i = fd_index[fd]
            s = socks[i]
            c = counts[i]
            while True:
                try:
                    data, addr = s.recvfrom(2048)
                except BlockingIOError:
                    break
                if len(data) < 10 or data[0] != 0xFD:
                    continue
                msgid = data[7] | (data[8] << 8) | (data[9] << 16)
                if measuring:
                    c[msgid] = c.get(msgid, 0) + 1
                if msgid == 0:
                    pl = data[10:10 + data[1]].ljust(9, b"\x00")
                    cm, _, _, base, sysst, _ = _HB.unpack(pl[:9])
                    status[i] = (cm, base, sysst)
                    if addrs[i] is None:
                        addrs[i] = addr
                    if not requested[i] and requests:
                        requested[i] = True
                        for mid, hz in requests.items():
                            command(i, 511, float(mid), -1.0 if hz <= 0 else 1e6 / hz)
                    if not fenced[i] and last_cmd[i] == 0.0:
                        last_cmd[i] = -1.0  # the fence upload started
                        s.sendto(enc.frame(SPECS["MISSION_COUNT"], SPECS["MISSION_COUNT"].pack(
                            count=len(fence_items[i]), target_system=sysids[i],
                            target_component=1, mission_type=1)), addr)  # fmt: skip
                elif msgid == 51 and not fenced[i]:  # MISSION_REQUEST_INT
                    seq = data[10] | ((data[11] << 8) if data[1] > 1 else 0)
                    if seq < len(fence_items[i]):
                        s.sendto(enc.frame(SPECS["MISSION_ITEM_INT"], fence_items[i][seq]), addr)
                elif msgid == 47 and not fenced[i]:  # MISSION_ACK
                    pl = data[10:10 + data[1]].ljust(4, b"\x00")
                    fenced[i] = pl[2] == 0  # MAV_MISSION_ACCEPTED
                elif msgid == 245:
                    pl = data[10:10 + data[1]].ljust(2, b"\x00")
                    landed[i] = pl[1]
    stop.set()
    res = results.get(timeout=60.0)
    proc.join(timeout=30.0)
    window = args.seconds
    ratios = []
    worst = (2.0, None, None)
    per_msg_min: dict[int, float] = {}
    for i in range(n):
        for msgid, hz in nominal.items():
            expected = hz * window
            if expected < 20:  # too few samples for a ratio (0.33-0.5 Hz streams)
                continue
            r = counts[i].get(msgid, 0) / expected
            ratios.append(r)
            per_msg_min[msgid] = min(per_msg_min.get(msgid, 9.9), r)
            if r < worst[0]:
                worst = (r, i, msgid)
    got = sum(sum(c.values()) for c in counts) / window
    names = {sp.msgid: name for name, sp in SPECS.items()}
    print(f"received {got:.0f} msg/s total ({got / n:.1f} per vehicle) over {window:.0f} s")
    if sp_hz > 0:
        elapsed = time.monotonic() - t0
        print(f"sent {setpoints_sent / elapsed:.0f} setpoints/s to the vehicles "
              f"({sp_hz:g} Hz each)")  # fmt: skip
    if args.fly:
        flying_end = sum(offboard(i) and landed[i] == 2 for i in range(n))
        print(f"in offboard flight (armed, OFFBOARD, IN_AIR): {flying_at_start}/{n} at the "
              f"window's start, {flying_end}/{n} at its end"
              + (f"; geofence uploaded to {sum(fenced)}/{n}" if args.fence else ""))  # fmt: skip
    user_s, sys_s = cpu1[0] - cpu0[0], cpu1[1] - cpu0[1]
    cores = (user_s + sys_s) / (w1 - w0)
    extra = ""
    if res:
        extra = (f"; {res['ticks']} ticks run, {res['late_ticks']} grid ticks missed "
                 f"({args.tick_hz:g} Hz); "
                 f"skipped {res['skipped_msgs']} msgs (loop > 0.25 s behind); tx errors "
                 f"{res['tx_errors']}")  # fmt: skip
    print(
        f"mock CPU ({args.processes or 1} process(es)): {user_s + sys_s:.2f} s (user "
        f"{user_s:.2f}, system {sys_s:.2f}) in {w1 - w0:.2f} s wall = {cores:.3f} cores = "
        f"{1000 * cores / n:.3f} ms per vehicle-second{extra}; load average "
        f"{os.getloadavg()[0]:.2f}"
    )
    print(
        f"rate ratio (received / nominal) over {len(ratios)} vehicle-streams: min "
        f"{min(ratios):.3f} (vehicle {worst[1]}, {names.get(worst[2], worst[2])}), median "
        f"{statistics.median(ratios):.3f}"
    )
    for msgid, r in sorted(per_msg_min.items(), key=lambda x: x[1])[:6]:
        print(
            f"  lowest: {names.get(msgid, msgid):28s} {nominal[msgid]:6.1f} Hz  min ratio {r:.3f}"
        )
    ok = min(ratios) >= 0.9 and cores <= 1.0
    print("PASS" if ok else "FAIL", "(criteria: min ratio >= 0.90 and <= 1.0 core)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
