"""Benchmark: the control loop's lateness while a re-partition runs in the worker thread.

    python bench/bench_gil.py [--seconds 10] [--switch-ms 5 0.5 0.2 0.1]

The runtime plans re-partitions around lost vehicles in a worker thread
(``fleet.tick.Tick.replan_worker``). That thread runs Python (the partition construction)
and holds the interpreter lock; the event loop needs it again after every ``select``
(telemetry datagrams, the tick's timer). With CPython's default switch interval (5 ms) each of
those wake-ups can wait up to 5 ms, so the loop falls behind: the convoy effect. This bench
runs an asyncio loop ticking at 20 Hz (a small numpy workload per tick) that receives ~300
datagrams/s from a child process (3 vehicles' telemetry), with and without a thread that
re-partitions ``configs/px4_sitl_3.toml`` around a lost vehicle over and over
(``core.loss.partition_around_lost``), for each switch interval, and prints the ticks run (of
``20 × seconds``), their lateness (p50, p99, max), the datagrams handled and the re-partitions
the thread finished. ``fleet.tick.GIL_SWITCH_S`` is the interval the control clock sets.

Run by hand (not in CI).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_loss  # noqa: E402

from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.core import loss  # noqa: E402
from vtube_fleet.core.partition import PartitionError, h_min  # noqa: E402
from vtube_fleet.core.tube import Obstacle  # noqa: E402
from vtube_fleet.fleet.flight_plan import LOST_APEX_FACTOR  # noqa: E402

PERIOD_S = 0.05


class _Sink(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.count = 0

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.count += 1
        np.frombuffer(data, dtype=np.uint8).sum()  # a little decoding work


def _replan_forever(stop: threading.Event, done: list[int]) -> None:
    mission = load_mission(ROOT / "configs" / "px4_sitl_3.toml")
    flown = bench_loss.flown_params(mission)
    r_lost = bench_loss.lost_radius(mission)
    sc = mission.scenario
    k = 0
    while not stop.is_set():
        lost = (Obstacle(np.array([12.0 + k % 20, -6.0]), r_lost,
                         LOST_APEX_FACTOR * h_min(r_lost, flown)),)
        k += 1
        try:
            loss.partition_around_lost(sc.tube, sc.obstacles, lost, flown)
        except PartitionError:
            pass
        done[0] += 1


async def _loop(seconds: float) -> tuple[np.ndarray, int]:
    loop = asyncio.get_running_loop()
    sink = _Sink()
    transport, _ = await loop.create_datagram_endpoint(lambda: sink,
                                                       local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    pid = os.fork()
    if pid == 0:  # the vehicles: 3 datagrams every 10 ms
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        end = time.time() + seconds + 1.0
        while time.time() < end:
            for _ in range(3):
                s.sendto(b"x" * 60, ("127.0.0.1", port))
            time.sleep(0.01)
        os._exit(0)
    late = []
    next_t = loop.time() + PERIOD_S
    end_t = loop.time() + seconds
    rng = np.random.default_rng(0)
    while loop.time() < end_t:
        await asyncio.sleep(max(0.0, next_t - loop.time()))
        late.append(loop.time() - next_t)
        a = rng.random((200, 2))
        float((a @ a.T).sum())  # the tick's work
        next_t += PERIOD_S
        if loop.time() > next_t:  # not caught up, as the control clock
            next_t = loop.time() + PERIOD_S
    os.waitpid(pid, 0)
    transport.close()
    return 1000.0 * np.asarray(late), sink.count


def run(switch_s: float, with_thread: bool, seconds: float) -> str:
    before = sys.getswitchinterval()
    sys.setswitchinterval(switch_s)
    stop, done = threading.Event(), [0]
    thread = threading.Thread(target=_replan_forever, args=(stop, done), daemon=True)
    if with_thread:
        thread.start()
    try:
        late, datagrams = asyncio.run(_loop(seconds))
    finally:
        stop.set()
        if with_thread:
            thread.join()
        sys.setswitchinterval(before)
    what = "re-partitioning thread" if with_thread else "no thread"
    return (f"switch {switch_s * 1000:g} ms, {what}: ticks {late.size}/"
            f"{int(seconds / PERIOD_S)}, late p50 "
            f"{np.percentile(late, 50):.1f} p99 {np.percentile(late, 99):.1f} max "
            f"{late.max():.1f} ms, datagrams {datagrams}, re-partitions {done[0]}")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--switch-ms", type=float, nargs="+", default=[5.0, 0.5, 0.2, 0.1])
    args = ap.parse_args(argv)
    print(run(args.switch_ms[0] / 1000.0, False, args.seconds), flush=True)
    for ms in args.switch_ms:
        print(run(ms / 1000.0, True, args.seconds), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
