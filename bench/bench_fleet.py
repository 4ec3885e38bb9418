"""Benchmark: one supervisor process drives N sim_stub vehicles (in ANOTHER process) at 20 Hz.

    python bench/bench_fleet.py [--count 200] [--seconds 30] [--rate 20] [--backend mavlink]
                                [--processes N] [--spacing M] [--no-fence] [--profile-out FILE]
                                [--lean-streams] [--position-hz HZ] [--mock-nice N] [--pin]
                                [--tick-hz HZ] [--record] [--serve-web PORT]
                                [--live-viewer {chromium,grpc}] [--live-viewer-nice N]

1. writes a mission with N slots (a wide straight tube, one obstacle, ``--spacing`` grid, 5 m;
   ``latency_s = 0.25`` fixed, so the in-flight budget watch does not end a run on a loaded
   machine) to a temp dir;
2. starts ``vtube-fleet mock-fleet MISSION --processes N`` (sim_stub vehicles in the slots,
   split over N mock processes, default one per 250 vehicles; on a free range of UDP ports,
   no GCS link) and reads its endpoints;
3. runs the :class:`~vtube_fleet.fleet.supervisor.Supervisor` in this process (connect, preflight,
   take-off, tube) and measures, over ``--seconds`` of tube flight: ticks, the share of ticks on
   time (started at most half a period after schedule), p50/p99/max tick duration, achieved
   rate, the CPU time of THIS process (user + system) per wall second and per tick, the CPU of
   the mock processes (the mock-fleet process and its children) and of the whole machine
   (/proc/stat) over the same window; ``connect_timeout_s`` is 0.15 s per vehicle (at least
   60 s); ``--lean-streams`` asks for fewer telemetry messages (:data:`LEAN_STREAMS_HZ`),
   ``--mock-nice 10`` runs the mocks at a lower priority (the supervisor first, as on a
   computer of its own), ``--pin`` puts this process on core 0 and the mocks on core 1,
   ``--tick-hz 50`` runs the mocks' scheduler at 50 Hz (less mock CPU);
   if the run ends before the window, the ticks until then are printed; ``--record`` records
   the flight as ``vtube-fleet run`` does (a temp .rrd), ``--serve-web PORT`` also serves it
   live (``--rerun-serve-web``), and ``--live-viewer`` attaches a live viewer to that server
   before the flight: ``chromium`` a real headless Chromium showing the web viewer page
   (software WebGPU/WebGL on the CPU; with ``--pin`` on the mocks' core, as if on another
   computer), ``grpc`` the rerun CLI as a gRPC client that receives the stream and saves it
   (what a viewer reads, without drawing); the same window measures the tick with it;
4. aborts (every vehicle holds), stops the mock processes, prints the numbers (and JSON with
   ``--json``; ``load_average`` is the machine's at the end). ``--profile-out FILE``: cProfile
   of this process (ticks and telemetry receive) over the measured window only (``python -m
   pstats FILE``).

Run by hand (not in CI): it needs about 60-90 s and both cores.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from missions import grid_mission  # noqa: E402

from sim_stub.ports import free_port_scheme  # noqa: E402
from vtube_fleet.config.mission import load_mission  # noqa: E402
from vtube_fleet.fleet.budget import on_time_share  # noqa: E402
from vtube_fleet.fleet.supervisor import Supervisor  # noqa: E402
from vtube_fleet.link import fleet_sysid, open_links  # noqa: E402
from vtube_fleet.link.mavlink import (  # noqa: E402
    DEFAULT_MESSAGE_RATES_HZ,
    MSG_LOCAL_POSITION_NED,
    UNUSED_STREAMS_OFF,  # noqa: E402
)
from vtube_fleet.state import Phase  # noqa: E402


def start_mock(mission_path: Path, count: int, profile: str, processes: int, nice: int = 0,
               cpus: set[int] | None = None, tick_hz: float = 100.0
               ) -> tuple[subprocess.Popen[str], list[str]]:
    ports = free_port_scheme(count)  # never the fixed px4/wide ranges other jobs may hold

    def child_setup() -> None:  # the mock processes inherit both
        if nice:
            os.nice(nice)
        if cpus is not None:
            os.sched_setaffinity(0, cpus)

    proc = subprocess.Popen(
        [sys.executable, "-m", "vtube_fleet", "mock-fleet", str(mission_path), "--count",
         str(count), "--profile", profile, "--processes", str(processes),
         "--gcs-port", str(ports.gcs_base), "--vehicle-port", str(ports.vehicle_base),
         "--tick-hz", f"{tick_hz:g}"],
        stdout=subprocess.PIPE, stderr=sys.stderr, text=True, cwd=ROOT,
        preexec_fn=child_setup if nice or cpus is not None else None)
    assert proc.stdout is not None
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise SystemExit(f"mock fleet exited early (code {proc.poll()})")
        if line.startswith(("udpin://", "udpout://", "udp://")):
            return proc, line.strip().split(",")
    raise SystemExit("mock fleet did not print its endpoints within 120 s")


#: ``--lean-streams``: what the supervisor reads, at lower rates (message id → Hz; 0 = off):
#: LOCAL_POSITION_NED 25 Hz (> the 20 Hz control rate), GLOBAL_POSITION_INT 2 Hz (take-off
#: altitude, heading), GPS_RAW_INT 1 Hz, SYS_STATUS 2 Hz (health), EXTENDED_SYS_STATE 1 Hz
#: (landed state), ESTIMATOR_STATUS 1 Hz (the budget watch's accuracy, judged once a second),
#: HOME_POSITION 0.2 Hz (asked for once on connect anyway), BATTERY_STATUS and CURRENT_MODE
#: off: with HEARTBEAT and the TIMESYNC answers ~34 datagrams per vehicle and second
LEAN_STREAMS_HZ: dict[int, float] = {32: 25.0, 33: 2.0, 24: 1.0, 1: 2.0, 245: 1.0, 230: 1.0,
                                     242: 0.2, 147: 0.0, 436: 0.0}


def start_live_viewer(kind: str, web: object, tmp: Path, cpus: set[int] | None,
                      nice: int = 0) -> subprocess.Popen[bytes]:
    """A live viewer of the served recording (module docstring), connected before the flight;
    waits until the page has loaded (chromium) or the client has connected (grpc)."""
    from vtube_fleet.recording.live import rerun_executable

    def child_setup() -> None:
        os.setsid()  # its own process group: stopped with all its helpers
        if nice:
            os.nice(nice)
        if cpus is not None:
            os.sched_setaffinity(0, cpus)

    if kind == "grpc":
        args = [rerun_executable(), web.grpc_url, "--save", str(tmp / "client.rrd"),
                "--port", str(web.grpc_port + 2), "--bind", "127.0.0.1"]
    else:
        import shutil

        sys.path.insert(0, str(ROOT / "tests"))
        from live_view import CHROMIUM_FLAGS

        exe = shutil.which("chromium") or shutil.which("chromium-browser")
        if exe is None:
            raise SystemExit("error: --live-viewer chromium: chromium is not installed")
        args = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={tmp / 'chromium-profile'}",
                "--window-size=1600,900", web.url]
    viewer = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              env={**os.environ, "RERUN_APP_ONLY": "true"},
                              preexec_fn=child_setup)
    # connected: an established TCP connection to the server's gRPC port
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        out = subprocess.run(["ss", "-tnH", "state", "established"], capture_output=True,
                             text=True).stdout
        if f":{web.grpc_port} " in out or f":{web.grpc_port}\n" in out:
            print(f"live viewer ({kind}) connected to port {web.grpc_port}", file=sys.stderr)
            return viewer
        if viewer.poll() is not None:
            raise SystemExit(f"error: the live viewer exited ({viewer.returncode})")
        time.sleep(0.5)
    raise SystemExit("error: the live viewer did not connect within 60 s")


def stop_live_viewer(viewer: subprocess.Popen[bytes]) -> None:
    try:
        os.killpg(viewer.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        viewer.wait(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(viewer.pid, signal.SIGKILL)
        viewer.wait()


def _tree_cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its descendants (Linux /proc; 0 if gone)."""
    total, todo = 0.0, [pid]
    tick = os.sysconf("SC_CLK_TCK")
    while todo:
        p = todo.pop()
        try:
            stat = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(stat[11]) + int(stat[12])) / tick
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return total


def _machine_busy_s() -> float:
    """CPU seconds the whole machine spent busy (all cores; /proc/stat)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


async def run(args: argparse.Namespace, mission_path: Path, endpoints: list[str],
              mock_pid: int, recorder: object = None, viewer_pid: int | None = None) -> dict:
    mission = load_mission(mission_path)
    window: dict[str, float] = {}
    web = getattr(recorder, "web", None)
    server_pid = -1 if web is None or web.pid is None else web.pid
    prof = cProfile.Profile() if args.profile_out else None

    def hook(tick: int, sup: Supervisor) -> None:
        if sup.tube_start_s is None:
            return
        if "t0" not in window:
            ru = resource.getrusage(resource.RUSAGE_SELF)
            window.update(t0=time.monotonic(), cpu0=ru.ru_utime + ru.ru_stime,
                          k0=len(sup.tick_durations), mock0=_tree_cpu_s(mock_pid),
                          busy0=_machine_busy_s(), server0=_tree_cpu_s(server_pid),
                          viewer0=_tree_cpu_s(viewer_pid))
            if prof is not None:
                prof.enable()
        elif time.monotonic() - window["t0"] >= args.seconds and "t1" not in window:
            ru = resource.getrusage(resource.RUSAGE_SELF)
            window.update(t1=time.monotonic(), cpu1=ru.ru_utime + ru.ru_stime,
                          k1=len(sup.tick_durations), mock1=_tree_cpu_s(mock_pid),
                          busy1=_machine_busy_s(), server1=_tree_cpu_s(server_pid),
                          viewer1=_tree_cpu_s(viewer_pid))
            if prof is not None:
                prof.disable()
                prof.dump_stats(args.profile_out)
            sup.request_abort(f"benchmark: {args.seconds:g} s of tube flight measured")

    sysids = [fleet_sysid(i) for i in range(len(endpoints))]
    rates = dict(UNUSED_STREAMS_OFF)
    if args.lean_streams:
        rates.update(LEAN_STREAMS_HZ)
    if args.position_hz is not None:
        rates[MSG_LOCAL_POSITION_NED] = args.position_hz
    options = {"message_rates_hz": rates} if args.backend == "mavlink" else {}
    async with open_links(endpoints, args.backend, sysids=sysids, **options) as links:
        sup = Supervisor(mission, links, backend=args.backend, tick_hook=hook,
                         fence=not args.no_fence, recorder=recorder)
        result = await sup.run()
    if "t1" not in window:
        # what the control clock did until the run ended (connect .. take-off), then the end
        dur = np.asarray(sup.tick_durations)
        if dur.size:
            print(f"before the end ({dur.size} ticks, {len(endpoints)} vehicles, stage "
                  f"{sup.stage}, load {os.getloadavg()[0]:.2f}): on time "
                  f"{on_time_share(sup.tick_lateness, 1.0 / args.rate):.4f}, tick p50 "
                  f"{1000 * float(np.percentile(dur, 50)):.1f} ms, p99 "
                  f"{1000 * float(np.percentile(dur, 99)):.1f} ms, max "
                  f"{1000 * float(dur.max()):.1f} ms", file=sys.stderr)
        reason = result.reason if len(result.reason) < 600 else result.reason[:600] + " …"
        raise SystemExit(f"the tube flight did not last {args.seconds} s: {result.outcome}: "
                         f"{reason}")
    k0, k1 = int(window["k0"]), int(window["k1"])
    dur = np.asarray(sup.tick_durations[k0:k1])
    wall = window["t1"] - window["t0"]
    period = 1.0 / args.rate
    in_tube = sum(p.phase in (Phase.IN_TUBE, Phase.EXITED, Phase.HOLDING) for p in sup.pilots)
    return {
        "vehicles": len(endpoints),
        "mock_processes": args.processes,
        "mock_tick_hz": args.tick_hz,
        "mock_nice": args.mock_nice,
        "pinned": args.pin,
        "streams": "lean" if args.lean_streams else "default",
        "position_hz": rates.get(MSG_LOCAL_POSITION_NED,
                                 DEFAULT_MESSAGE_RATES_HZ[MSG_LOCAL_POSITION_NED]),
        "fence": not args.no_fence,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "recording": ("none" if not args.record else "file" if args.serve_web is None
                      else f"file + served, live viewer: {args.live_viewer or 'none'}"
                      + (f" (nice {args.live_viewer_nice})" if args.live_viewer_nice else "")),
        "recorder_dropped_ticks": getattr(recorder, "dropped_ticks", None),
        "backend": args.backend,
        "rate_hz": args.rate,
        "seconds": round(wall, 2),
        "ticks": int(dur.size),
        "expected_ticks": int(round(wall / period)),
        "achieved_rate_hz": round(dur.size / wall, 2),
        "on_time_share": round(on_time_share(sup.tick_lateness[k0:k1], period) or 0.0, 4),
        "overruns": int(np.sum(dur > period)),
        "tick_p50_ms": round(1000 * float(np.percentile(dur, 50)), 2),
        "tick_p99_ms": round(1000 * float(np.percentile(dur, 99)), 2),
        "tick_max_ms": round(1000 * float(dur.max()), 2),
        "cpu_share": round((window["cpu1"] - window["cpu0"]) / wall, 3),
        "cpu_ms_per_tick": round(1000 * (window["cpu1"] - window["cpu0"]) / max(dur.size, 1),
                                 2),
        "mock_cpu_share": round((window["mock1"] - window["mock0"]) / wall, 3),
        "machine_busy_cores": round((window["busy1"] - window["busy0"]) / wall, 3),
        "server_cpu_share": round((window["server1"] - window["server0"]) / wall, 3),
        "live_viewer_cpu_share": round((window["viewer1"] - window["viewer0"]) / wall, 3),
        "machine_cores": os.cpu_count(),
        "vehicles_airborne_at_end": int(in_tube),
        "min_pair_distance_airborne_m": result.summary.get("min_pair_distance_airborne_m"),
        "link_latency_p50_ms": (None if result.summary.get("link_latency_p50_s") is None
                                else round(1000 * result.summary["link_latency_p50_s"], 2)),
        "outcome": result.outcome,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--backend", choices=("mavlink", "mavsdk"), default="mavlink")
    ap.add_argument("--profile", choices=("full", "lite"), default="lite",
                    help="sim_stub stream set of the mock process (default lite)")
    ap.add_argument("--spacing", type=float, default=5.0, metavar="M",
                    help="slot grid spacing (default 5 m: the safety budget with px4-sih's "
                         "0.3 m estimate needs r_s' ~ 1.9 m)")
    ap.add_argument("--processes", type=int, default=None, metavar="N",
                    help="mock processes (default: one per 250 vehicles)")
    ap.add_argument("--profile-out", type=Path, default=None, metavar="FILE",
                    help="cProfile this process over the measured window into FILE")
    ap.add_argument("--no-fence", action="store_true",
                    help="skip the geofence upload before arming (a preflight step, several "
                         "round trips per vehicle; not part of the measured tick)")
    ap.add_argument("--position-hz", type=float, default=None, metavar="HZ",
                    help="LOCAL_POSITION_NED rate asked for (default: the link's, "
                         f"{DEFAULT_MESSAGE_RATES_HZ[MSG_LOCAL_POSITION_NED]:g} Hz)")
    ap.add_argument("--lean-streams", action="store_true",
                    help="ask for fewer telemetry messages (LEAN_STREAMS_HZ: ~34 instead of ~84 "
                         "per vehicle and second)")
    ap.add_argument("--mock-nice", type=int, default=0, metavar="N",
                    help="run the mock processes at this nice value (e.g. 10: the supervisor "
                         "is served first, as on its own computer; the mocks get the rest)")
    ap.add_argument("--pin", action="store_true",
                    help="run this process (the supervisor) on core 0 and the mock processes "
                         "on core 1, as if the mocks ran on a computer of their own")
    ap.add_argument("--tick-hz", type=float, default=100.0, metavar="HZ",
                    help="the mock's scheduler tick (mock-fleet --tick-hz; default 100, 50 "
                         "takes about a third less mock CPU for large fleets)")
    ap.add_argument("--record", action="store_true",
                    help="record the flight to an .rrd (as `vtube-fleet run` does)")
    ap.add_argument("--serve-web", type=int, default=None, metavar="PORT",
                    help="also serve it live (the web viewer on PORT, its data on PORT + 1)")
    ap.add_argument("--live-viewer", choices=("chromium", "grpc"), default=None,
                    help="attach a live viewer to --serve-web before the flight: a headless "
                         "Chromium on the page, or the rerun CLI as a gRPC client")
    ap.add_argument("--live-viewer-nice", type=int, default=0, metavar="N",
                    help="run the live viewer at this nice value (e.g. 10: a browser on the "
                         "flight computer that yields the CPU to the control loop)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    # SIGTERM (kill, a job scheduler) unwinds like Ctrl-C: the mock processes are stopped
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if args.processes is None:
        args.processes = max(1, math.ceil(args.count / 250))
    if not 1 <= args.processes <= args.count:
        raise SystemExit(f"error: --processes must be in 1..{args.count}, got {args.processes}")
    os.environ.setdefault("MAVLINK20", "1")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"bench_{args.count}.toml"
        # [mission] is the last table: a fixed L (the most the budget accepts) instead of the
        # measured one, so that a loaded shared machine does not end the measurement through
        # the in-flight budget watch (what is measured here is the tick, not the clearance)
        text = grid_mission(args.count, args.rate, args.seconds, args.spacing)
        # the fixture's 60 s to connect are for ~200 vehicles; a starved machine connects a
        # thousand in ~1.5-2 min (docs/fleet.md)
        connect_s = max(60.0, 0.15 * args.count)
        text = text.replace("connect_timeout_s = 60.0", f"connect_timeout_s = {connect_s:g}")
        path.write_text(text + "latency_s = 0.25\n")
        mock_cpus = None
        if args.pin:
            # as if the mocks ran on another computer: they share one core, this process
            # (the supervisor) has the other (the kernel's loopback work still lands on both)
            if (os.cpu_count() or 1) < 2:
                raise SystemExit("error: --pin needs 2 cores")
            os.sched_setaffinity(0, {0})
            mock_cpus = {1}
        proc, endpoints = start_mock(path, args.count, args.profile, args.processes,
                                     args.mock_nice, mock_cpus, args.tick_hz)
        recorder = None
        viewer = None
        try:
            if args.record or args.serve_web is not None:
                from vtube_fleet.recording import open_recorder

                recorder = open_recorder(Path(tmp) / "recording.rrd", kind="fleet",
                                         serve_web=args.serve_web)
            if args.live_viewer is not None:
                if recorder is None or getattr(recorder, "web", None) is None:
                    raise SystemExit("error: --live-viewer needs --serve-web PORT")
                viewer = start_live_viewer(args.live_viewer, recorder.web, Path(tmp),
                                           mock_cpus, args.live_viewer_nice)
            out = asyncio.run(run(args, path, endpoints, proc.pid, recorder,
                                  -1 if viewer is None else viewer.pid))
        finally:
            if recorder is not None:
                recorder.close()
            if viewer is not None:
                stop_live_viewer(viewer)
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for k, v in out.items():
            print(f"{k:30s} {v}")


if __name__ == "__main__":
    main()
