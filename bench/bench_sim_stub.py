"""Benchmark: one process serving N mock PX4 vehicles at PX4's telemetry rates.

    python bench/bench_sim_stub.py [--count 200] [--seconds 30] [--profile full|lite]
                                   [--no-requests]

The mock fleet runs in a child process (one asyncio loop, one scheduler tick). A receiver in this
process binds the N GCS ports, sends each vehicle the same four SET_MESSAGE_INTERVAL commands the
capture GCS sent (LOCAL_POSITION_NED 50 Hz, GLOBAL_POSITION_INT 10 Hz, EXTENDED_SYS_STATE 5 Hz,
HOME_POSITION 1 Hz; skip with --no-requests) once the vehicle's first HEARTBEAT arrives, and counts
every datagram per vehicle and message id. After the warm-up (boot), it compares each vehicle's
per-message rate over the measurement window with the nominal rate and prints the minimum ratio.
The mock process reports its own CPU time (user + system, ``os.times``) over the same window:
``cpu_cores = cpu_seconds / wall_seconds`` (1.0 = one core fully busy).
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import selectors
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
from sim_stub.ports import free_port_scheme  # noqa: E402
from sim_stub.telemetry import STREAM_CATALOG  # noqa: E402

WARMUP_S = 8.0  # boot (~5.6 s) plus the interval requests
REQUESTS = {32: 50.0, 33: 10.0, 245: 5.0, 242: 1.0}  # msgid -> Hz (capture GCS)


def nominal_rates(profile: str, requests: bool) -> dict[int, float]:
    rates = {}
    for sd in STREAM_CATALOG:
        hz = sd.full_hz if profile == "full" else sd.lite_hz
        if hz > 0:
            rates[SPECS[sd.name].msgid] = hz
    if requests:
        for msgid, hz in REQUESTS.items():
            rates[msgid] = hz
    return rates


def mock_process(count, scheme_args, profile, seconds, ready, results) -> None:
    async def run() -> None:
        scheme = PortScheme(*scheme_args)
        fleet = MockFleet(count, port_scheme=scheme, profile=profile, spacing_m=5.0)
        async with fleet:
            ready.set()
            t_start = time.monotonic()
            await asyncio.sleep(WARMUP_S)
            c0, w0 = os.times(), time.monotonic()
            await asyncio.sleep(seconds)
            c1, w1 = os.times(), time.monotonic()
            sched = fleet.scheduler
            results.put(
                {
                    "cpu_s": (c1.user - c0.user) + (c1.system - c0.system),
                    "wall_s": w1 - w0,
                    "late_ticks": sched.late_ticks,
                    "skipped_msgs": sched.skipped_msgs,
                    "ticks": sched._ticks,
                    "tx_packets": sum(v.counters.tx_packets for v in fleet.vehicles),
                    "tx_errors": sum(v.counters.tx_errors for v in fleet.vehicles),
                    "uptime": time.monotonic() - t_start,
                }
            )
            await asyncio.sleep(1.0)

    asyncio.run(run())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=30.0, help="measurement window")
    ap.add_argument("--profile", choices=("full", "lite"), default="full")
    ap.add_argument("--no-requests", action="store_true", help="keep PX4's default rates")
    ap.add_argument("--setpoint-hz", type=float, default=0.0,
                    help="also send each vehicle SET_POSITION_TARGET_LOCAL_NED at this rate, "
                    "like a fleet controller (e.g. 20)")  # fmt: skip
    args = ap.parse_args()
    n = args.count
    scheme = free_port_scheme(n)
    nominal = nominal_rates(args.profile, not args.no_requests)
    print(
        f"bench_sim_stub: {n} vehicles, profile {args.profile}, "
        f"{'capture GCS interval requests' if not args.no_requests else 'default rates'}, "
        f"nominal {sum(nominal.values()):.1f} msg/s per vehicle, "
        f"{n * sum(nominal.values()):.0f} msg/s total; ports {scheme.vehicle_base}+i -> "
        f"{scheme.gcs_base}+i",
        flush=True,
    )
    # receiver sockets first, so nothing is lost at boot
    sel = selectors.DefaultSelector()
    socks = []
    for i in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.bind((scheme.host, scheme.gcs_port(i)))
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ, i)
        socks.append(s)
    ctx = mp.get_context("spawn")
    ready = ctx.Event()
    results = ctx.Queue()
    proc = ctx.Process(
        target=mock_process,
        args=(n, (scheme.name, scheme.vehicle_base, scheme.gcs_base, scheme.host), args.profile,
              args.seconds, ready, results),
    )  # fmt: skip
    proc.start()
    if not ready.wait(30.0):
        print("error: mock process did not start", file=sys.stderr)
        proc.kill()
        return 2
    t0 = time.monotonic()
    enc = Encoder(255, 190)
    cl = mav.MAVLink_command_long_message
    cl_struct = struct.Struct(cl.unpacker.format)  # param1..7, command, target sys/comp, conf
    cl_spec = MsgSpec(
        "COMMAND_LONG", cl.id, cl.crc_extra, cl_struct, tuple(cl.ordered_fieldnames), (1,) * 11
    )
    requested = [False] * n
    addrs: list[tuple[str, int] | None] = [None] * n
    sp = mav.MAVLink_set_position_target_local_ned_message
    sp_struct = struct.Struct(sp.unpacker.format)
    sp_spec = MsgSpec(
        "SET_POSITION_TARGET_LOCAL_NED", sp.id, sp.crc_extra, sp_struct,
        tuple(sp.ordered_fieldnames), (1,) * 16,
    )  # fmt: skip
    next_sp = time.monotonic()
    setpoints_sent = 0
    counts: list[dict[int, int]] = [dict() for _ in range(n)]
    t_meas0 = t0 + WARMUP_S
    t_meas1 = t_meas0 + args.seconds
    recv_count = 0
    while True:
        now = time.monotonic()
        if now >= t_meas1:
            break
        measuring = now >= t_meas0
        if args.setpoint_hz > 0 and now >= next_sp:
            next_sp += 1.0 / args.setpoint_hz
            for i, a in enumerate(addrs):
                if a is not None:  # time_boot_ms, x..yaw_rate (11 f), type_mask, target, frame
                    payload = sp_struct.pack(0, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0, 3527,
                                             i % 254 + 1, 1, 1)  # fmt: skip
                    socks[i].sendto(enc.frame(sp_spec, payload), a)
                    setpoints_sent += 1
        for key, _ in sel.select(timeout=0.01):
            s = key.fileobj
            i = key.data
            c = counts[i]
            while True:
                try:
                    data, addr = s.recvfrom(2048)  # type: ignore[union-attr]
                except BlockingIOError:
                    break
                recv_count += 1
                if len(data) < 10:
                    continue
                msgid = data[7] | (data[8] << 8) | (data[9] << 16)
                if measuring:
                    c[msgid] = c.get(msgid, 0) + 1
                if addrs[i] is None:
                    addrs[i] = addr
                if msgid == 0 and not requested[i] and not args.no_requests:
                    requested[i] = True
                    sysid = i % 254 + 1  # MockFleet's sysids wrap beyond 254 vehicles
                    for mid, hz in REQUESTS.items():
                        payload = cl_struct.pack(mid, 1e6 / hz, 0, 0, 0, 0, 0, 511, sysid, 1, 0)
                        s.sendto(enc.frame(cl_spec, payload), addr)  # type: ignore[union-attr]
    res = results.get(timeout=30.0)
    proc.join(timeout=10.0)
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
    if args.setpoint_hz > 0:
        elapsed = time.monotonic() - t0
        print(f"sent {setpoints_sent / elapsed:.0f} setpoints/s to the vehicles "
              f"({args.setpoint_hz:g} Hz each)")  # fmt: skip
    print(
        f"mock process CPU: {res['cpu_s']:.2f} s in {res['wall_s']:.2f} s wall = "
        f"{res['cpu_s'] / res['wall_s']:.2f} cores; {res['ticks']} ticks run, "
        f"{res['late_ticks']} grid ticks missed (100 Hz); skipped {res['skipped_msgs']} msgs "
        f"(loop > 0.25 s behind); tx errors {res['tx_errors']}"
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
    ok = min(ratios) >= 0.9 and res["cpu_s"] / res["wall_s"] <= 1.0
    print("PASS" if ok else "FAIL", "(criteria: min ratio >= 0.90 and <= 1.0 core)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
