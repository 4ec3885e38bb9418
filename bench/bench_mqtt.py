"""Benchmark: N agents' neighbour traffic at 20 Hz through a local mosquitto.

    python bench/bench_mqtt.py [--agents 100] [--procs 4] [--rate 20] [--seconds 20]
                               [--warmup 5] [--broker mosquitto|amqtt] [--secured] [--json]

``--secured``: the broker ``vtube-fleet bus-setup`` configures (TLS listener, a password per
agent, the ACL), every agent with its own credentials, as a secured fleet flies.

Each agent is one :class:`~vtube_fleet.bus.mqtt.MqttBus` (its own MQTT connection, last will,
subscriptions to every other vehicle's state, exactly what ``vtube-fleet agent`` uses),
publishing its :class:`~vtube_fleet.state.NeighbourState` at ``--rate`` Hz from its own
asyncio task; the agents are spread over ``--procs`` worker processes (a vehicle's controller
and link are not simulated: only the bus). Measured over ``--seconds`` after ``--warmup``:

* **neighbour-state age** at the receivers: receive wall time − the sender's stamp, for every
  state an agent accepted from another (p50 / p99 / max), and the share of the expected
  deliveries (N·(N−1)·rate·seconds) that arrived;
* **broker CPU**: psutil CPU time of the broker process per wall second (100 % = one core),
  and the workers' CPU likewise;
* publisher side: states sent, superseded in the one-slot mailbox (the sender could not keep
  up), dropped while disconnected.

Run by hand (not in CI); it uses both cores. Numbers are for THIS machine.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import subprocess
import sys
import time
from array import array
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vtube_fleet.bus.mqtt import MqttBus  # noqa: E402
from vtube_fleet.state import NeighbourState, Phase  # noqa: E402

MISSION_ID = "bench"


# ----------------------------------------------------------------------------------------------
# worker process: a slice of the agents
# ----------------------------------------------------------------------------------------------
def position(vid: int, across: int, t: float) -> tuple[float, float]:
    """Vehicle ``vid`` of a block ``across`` wide on a 2.5 m grid, moving along x at 1 m/s."""
    row, col = divmod(vid, across)
    return 2.5 * row + (t % 1000.0), 2.5 * col


async def _agent(
    bus: MqttBus,
    vid: int,
    rate: float,
    t_measure: float,
    t_end: float,
    sent: list[int],
    across: int,
) -> None:
    period = 1.0 / rate
    loop = asyncio.get_running_loop()
    await asyncio.sleep((vid % 97) / 97 * period)  # spread the agents over the period
    next_t = loop.time()
    seq = 0
    while time.time() < t_end:
        seq += 1
        now = time.time()
        x, y = position(vid, across, now)
        bus.publish(NeighbourState(vid, x, y, 1.0, 0.0, Phase.IN_TUBE, now, seq))
        if t_measure <= now <= t_end:
            sent[0] += 1
        next_t += period
        await asyncio.sleep(max(0.0, next_t - loop.time()))  # the agent's control clock


async def _worker(
    url: str,
    ids: list[int],
    rate: float,
    t_measure: float,
    t_end: float,
    cell_m: float,
    across: int,
    setup: str | None = None,
) -> dict:
    ages = array("d")

    def on_state(state: NeighbourState, received: float) -> None:
        if t_measure <= received <= t_end:
            ages.append(received - state.stamp_s)

    def creds(vid: int) -> Path | None:
        return None if setup is None else Path(setup) / "credentials" / f"vehicle-{vid}.toml"

    buses = [MqttBus(url, MISSION_ID, vid, keepalive_s=5, cell_m=cell_m, credentials=creds(vid))
             for vid in ids]
    for b in buses:
        b.add_state_listener(on_state)
        b.start()
    for b in buses:
        await b.wait_connected(60)
    sent = [0]
    await asyncio.gather(
        *(
            _agent(b, vid, rate, t_measure, t_end, sent, across)
            for b, vid in zip(buses, ids, strict=True)
        )
    )
    stats = [b.stats for b in buses]
    for b in buses:
        await b.close()
    return {
        "ages": list(ages),
        "published": sent[0],
        "superseded": sum(s.superseded for s in stats),
        "dropped_offline": sum(s.dropped_offline for s in stats),
        "dropped_stale": sum(s.dropped_stale for s in stats),
        "received": sum(s.received for s in stats),
    }


def worker_main(args: argparse.Namespace) -> int:
    ids = [int(i) for i in args.ids.split(",")]
    out = asyncio.run(
        _worker(args.url, ids, args.rate, args.t_measure, args.t_end, args.cell, args.across,
                args.setup)
    )
    Path(args.result).write_text(json.dumps(out))
    return 0


# ----------------------------------------------------------------------------------------------
# parent: broker, workers, numbers
# ----------------------------------------------------------------------------------------------
def _pct(a: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(a), q)) if a else math.nan


def heard_pairs(n: int, across: int, cell_m: float, t: float) -> int:
    """Ordered pairs (i hears j) at time ``t``: j in the 3×3 cells around i (all with inf)."""
    bus = MqttBus("mqtt://127.0.0.1", MISSION_ID, 0, cell_m=cell_m)
    cells = [bus.cell_of(*position(v, across, t)) for v in range(n)]
    return sum(
        1
        for i in range(n)
        for j in range(n)
        if i != j and abs(cells[i][0] - cells[j][0]) <= 1 and abs(cells[i][1] - cells[j][1]) <= 1
    )


def run(args: argparse.Namespace) -> dict:
    import tempfile

    import psutil

    sys.path.insert(0, str(ROOT / "tests"))
    from broker import LocalBroker, free_port

    from vtube_fleet.bus.security import bus_setup

    n, procs = args.agents, max(1, min(args.procs, args.agents))
    tmp = Path(tempfile.mkdtemp(prefix="bench-mqtt-"))
    setup = (bus_setup(tmp / "bus", MISSION_ID, n, port=free_port(), bind="127.0.0.1")
             if args.secured else None)
    with (LocalBroker(config=setup.conf, ca_file=setup.ca_file) if setup is not None
          else LocalBroker(kind=args.broker)) as broker:
        bproc = psutil.Process(broker.pid)
        t_measure = time.time() + 2.0 + args.warmup  # after start-up and the warm-up
        t_end = t_measure + args.seconds
        chunks = [list(range(n))[k::procs] for k in range(procs)]
        workers = []
        for k, ids in enumerate(chunks):
            workers.append(
                subprocess.Popen(
                    [
                        sys.executable,
                        __file__,
                        "--worker",
                        "--url",
                        broker.url,
                        "--ids",
                        ",".join(map(str, ids)),
                        "--agents",
                        str(n),
                        "--rate",
                        str(args.rate),
                        "--cell",
                        repr(args.cell),
                        "--across",
                        str(args.across),
                        "--t-measure",
                        repr(t_measure),
                        "--t-end",
                        repr(t_end),
                        "--result",
                        str(tmp / f"w{k}.json"),
                        *(["--setup", str(setup.out)] if setup is not None else []),
                    ]
                )
            )
        wprocs = [psutil.Process(w.pid) for w in workers]
        time.sleep(max(0.0, t_measure - time.time()))  # until the measurement window opens
        b0 = bproc.cpu_times()
        w0 = [p.cpu_times() for p in wprocs]
        m0 = time.time()
        time.sleep(max(0.0, t_end - time.time()))
        b1 = bproc.cpu_times()
        w1 = [p.cpu_times() for p in wprocs]
        wall = time.time() - m0
        for w in workers:
            if w.wait(timeout=120) != 0:
                raise SystemExit(f"worker {w.pid} failed with code {w.returncode}")
    results = [json.loads((tmp / f"w{k}.json").read_text()) for k in range(procs)]
    ages = [a for r in results for a in r["ages"]]
    expected = heard_pairs(n, args.across, args.cell, t_measure) * args.rate * args.seconds
    broker_cpu = (b1.user + b1.system - b0.user - b0.system) / wall
    worker_cpu = (
        sum((b.user + b.system - a.user - a.system) for a, b in zip(w0, w1, strict=True)) / wall
    )
    return {
        "agents": n,
        "procs": procs,
        "rate_hz": args.rate,
        "seconds": args.seconds,
        "broker": args.broker,
        "secured": bool(args.secured),
        "cell_m": args.cell,
        "across": args.across,
        "heard_per_agent": heard_pairs(n, args.across, args.cell, t_measure) / n,
        "published_msgs_per_s": sum(r["published"] for r in results) / args.seconds,
        "deliveries_expected": int(expected),
        "deliveries_measured": len(ages),
        "delivered_share": len(ages) / expected if expected else math.nan,
        "age_p50_ms": 1000 * _pct(ages, 50),
        "age_p99_ms": 1000 * _pct(ages, 99),
        "age_max_ms": 1000 * max(ages) if ages else math.nan,
        "broker_cpu_percent": 100 * broker_cpu,
        "workers_cpu_percent": 100 * worker_cpu,
        "superseded": sum(r["superseded"] for r in results),
        "dropped_offline": sum(r["dropped_offline"] for r in results),
        "dropped_stale": sum(r["dropped_stale"] for r in results),
        "cores": os.cpu_count(),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=100)
    p.add_argument("--procs", type=int, default=4)
    p.add_argument("--rate", type=float, default=20.0)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup", type=float, default=5.0)
    p.add_argument("--broker", choices=("mosquitto", "amqtt"), default="mosquitto")
    p.add_argument(
        "--cell",
        type=float,
        default=math.inf,
        help="cell size in metres (default inf: every agent hears every agent)",
    )
    p.add_argument(
        "--across",
        type=int,
        default=10,
        help="vehicles per row of the moving 2.5 m grid (default 10)",
    )
    p.add_argument("--secured", action="store_true",
                   help="TLS, passwords and ACL of `vtube-fleet bus-setup` (mosquitto)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--setup", help=argparse.SUPPRESS)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--url", help=argparse.SUPPRESS)
    p.add_argument("--ids", help=argparse.SUPPRESS)
    p.add_argument("--t-measure", type=float, help=argparse.SUPPRESS)
    p.add_argument("--t-end", type=float, help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker_main(args)
    r = run(args)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"{r['agents']} agents in {r['procs']} processes at {r['rate_hz']:g} Hz through "
        f"{r['broker']}{' (secured: TLS, passwords, ACL)' if r['secured'] else ''} "
        f"({r['seconds']:g} s measured, {r['cores']} cores); cells "
        f"{r['cell_m']:g} m, {r['across']} across: each agent hears "
        f"{r['heard_per_agent']:.1f} others:\n"
        f"  neighbour-state age p50 {r['age_p50_ms']:.1f} ms, p99 {r['age_p99_ms']:.1f} ms, "
        f"max {r['age_max_ms']:.1f} ms\n"
        f"  delivered {r['deliveries_measured']} of {r['deliveries_expected']} expected "
        f"({100 * r['delivered_share']:.1f} %); published {r['published_msgs_per_s']:.0f} "
        f"states/s; superseded in the mailbox {r['superseded']}\n"
        f"  broker CPU {r['broker_cpu_percent']:.0f} % of a core; agents' processes "
        f"{r['workers_cpu_percent']:.0f} %"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
