"""Benchmark: N agents' neighbour traffic at 20 Hz through a local mosquitto.

    python bench/bench_mqtt.py [--agents 100] [--procs 4] [--rate 20] [--seconds 20]
                               [--warmup 5] [--cell M] [--across K] [--broker mosquitto|amqtt]
                               [--client own|gmqtt] [--secured] [--profile FILE] [--json]

``--secured``: the broker ``vtube-fleet bus-setup`` configures (TLS listener, a password per
agent, the ACL), every agent with its own credentials, as a secured fleet flies.

``--client gmqtt``: the same :class:`MqttBus` on gmqtt (``pip install gmqtt``) instead of our
:class:`~vtube_fleet.bus.client.MqttClient`, through the adapter ``bench/gmqtt_client.py`` (the
same interface): both clients measured by the same runs of the same bench.

``--parse N``: instead of the fleet, the chosen client's receive path alone, in this process:
N PUBLISH packets of an agent's state (the bus's topic and codec), ``--parse-chunk`` packets
per chunk as the socket hands them over, through the client's parser to an ``on_message``
that does nothing; process time per message (the best of 5 rounds), which the load of other
work hardly changes. The fleet's numbers include the bus's own work per state; this is the
client's part of it.

Each agent is one :class:`~vtube_fleet.bus.mqtt.MqttBus` (its own MQTT connection, last will,
subscriptions to every other vehicle's state, exactly what ``vtube-fleet agent`` uses),
publishing its :class:`~vtube_fleet.state.NeighbourState` at ``--rate`` Hz from its own
asyncio task; the agents are spread over ``--procs`` worker processes (a vehicle's controller
and link are not simulated: only the bus). The warm-up starts when every worker reports all its
agents connected. Measured over ``--seconds`` after ``--warmup``:

* **neighbour-state age** at the receivers: receive wall time − the sender's stamp, for every
  state an agent accepted from another (p50 / p99 / max), and the share of the expected
  deliveries (N·(N−1)·rate·seconds) that arrived;
* **broker CPU**: psutil CPU time of the broker process per wall second (100 % = one core),
  and the workers' CPU likewise; both also per received state (less sensitive to the load of
  other work than the ages), and the 1-minute load average at the start and the end;
* ``--profile FILE``: the first worker under cProfile (CPU time) over the window;
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

from vtube_fleet.bus.client import MqttClient  # noqa: E402
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
    cell_m: float,
    across: int,
    setup: str | None = None,
    profile: str | None = None,
    client: str = "own",
) -> dict:
    ages = array("d")
    window = [math.inf, -math.inf]  # the measurement window, once the parent has sent it

    def on_state(state: NeighbourState, received: float) -> None:
        if window[0] <= received <= window[1]:
            ages.append(received - state.stamp_s)

    def creds(vid: int) -> Path | None:
        return None if setup is None else Path(setup) / "credentials" / f"vehicle-{vid}.toml"

    bus_class = MqttBus if client == "own" else _gmqtt_bus_class()
    buses = [bus_class(url, MISSION_ID, vid, keepalive_s=5, cell_m=cell_m,
                       credentials=creds(vid)) for vid in ids]
    for b in buses:
        b.add_state_listener(on_state)
        b.start()
    for b in buses:
        await b.wait_connected(60)
    # every agent of this worker is connected: tell the parent, which opens the measurement
    # window (after its warm-up) once every worker is, so start-up never counts
    loop = asyncio.get_running_loop()
    print("ready", flush=True)
    line = await loop.run_in_executor(None, sys.stdin.readline)
    t_measure, t_end = (float(v) for v in line.split())
    window[:] = [t_measure, t_end]
    prof = None
    if profile is not None:
        import cProfile

        prof = cProfile.Profile(time.process_time)  # CPU, not time spent descheduled
        loop.call_at(loop.time() + (t_measure - time.time()), prof.enable)
        loop.call_at(loop.time() + (t_end - time.time()), prof.disable)
    sent = [0]
    await asyncio.gather(
        *(
            _agent(b, vid, rate, t_measure, t_end, sent, across)
            for b, vid in zip(buses, ids, strict=True)
        )
    )
    if prof is not None:
        prof.disable()
        prof.dump_stats(profile)
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


def _gmqtt_bus_class() -> type[MqttBus]:
    """:class:`MqttBus` with the gmqtt adapter as its client (everything else the same)."""
    from gmqtt_client import GmqttClient  # bench/gmqtt_client.py (needs `pip install gmqtt`)

    class GmqttBus(MqttBus):
        def _make_client(self) -> MqttClient:
            return GmqttClient.like(super()._make_client())  # type: ignore[return-value]

    return GmqttBus


def worker_main(args: argparse.Namespace) -> int:
    ids = [int(i) for i in args.ids.split(",")]
    out = asyncio.run(
        _worker(args.url, ids, args.rate, args.cell, args.across, args.setup,
                args.worker_profile, args.client)
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
    import numpy as np

    if not math.isfinite(cell_m):
        return n * (n - 1)
    xy = np.array([position(v, across, t) for v in range(n)])
    cells = np.floor(xy / cell_m)  # MqttBus.cell_of
    near = np.all(np.abs(cells[:, None, :] - cells[None, :, :]) <= 1, axis=2)
    return int(near.sum()) - n


def expected_deliveries(n: int, across: int, cell_m: float, rate: float, t0: float,
                        seconds: float) -> float:
    """Deliveries the window should see: the heard pairs at every control tick of it (the grid
    moves, so who hears whom changes as the vehicles cross cell borders)."""
    ticks = max(1, round(rate * seconds))
    return sum(heard_pairs(n, across, cell_m, t0 + (k + 0.5) / rate) for k in range(ticks))


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
                        "--result",
                        str(tmp / f"w{k}.json"),
                        "--client",
                        args.client,
                        *(["--setup", str(setup.out)] if setup is not None else []),
                        *(["--worker-profile", args.profile]
                          if args.profile is not None and k == 0 else []),
                    ],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    text=True,
                )
            )
        for w in workers:  # every agent connected (start-up is not part of the warm-up)
            if w.stdout is None or w.stdout.readline().strip() != "ready":
                raise SystemExit(f"worker {w.pid} failed to start (code {w.wait()})")
        t_measure = time.time() + args.warmup
        t_end = t_measure + args.seconds
        for w in workers:
            assert w.stdin is not None
            w.stdin.write(f"{t_measure!r} {t_end!r}\n")
            w.stdin.flush()
        wprocs = [psutil.Process(w.pid) for w in workers]
        time.sleep(max(0.0, t_measure - time.time()))  # until the measurement window opens
        load0 = os.getloadavg()[0]
        b0 = bproc.cpu_times()
        w0 = [p.cpu_times() for p in wprocs]
        m0 = time.time()
        time.sleep(max(0.0, t_end - time.time()))
        b1 = bproc.cpu_times()
        w1 = [p.cpu_times() for p in wprocs]
        wall = time.time() - m0
        load1 = os.getloadavg()[0]
        for w in workers:
            if w.wait(timeout=120) != 0:
                raise SystemExit(f"worker {w.pid} failed with code {w.returncode}")
    results = [json.loads((tmp / f"w{k}.json").read_text()) for k in range(procs)]
    ages = [a for r in results for a in r["ages"]]
    expected = expected_deliveries(n, args.across, args.cell, args.rate, t_measure,
                                   args.seconds)
    broker_cpu = (b1.user + b1.system - b0.user - b0.system) / wall
    worker_cpu_s = sum((b.user + b.system - a.user - a.system)
                       for a, b in zip(w0, w1, strict=True))
    worker_cpu = worker_cpu_s / wall
    return {
        "agents": n,
        "procs": procs,
        "rate_hz": args.rate,
        "seconds": args.seconds,
        "broker": args.broker,
        "client": args.client,
        "secured": bool(args.secured),
        "cell_m": args.cell,
        "across": args.across,
        "heard_per_agent": expected / (args.rate * args.seconds) / n,
        "published_msgs_per_s": sum(r["published"] for r in results) / args.seconds,
        "deliveries_expected": int(expected),
        "deliveries_measured": len(ages),
        "delivered_share": len(ages) / expected if expected else math.nan,
        "age_p50_ms": 1000 * _pct(ages, 50),
        "age_p99_ms": 1000 * _pct(ages, 99),
        "age_max_ms": 1000 * max(ages) if ages else math.nan,
        "broker_cpu_percent": 100 * broker_cpu,
        "workers_cpu_percent": 100 * worker_cpu,
        # the agents' CPU (publishing included) per state received: less load-sensitive
        "workers_cpu_us_per_received": 1e6 * worker_cpu_s / len(ages) if ages else math.nan,
        "broker_cpu_us_per_delivered": (1e6 * broker_cpu * wall / len(ages) if ages
                                        else math.nan),
        "load_average_1min": [load0, load1],
        "superseded": sum(r["superseded"] for r in results),
        "dropped_offline": sum(r["dropped_offline"] for r in results),
        "dropped_stale": sum(r["dropped_stale"] for r in results),
        "cores": os.cpu_count(),
    }


def parse_only(client: str, n: int, per_chunk: int) -> dict:
    """``--parse``: µs of process time per PUBLISH through the client's receive path."""
    from vtube_fleet.bus.codec import encode_state
    from vtube_fleet.bus.topics import MissionTopics

    topics = MissionTopics(MISSION_ID)
    packets = []
    for k in range(n):
        vid = k % 100
        body = (len(t := topics.state(vid, (k % 7, -(k % 3))).encode()).to_bytes(2, "big") + t
                + encode_state(NeighbourState(vid, 1.0 * k, 2.0, 1.0, 0.0, Phase.IN_TUBE,
                                              time.time(), k)))
        packets.append(bytes((0x30, len(body))) + body)
    chunks = [b"".join(packets[i:i + per_chunk]) for i in range(0, n, per_chunk)]
    got = [0]

    def sink(topic: str, payload: bytes) -> None:
        got[0] += 1

    if client == "own":
        c = MqttClient("127.0.0.1", 1, client_id="parse", on_message=sink)
        feed = c._feed
    else:
        feed = _gmqtt_parser(sink)
    best = math.inf
    for _ in range(5):
        got[0] = 0
        t0 = time.process_time()
        for ch in chunks:
            feed(ch)
        best = min(best, time.process_time() - t0)
        assert got[0] == n, (got[0], n)
    return {"client": client, "messages": n, "per_chunk": per_chunk,
            "us_per_message": 1e6 * best / n, "load_average_1min": os.getloadavg()[0]}


def _gmqtt_parser(sink):  # noqa: ANN001, ANN202 - bench only
    """gmqtt's receive path after the socket read: its protocol's packet splitter, a real
    MQTTConnection and package handler (MQTT 3.1.1), the adapter's on_message."""
    from gmqtt.mqtt.connection import MQTTConnection
    from gmqtt.mqtt.constants import MQTTv311
    from gmqtt.mqtt.protocol import MQTTProtocol
    from gmqtt_client import GmqttClient

    asyncio.set_event_loop(loop := asyncio.new_event_loop())
    g = GmqttClient("127.0.0.1", 1, client_id="parse", on_message=sink)
    c = g._c
    c._connection_state.protocol_version = MQTTv311

    class _Transport:  # nothing is written while parsing QoS-0 messages
        def is_closing(self) -> bool:
            return False

    proto = MQTTProtocol(connection_state=c._connection_state,
                         id_generator=c._package_handler.id_generator, loop=loop)
    MQTTConnection(_Transport(), proto, True, 60, package_handler=c._package_handler)
    buf = [b""]

    def feed(data: bytes) -> None:  # what its read loop does with each chunk read
        b = buf[0] + data
        buf[0] = b[proto._read_packet(b):]

    return feed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=100)
    p.add_argument("--procs", type=int, default=4)
    p.add_argument("--rate", type=float, default=20.0)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup", type=float, default=5.0)
    p.add_argument("--broker", choices=("mosquitto", "amqtt"), default="mosquitto")
    p.add_argument("--client", choices=("own", "gmqtt"), default="own",
                   help="the bus's MQTT client: ours (vtube_fleet.bus.client) or gmqtt "
                        "(through bench/gmqtt_client.py; pip install gmqtt)")
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
    p.add_argument("--profile", metavar="FILE",
                   help="cProfile the first worker process over the measured seconds into FILE "
                        "(pstats format)")
    p.add_argument("--parse", type=int, metavar="N", default=None,
                   help="measure only the client's receive path: N packets (see above)")
    p.add_argument("--parse-chunk", type=int, metavar="K", default=4,
                   help="--parse: packets per chunk read from the socket (default 4)")
    p.add_argument("--setup", help=argparse.SUPPRESS)
    p.add_argument("--worker-profile", help=argparse.SUPPRESS)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--url", help=argparse.SUPPRESS)
    p.add_argument("--ids", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker_main(args)
    if args.parse is not None:
        r = parse_only(args.client, args.parse, max(1, args.parse_chunk))
        print(json.dumps(r, indent=2) if args.json else
              f"client {r['client']}: {r['us_per_message']:.2f} µs of process time per "
              f"PUBLISH received ({r['messages']} messages, {r['per_chunk']} per chunk; "
              f"load average {r['load_average_1min']:.2f})")
        return 0
    r = run(args)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"{r['agents']} agents in {r['procs']} processes at {r['rate_hz']:g} Hz through "
        f"{r['broker']}{' (secured: TLS, passwords, ACL)' if r['secured'] else ''}, client "
        f"{r['client']} "
        f"({r['seconds']:g} s measured, {r['cores']} cores); cells "
        f"{r['cell_m']:g} m, {r['across']} across: each agent hears "
        f"{r['heard_per_agent']:.1f} others:\n"
        f"  neighbour-state age p50 {r['age_p50_ms']:.1f} ms, p99 {r['age_p99_ms']:.1f} ms, "
        f"max {r['age_max_ms']:.1f} ms\n"
        f"  delivered {r['deliveries_measured']} of {r['deliveries_expected']} expected "
        f"({100 * r['delivered_share']:.1f} %); published {r['published_msgs_per_s']:.0f} "
        f"states/s; superseded in the mailbox {r['superseded']}\n"
        f"  broker CPU {r['broker_cpu_percent']:.0f} % of a core; agents' processes "
        f"{r['workers_cpu_percent']:.0f} % ({r['workers_cpu_us_per_received']:.1f} µs per "
        f"received state; broker {r['broker_cpu_us_per_delivered']:.1f} µs per delivery)\n"
        f"  load average (1 min) {r['load_average_1min'][0]:.2f} at the start, "
        f"{r['load_average_1min'][1]:.2f} at the end of the measurement"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
