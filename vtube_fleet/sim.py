"""Offline simulator: the paper's numerical simulation (Section V-A).

Each step (all robots still in the tube at once):

1. robots satisfying (TraCondition) for the MAIN tube, −n_cᵀ(p_i − p_r1) ≤ ε_0, exit
   (Assumption 2): they are removed, recorded as NaN from then on, and are nobody's neighbours;
2. every robot's sub-tube k_i is located (switching rule (ObstacleController),
   :meth:`Partition.locate`, through a :class:`~vtube_fleet.core.partition.SubTubeTracker`, which
   gives the same result but re-runs the full locate only when a robot may have changed
   sub-tube); for ``controller="apf"`` there is no partition and every robot
   uses the main tube (Appendix C);
3. neighbour candidates come from a Verlet list (:class:`~vtube_fleet.core.neighbours.VerletPairs`);
4. the velocity commands v_c come from :func:`~vtube_fleet.core.controller.velocity_command`
   (through its per-loop form :class:`~vtube_fleet.core.controller.CommandEvaluator`, told how
   far a point can move per step so that it skips the barrier elements that are exactly 0)
   ("new" = (ModifiedVectorField), "old" = (Oldcontroller), "apf" = Appendix C);
5. the robots move one step of their model (:mod:`vtube_fleet.core.models`): the single
   integrator (Single), or the unicycle driven through (NID), whose controller is evaluated at
   the control point p + s[cos θ, sin θ] (paper note 10). The integrator
   (:mod:`vtube_fleet.core.integrate`) is ``"adaptive"`` by default: forward Euler while every
   barrier margin exceeds what one step can consume, else Euler sub-steps halved until no
   margin loses more than half of what is left; ``"rk4"`` (single integrator only) and
   ``"euler"`` on request.

A route of several segments (docs/route.md) is flown the same way with a
:class:`~vtube_fleet.core.route.RouteTracker` for step 2 (each robot in its segment's
partition, the hand-over to the next segment tested whenever some robot may have come within
reach of it, the metric chunk flushed at every hand-over), exits at the last segment's
finishing line, and the leg distances of the metrics and of the adaptive step's margins taken
to each robot's own segment.

The scenario must be certified (:func:`~vtube_fleet.core.validation.validate_route`: every
condition of the paper holds, and for a route every junction condition).
``uncertified=True`` flies a single tube that is not, with the triangles circumscribed about O
instead of O' as the authors' published code does; the summary then says ``certified: false``
and lists the failed conditions.

The trajectory holds every ``record_every``-th step and always the final state (at t_end, after
the last step): every robot still present then, the ones that meet (TraCondition) at that
instant included (they exit at t_end; a robot that exited earlier is NaN from its exit step on).
``exit_pos`` holds where each robot met (TraCondition).

Safety metrics (:mod:`vtube_fleet.core.metrics`) are taken at every step, in chunks: positions and
commands are kept in a buffer and evaluated in one vectorized call per chunk (a chunk ends when
the neighbour list is rebuilt, a robot exits, or the buffer is full). For the single integrator
the buffer holds the state itself (the controller and the Euler step write their rows), so the
metrics cost no copy per step. For the unicycle the control points are the primary stream (the
controller's guarantee) and the robot centres a second stream (``*_center`` keys).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np

from vtube_fleet.config.scenario import MAX_SIM_STEPS, Scenario
from vtube_fleet.core import models
from vtube_fleet.core.controller import CommandEvaluator, TubeArrays, reuse_heap
from vtube_fleet.core.integrate import (
    INTEGRATORS,
    AdaptiveStats,
    MarginGuard,
    adaptive_state_step,
    adaptive_step,
    rk4_step,
)
from vtube_fleet.core.metrics import (
    METRIC_KEYS,
    SafetyLimits,
    SafetyMonitor,
    StepMetrics,
    SummaryAccumulator,
)
from vtube_fleet.core.neighbours import VerletPairs
from vtube_fleet.core.partition import Partition, PartitionError, SubTubeTracker
from vtube_fleet.core.route import Route, RouteTracker
from vtube_fleet.core.validation import ScenarioError, validate_route
from vtube_fleet.errors import UserError

__all__ = [
    "CONTROLLERS",
    "ProgressBar",
    "SimError",
    "SimResult",
    "default_record_every",
    "simulate",
]

#: Controller laws: (ModifiedVectorField), (Oldcontroller), Appendix C's potential term.
CONTROLLERS: tuple[str, ...] = ("new", "old", "apf")

#: Default recording rate: one frame per RECORD_PERIOD_S of simulated time at most ...
RECORD_PERIOD_S = 0.01
#: ... and the recorded arrays stay below this many bytes.
RECORD_BUDGET_BYTES = 40_000_000

#: Per-step metric series go to the recorder in blocks of at least this many steps.
REC_METRIC_BLOCK = 2048

ProgressFn = Callable[[float, float, int, int], None]


class SimError(UserError):
    """A simulation request that cannot run (bad dt, duration, robot count or controller)."""


@dataclass(frozen=True, eq=False)
class SimResult:
    """What :func:`simulate` returns.

    Recorded every ``record_every`` steps (frame 0 = initial state, config order):
    ``t`` (T,), ``pos`` and ``vel`` (T, M, 2) in the tube frame, NaN after a robot exits
    (robot centres and their velocities; for the unicycle also ``control_pos``/``control_vel``
    (T, M, 2) and ``heading`` (T, M)). ``exit_time_s`` (M,) is NaN for robots still in the
    tube; ``exit_pos`` (M, 2) where it met (TraCondition) (its control point for the unicycle),
    NaN if it did not. The last frame is the final state (module docstring). Every step:
    ``step_t`` (S,) and ``metrics`` (S,) (control points for the unicycle), ``metrics_center``
    for unicycle centres (the final state has none: no command is evaluated there).
    ``summary`` is the ``summary.json`` dict.
    """

    scenario: Scenario
    controller: str
    dt: float
    record_every: int
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    exit_time_s: np.ndarray
    step_t: np.ndarray
    metrics: StepMetrics
    summary: dict[str, Any]
    partition: Partition | None
    metrics_center: StepMetrics | None = None
    control_pos: np.ndarray | None = None
    control_vel: np.ndarray | None = None
    heading: np.ndarray | None = None
    interrupted: bool = False
    exit_pos: np.ndarray | None = None
    #: the planned route of a route of several segments (``partition`` is then None)
    route: Route | None = None

    def trajectory_arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``trajectory.npz``."""
        out = {"t": self.t, "pos": self.pos, "vel": self.vel, "exit_time_s": self.exit_time_s}
        for name in ("exit_pos", "control_pos", "control_vel", "heading"):
            val = getattr(self, name)
            if val is not None:
                out[name] = val
        return out


def default_record_every(dt: float, steps: int, robots: int, floats_per_robot: int = 4) -> int:
    """Decimation so that frames are ≥ RECORD_PERIOD_S apart and the arrays stay in budget."""
    by_rate = max(1, round(RECORD_PERIOD_S / dt))
    frame_bytes = 8 * floats_per_robot * max(robots, 1)
    by_size = math.ceil((steps + 1) * frame_bytes / RECORD_BUDGET_BYTES)
    return max(by_rate, by_size, 1)


class ProgressBar:
    """A dependency-free progress bar on a stream (stderr by default).

    On a terminal it redraws one line at most every ``interval_s`` of wall time; otherwise it
    stays silent until :meth:`close`, which prints one final line either way.
    """

    def __init__(self, stream: TextIO | None = None, interval_s: float = 0.1,
                 width: int = 28) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = interval_s
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._start = time.perf_counter()
        self._last = -math.inf
        self._state = (0.0, 0.0, 0, 0)
        self.used = False

    def _line(self) -> str:
        t, total, in_tube, exited = self._state
        frac = min(1.0, t / total) if total > 0 else 1.0
        fill = int(round(frac * self.width))
        wall = time.perf_counter() - self._start
        return (f"[{'#' * fill}{'.' * (self.width - fill)}] t = {t:6.2f}/{total:.2f} s  "
                f"exited {exited}/{in_tube + exited}  wall {wall:5.1f} s")

    def __call__(self, t: float, total: float, in_tube: int, exited: int) -> None:
        self._state = (t, total, in_tube, exited)
        self.used = True
        if not self.tty:
            return
        now = time.perf_counter()
        if now - self._last >= self.interval_s:
            self._last = now
            self.stream.write("\r" + self._line())
            self.stream.flush()

    def close(self, message: str | None = None) -> None:
        """Print the final line (nothing if the bar was never updated)."""
        if not self.used:
            return
        line = self._line() + (f"  {message}" if message else "")
        self.stream.write(("\r" if self.tty else "") + line + "\n")
        self.stream.flush()


# ----------------------------------------------------------------------------------------
# the simulation
# ----------------------------------------------------------------------------------------


def simulate(
    scenario: Scenario,
    *,
    controller: str = "new",
    dt: float | None = None,
    duration: float | None = None,
    robots: int | None = None,
    record_every: int | None = None,
    progress: ProgressFn | None = None,
    skin: float | None = None,
    validate: bool = True,
    recorder: Any = None,
    integrator: str | None = None,
    uncertified: bool = False,
) -> SimResult:
    """Run the scenario (see the module docstring).

    ``dt``/``duration``/``record_every`` override the scenario's [sim] values, ``robots`` keeps
    the first N robots. ``progress(t, duration, in_tube, exited)`` is called about every 0.1 s
    of simulated time. The scenario is validated first (:func:`check_scenario`, raising
    :class:`~vtube_fleet.core.validation.ScenarioError`) unless ``validate=False``. ``skin`` is the
    Verlet-list margin in metres (default (r_s + r_a)/2). Ctrl-C stops the run early:
    the result (``interrupted=True``) holds everything up to that step. ``recorder`` (a
    :class:`vtube_fleet.recording.api.Recorder`) gets the scene, every recorded frame, every step's
    metrics, the exits and the summary; the caller closes it. ``integrator`` overrides
    [sim].integrator. ``uncertified=True``: a scenario that fails validation is flown anyway,
    its triangles about O (module docstring); ``certified`` and ``failed_conditions`` in the
    summary and the recording's meta say so.
    """
    if controller not in CONTROLLERS:
        raise SimError(f"unknown controller {controller!r} (choose from {', '.join(CONTROLLERS)})")
    if controller == "apf" and not scenario.obstacles:
        raise SimError("controller 'apf' needs obstacles (its term u5 repels from them)")
    if robots is not None:
        scenario = scenario.with_robots(robots)
    integrator = scenario.sim.integrator if integrator is None else integrator
    if integrator not in INTEGRATORS:
        raise SimError(f"unknown integrator {integrator!r} (choose from {', '.join(INTEGRATORS)})")
    if integrator == "rk4" and scenario.robots.model == "unicycle":
        raise SimError("integrator 'rk4' is implemented for the single integrator only "
                       "(use adaptive or euler for unicycles)")
    dt = scenario.sim.dt if dt is None else float(dt)
    duration = scenario.sim.duration if duration is None else float(duration)
    if not (math.isfinite(dt) and dt > 0):
        raise SimError(f"dt must be > 0, got {dt}")
    if not (math.isfinite(duration) and duration > 0):
        raise SimError(f"duration must be > 0, got {duration}")
    n_steps = int(math.ceil(duration / dt - 1e-9))
    if n_steps > MAX_SIM_STEPS:  # as the scenario file's [sim] check, for --dt/--duration too
        raise SimError(f"duration / dt must be <= {MAX_SIM_STEPS:.0e} steps, got "
                       f"{duration:g} s / {dt:g} s = {n_steps:.3g} steps".replace("e+0", "e"))
    rcfg = scenario.robots
    params = scenario.controller
    unicycle = rcfg.model == "unicycle"
    m = rcfg.count
    if record_every is None:
        record_every = scenario.sim.record_every
    if record_every is None:
        record_every = default_record_every(dt, n_steps, m, 7 if unicycle else 4)
    if not isinstance(record_every, int) or record_every < 1:
        raise SimError(f"record_every must be >= 1, got {record_every}")

    control0 = rcfg.control_points()
    if not scenario.geometry.is_single:
        return _simulate_route(scenario, controller, dt, n_steps, record_every, progress, skin,
                               validate, recorder, integrator, uncertified, control0)
    part: Partition | None = None
    certified: bool | None = None  # None: not validated
    failed: list[dict[str, str]] = []
    about = "O'"
    corridor = scenario.corridor  # one segment: its tube and obstacles
    if validate:
        res = validate_route(corridor, params, control0)
        part = None if res.route is None else res.route.segments[0].partition
        violations = list(res.violations)
        certified = not violations
        if violations and not uncertified:
            raise ScenarioError(violations)
        if violations:
            failed = [{"condition": v.condition, "message": v.message} for v in violations]
            part, about = _uncertified_partition(scenario, params), "O"
            failed += _uncertified_conditions(scenario, part)
    if controller == "apf":
        arrays = TubeArrays.from_tubes([corridor.tube])
        tracker = None
    else:
        if part is None:
            part = Route.plan(corridor, params).segments[0].partition
        arrays = TubeArrays.from_tubes(part.sub_tubes)
        tracker = part.tracker()

    info = {"integrator": integrator, "certified": certified, "failed_conditions": failed,
            "triangles_about": about}
    if recorder is not None:
        recorder.log_scene(scenario, part if controller != "apf" else None, meta={
            "dt_s": dt, "controller": controller, "record_every": record_every, **info})
    run = _Run(scenario, controller, dt, n_steps, record_every, arrays, tracker, progress, skin,
               recorder, integrator)
    run.execute()
    result = run.result(part, info)
    if recorder is not None:
        recorder.log_summary(result.summary)
    return result


def _simulate_route(scenario: Scenario, controller: str, dt: float, n_steps: int,
                    record_every: int, progress: ProgressFn | None, skin: float | None,
                    validate: bool, recorder: Any, integrator: str, uncertified: bool,
                    control0: np.ndarray) -> SimResult:
    """:func:`simulate` of a route of several segments (docs/route.md): the paper's controller
    in each robot's segment, the hand-over at the junctions (:class:`~vtube_fleet.core.route.
    RouteTracker`), exits at the last finishing line, the leg distances judged to each robot's
    segment."""
    corridor = scenario.corridor
    params = scenario.controller
    if controller == "apf":
        raise SimError(f"controller 'apf' (Appendix C's potential on the main tube) flies one "
                       f"tube; this route has {corridor.S} segments")
    certified: bool | None = None
    route: Route | None = None
    if validate:
        res = validate_route(corridor, params, control0)
        certified = res.ok
        if not res.ok:
            if uncertified:
                raise SimError("--uncertified flies one tube as the authors' code builds it; "
                               "a route must pass its conditions (vtube-fleet check)")
            raise ScenarioError(res.violations)
        route = res.route
    if route is None:
        route = Route.plan(corridor, params)
    info = {"integrator": integrator, "certified": certified, "failed_conditions": [],
            "triangles_about": "O'"}
    if recorder is not None:
        recorder.log_scene(scenario, route, meta={
            "dt_s": dt, "controller": controller, "record_every": record_every, **info})
    run = _Run(scenario, controller, dt, n_steps, record_every, route.arrays,
               route.tracker(control0), progress, skin, recorder, integrator, route=route)
    run.execute()
    result = run.result(None, info)
    if recorder is not None:
        recorder.log_summary(result.summary)
    return result


def _uncertified_conditions(scenario: Scenario, part: Partition) -> list[dict[str, str]]:
    """What the uncertified partition itself breaks: its warnings (e.g. Assumption 3' in a kept
    side tube) and, for every triangle, that it is circumscribed about O, not O'."""
    out = [{"condition": w.condition, "message": f"flown partition (triangles about O): {w}"}
           for w in part.warnings]
    r_s = scenario.controller.r_s
    for tri in part.triangles:
        ob = scenario.obstacles[tri.obstacle]
        out.append({"condition": "ExtObstacle", "message": (
            f"obstacle #{tri.obstacle + 1}: triangle circumscribed about O (r_o = {ob.radius:g}"
            f" m), not O' (r_o + r_s = {ob.radius + r_s:g} m): O' pokes {r_s:g} m out of it, so "
            f"a robot centre outside the triangle (e.g. just past its base) may come within r_o "
            f"of the obstacle centre (S_i ∩ O = ∅ is no longer guaranteed)")})
    return out


def _uncertified_partition(scenario: Scenario, params: Any) -> Partition:
    """The partition of a scenario that failed validation, built as the authors' published
    code does: triangles circumscribed about O (radius r_o), not O' (docs/config.md), with the
    non-strict checks (failures become warnings). Raises :class:`SimError` when even that
    cannot be built."""
    from vtube_fleet.core.partition import partition as build_partition

    auto = [i + 1 for i, ob in enumerate(scenario.obstacles) if isinstance(ob.apex_distance, str)]
    if auto:
        raise SimError("--uncertified builds the triangles with the given apex distances; "
                       f"obstacle(s) {', '.join(f'#{i}' for i in auto)} have "
                       "apex_distance = \"auto\"")
    try:
        return build_partition(scenario.tube, scenario.obstacles, params, strict=False,
                               triangles_about="O")
    except PartitionError as e:
        raise SimError(f"--uncertified: no partition even with the triangles about O: {e}"
                       ) from None


def _cz(q: np.ndarray) -> np.ndarray:
    """(n, 2) float → (n,) complex view (a copy if ``q`` is not C-contiguous)."""
    return np.ascontiguousarray(q).view(np.complex128)[:, 0]


class _Run:
    """State of one simulation; the hot loop lives in :meth:`execute`."""

    def __init__(self, scenario: Scenario, controller: str, dt: float, n_steps: int,
                 record_every: int, arrays: TubeArrays,
                 tracker: SubTubeTracker | RouteTracker | None,
                 progress: ProgressFn | None, skin: float | None, recorder: Any = None,
                 integrator: str = "euler", route: Route | None = None) -> None:
        self.scenario = scenario
        self.route = route
        self.integrator = integrator
        self.istats = AdaptiveStats()
        self.recorder = recorder
        self.controller = controller
        self.dt = dt
        self.n_steps = n_steps
        self.record_every = record_every
        self.arrays = arrays
        self.tracker = tracker
        self.progress = progress
        p = scenario.controller
        self.params = p
        # Verlet skin: rebuild the KD-tree about every skin / (2 v_max dt) steps
        self.skin = float(skin) if skin is not None else 0.5 * (p.r_a + p.r_s)
        r = scenario.robots
        self.unicycle = r.model == "unicycle"
        self.m = r.count
        self.monitor = SafetyMonitor.for_corridor(scenario.corridor, p)
        self.acc = SummaryAccumulator(self.m)
        # where each robot met (TraCondition): the robot, or a unicycle's control point
        self.exit_pos = np.full((self.m, 2), np.nan)
        self.parts: list[StepMetrics] = []
        self.parts_center: list[StepMetrics] = []
        self.step_t_parts: list[np.ndarray] = []
        self.steps_done = 0
        self.t_end = 0.0
        self.wall_s = 0.0
        self.interrupted = False

    # ----- recording ------------------------------------------------------------------------
    def _alloc_records(self) -> None:
        frames = self.n_steps // self.record_every + 2  # + the final state
        m = self.m
        self.rec_t = np.full(frames, np.nan)
        self.rec_pos = np.full((frames, m, 2), np.nan)
        self.rec_vel = np.full((frames, m, 2), np.nan)
        if self.unicycle:
            self.rec_cpos = np.full((frames, m, 2), np.nan)
            self.rec_cvel = np.full((frames, m, 2), np.nan)
            self.rec_head = np.full((frames, m), np.nan)
        self.frames = 0

    def execute(self) -> None:
        sc = self.scenario
        dt = self.dt
        p = self.params
        route = self.route
        # a route of several segments: the hand-overs (RouteTracker), exits from the last
        # segment only, each robot's legs for the metrics and the integrator's margins
        route_tr: Any = self.tracker if route is not None else None  # (a RouteTracker)
        tube = sc.tube if route is None else route.segments[-1].tube
        n_c = np.array(tube.n_c)
        thresh = tube.finish_threshold(p.eps_0)  # (TraCondition): n_cᵀp ≥ this
        # An upper bound of how far any evaluation point moves per second: ‖v_c‖ ≤ v_max under
        # Constraint1 (all three laws saturate), and a unicycle's control point moves by at most
        # √2‖v_c‖dt per Euler step (v_lin and s·ω are the two components of v_c in the body
        # frame). The exit test and the Verlet-list check are skipped while no point can have
        # reached the finishing line / moved skin/2 since the list was built.
        v_bound = (1.5 if self.unicycle else 1.0 + 1e-6) * max(p.v_max, p.v + p.v_max_prime)
        integ = self.integrator
        # RK4's intermediate points and the adaptive sub-steps lie within one step's move of
        # the step's start: keep the neighbour list valid for them too
        half_skin = 0.5 * self.skin - (0.0 if integ == "euler" else v_bound * dt)
        if half_skin <= 0:
            half_skin = 0.5 * self.skin
        verlet_safe = max(1, int(half_skin / (v_bound * dt)))
        kind = self.controller
        obstacles = sc.obstacles if kind == "apf" else ()
        arrays, params = self.arrays, p
        tracker = self.tracker
        max_move = v_bound * dt
        dt_z = np.array(dt, dtype=np.complex128)  # the Euler step's factor, converted once
        # the tracker's bound between calls: RK4's last evaluation (at z + h k3) is up to two
        # steps' move away from the next step's start
        track_move = 2.0 * max_move if integ == "rk4" else max_move
        adaptive = integ == "adaptive"
        rk4 = integ == "rk4"
        guard = MarginGuard(tube, sc.obstacles, SafetyLimits.from_params(p))
        base_guard = guard
        cur_seg: np.ndarray | None = None  # the segments of the buffered steps (a route)
        last_seg = 0 if route is None else route.S - 1
        if route_tr is not None:
            cur_seg = route_tr.segment
            guard = base_guard.with_legs(*route.leg_table(cur_seg))
        thr_single = guard.single_threshold(max_move)
        thr_pair = guard.pair_threshold(max_move) + guard.limits.pair_m  # on the pair distance
        next_single = 0
        near_single = False
        istats = self.istats
        verlet = VerletPairs(p.r_s + p.r_a, self.skin)
        monitor, acc = self.monitor, self.acc
        unicycle = self.unicycle
        s_nid = sc.robots.nid_distance
        centre_pairs_ok = unicycle and 2.0 * s_nid <= p.r_a - p.r_s

        # state of the robots still in the tube (compacted; ids = config indices)
        pos = np.array(sc.robots.positions, dtype=float)  # centres
        theta = np.array(sc.robots.headings, dtype=float) if unicycle else None
        ids = np.arange(self.m)
        kzero = np.zeros(0, dtype=np.intp)  # apf: everyone in the main tube (read-only)
        # the controller computes every candidate pair's distance anyway: it keeps their
        # minimum for the metrics (the same number SafetyMonitor would compute from the list)
        command = CommandEvaluator(arrays, params, kind, obstacles, track_min_pair=True)

        # metric chunks: rows 0 … nc−1 of the buffers hold the steps taken since the last
        # flush (evaluation points and commands). For the single integrator the state lives
        # in the buffer: row nc holds the current positions, the Euler step writes row nc + 1
        # and the commands are written to their row directly (no copies).
        chunk = int(max(4, min(256, 400_000 // max(self.m, 1))))
        cpos = np.empty((chunk + 1, self.m, 2))
        cvel = np.empty((chunk + 1, self.m, 2))
        cpm = np.empty(chunk + 1)  # minimum pair distance over the neighbour list
        if unicycle:
            ccen = np.empty((chunk + 1, self.m, 2))
            ccvel = np.empty((chunk + 1, self.m, 2))
        # a flush makes a few (chunk, m) complex temporaries: keep such blocks on the heap
        # (else each one is mapped and page-faulted anew: 0.57 instead of 0.21 ms per flush of
        # 256 steps × 120 robots here)
        reuse_heap(8 * cpos.nbytes)
        nc = 0
        cur_I = None
        cur_pairs: tuple[np.ndarray, np.ndarray] | None = None

        def flush(n: int, step: int) -> None:
            """Metrics of the nc buffered steps (the last before ``step``), n robots."""
            nonlocal nc
            if nc == 0:
                return
            tt = (step - nc + np.arange(nc)) * dt  # == (step − nc + i)·dt of the loop
            met = monitor.evaluate(cpos[:nc, :n], cvel[:nc, :n], pairs=cur_pairs,
                                   all_present=True, min_pair=cpm[:nc], segment=cur_seg)
            acc.add(tt, met)
            self.parts.append(met)
            self.step_t_parts.append(tt)
            if unicycle:
                # centre pairs closer than r_s + r_a − 2s are control-point pairs closer than
                # r_s + r_a, hence in the list; otherwise search them step by step
                metc = monitor.evaluate(ccen[:nc, :n], ccvel[:nc, :n],
                                        pairs=cur_pairs if centre_pairs_ok else None,
                                        all_present=True, segment=cur_seg)
                acc.add(tt, metc, suffix="_center")
                self.parts_center.append(metc)
            if rec is not None:  # handed to the recorder in blocks of >= REC_METRIC_BLOCK steps
                series = {key: getattr(met, key) for key in METRIC_KEYS}
                if unicycle:
                    series.update({f"{key}_center": getattr(metc, key) for key in METRIC_KEYS})
                rec_metrics.append((tt, step - nc + np.arange(nc), series))
                if sum(len(b[0]) for b in rec_metrics) >= REC_METRIC_BLOCK:
                    send_metrics()
            nc = 0

        rec_metrics: list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]] = []

        def send_metrics() -> None:
            """Hand the buffered metric series to the recorder, grouped by frame (the final
            state, a frame of its own, has no metrics: no command is evaluated there)."""
            if not rec_metrics:
                return
            blocks = rec_metrics[:]
            rec_metrics.clear()
            tt = np.concatenate([b[0] for b in blocks])
            kk = np.concatenate([b[1] for b in blocks])
            ser = {key: np.concatenate([b[2][key] for b in blocks]) for key in blocks[0][2]}
            rec.log_metrics(tt, kk, ser, every=rec_every)

        self._alloc_records()
        rec = self.recorder
        rec_every = self.record_every
        next_rec = 0
        next_exit_check = 0
        next_verlet = 0
        builds = -1
        pairs = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        next_progress = 0
        progress_every = max(1, int(round(0.1 / dt)))
        progress = self.progress
        n_steps = self.n_steps
        n = pos.shape[0]
        # single integrator: the rows of the first n robots, as (n, 2) floats (P2) and as
        # complex x + iy (Z2: positions, V2: commands), the form the controller works in
        P2, Z2, V2 = cpos[:, :n], cpos.view(np.complex128)[:, :n, 0], cvel.view(
            np.complex128)[:, :n, 0]
        if not unicycle:
            P2[0] = pos
            pos = P2[0]  # the state: row nc of the buffer
        # the rows as lists of views (a list item costs less than indexing an array per step)
        PR, ZR, VR = list(P2), list(Z2), list(V2)
        last_rec = -1

        def last_command(buf: np.ndarray) -> np.ndarray:
            """The rows of the last step taken (nc − 1) of a command buffer: the velocities
            that brought the robots to the current state."""
            return buf[nc - 1, :n].copy() if nc else np.full((n, 2), np.nan)

        def record_frame(st: int, ids_: np.ndarray, pos_: np.ndarray, vel_: np.ndarray,
                         q_: np.ndarray | None = None, vc_: np.ndarray | None = None,
                         th_: np.ndarray | None = None) -> None:
            """Frame of step ``st``: centres and their velocities (the commands for the single
            integrator; for unicycles also control points, their commands and headings)."""
            nonlocal last_rec
            t = st * dt
            f = self.frames
            self.rec_t[f] = t
            self.rec_pos[f, ids_] = pos_
            self.rec_vel[f, ids_] = vel_
            if unicycle:
                self.rec_cpos[f, ids_] = q_
                self.rec_cvel[f, ids_] = vc_
                self.rec_head[f, ids_] = th_
            self.frames = f + 1
            last_rec = st
            if rec is not None and unicycle:
                rec.log_tick(t_s=t, tick=st, ids=ids_, pos=pos_, vel=vel_,
                             safety={"": (q_, vc_), "_center": (pos_, vel_)})
            elif rec is not None:
                rec.log_tick(t_s=t, tick=st, ids=ids_, pos=pos_, vel=vel_)

        # the tracker between the steps' own locates (integrator sub-steps, the quiet loop
        # below): a route hands over only at a step's start (the outer loop)
        sub_update: Any = None
        if route_tr is not None:
            def sub_update(pp: np.ndarray, mv: float) -> np.ndarray:
                return route_tr.update(pp, mv, False)
        elif tracker is not None:
            sub_update = tracker.update

        def rhs_of(k0: np.ndarray, prs: tuple) -> Callable[[np.ndarray, float], np.ndarray]:
            """The command at sub-step points z (complex) of the single integrator."""
            def rhs(z: np.ndarray, move: float) -> np.ndarray:
                kk = k0 if tracker is None else sub_update(
                    z.view(np.float64).reshape(-1, 2), move)
                return command.step(z, kk, prs, move=move)
            return rhs

        def uni_move(state: tuple, vcmd: np.ndarray, hs: float) -> tuple[tuple, np.ndarray]:
            """One Euler sub-step of the unicycles under the control-point command (NID)."""
            pp, th = state
            vl, om = models.nid_inputs(th, vcmd, s_nid)
            p1, th1 = models.unicycle_step(pp, th, vl, om, hs)
            return (p1, th1), _cz(models.nid_control_point(p1, th1, s_nid))

        def uni_rhs(k0: np.ndarray, prs: tuple) -> Callable:
            def rhs(state: tuple, z: np.ndarray, move: float) -> np.ndarray:
                qq = np.ascontiguousarray(z.view(np.float64).reshape(-1, 2))
                kk = k0 if tracker is None else sub_update(qq, move)
                return command(qq, kk, prs)
            return rhs

        quiet = not unicycle and not rk4  # (the loop's short form, below)
        cstep, mul, add = command.step, np.multiply, np.add
        start = time.perf_counter()
        step = 0
        try:
            while step < n_steps:
                q = models.nid_control_point(pos, theta, s_nid) if unicycle else pos
                # 1. exits (TraCondition), main tube only (Assumption 2)
                if step >= next_exit_check:
                    xi = q @ n_c
                    xmax = xi.max()
                    gone = None
                    if xmax >= thresh:
                        gone = xi >= thresh
                        if route_tr is not None:  # only from the last segment
                            gone &= route_tr.segment == last_seg
                            if not gone.any():
                                gone = None
                    if gone is not None:
                        if gone.all():  # the run ends here: the final state is a frame
                            if unicycle:
                                record_frame(step, ids, pos, last_command(ccvel), q,
                                             last_command(cvel), theta)
                            else:
                                record_frame(step, ids, q, last_command(cvel))
                        flush(n, step)
                        t = step * dt
                        acc.add_exits(t, ids[gone])
                        self.exit_pos[ids[gone]] = q[gone]
                        if rec is not None:
                            rec.log_exits(t, step, ids[gone])
                        keep = ~gone
                        ids = ids[keep]
                        q = q[keep]
                        n = q.shape[0]
                        P2, Z2, V2 = P2[:, :n], Z2[:, :n], V2[:, :n]
                        PR, ZR, VR = list(P2), list(Z2), list(V2)
                        if unicycle:
                            pos = pos[keep]
                            theta = theta[keep]
                        else:
                            P2[0] = q
                            q = pos = PR[0]
                        if n == 0:
                            break
                        if route_tr is not None:
                            route_tr.keep(keep)
                            cur_seg = route_tr.segment
                            guard = base_guard.with_legs(*route.leg_table(cur_seg))
                            next_single = step
                        xmax = xi[keep].max()
                        next_verlet = step  # the robot set changed: rebuild the list now
                    next_exit_check = step + max(1, int((thresh - xmax) / (v_bound * dt)))
                # 2-4. sub-tube, neighbours, command
                if tracker is not None:
                    k = tracker.update(q, track_move)
                    if route_tr is not None and route_tr.handed:
                        # a hand-over: the buffered steps are judged in the old segments
                        route_tr.handed = False
                        if nc:
                            flush(n, step)
                            if not unicycle:  # the current positions move to row 0
                                P2[0] = pos
                                q = pos = PR[0]
                        cur_seg = route_tr.segment
                        guard = base_guard.with_legs(*route.leg_table(cur_seg))
                        next_single = step
                else:
                    if kzero.shape[0] != n:
                        kzero = np.zeros(n, dtype=np.intp)
                        kzero.setflags(write=False)
                    k = kzero
                if step >= next_verlet:
                    pairs = verlet.candidates(q)
                    if verlet.builds != builds:
                        builds = verlet.builds
                        next_verlet = step + verlet_safe
                    else:  # still valid: ask again when the farthest mover may reach skin/2
                        dmax = verlet.last_move  # (the largest move since the build)
                        next_verlet = step + max(1, int((half_skin - dmax) / (v_bound * dt)))
                # metrics buffer: one robot set per chunk (exits flush above); for unicycles
                # also one pair list (the centre metrics search it), while the single
                # integrator's pair minima come with the buffer (cpm), whatever the list
                if nc == chunk or (unicycle and pairs[0] is not cur_I):
                    if nc:
                        flush(n, step)
                        if not unicycle:  # the current positions move to row 0
                            P2[0] = pos
                            q = pos = PR[0]
                    cur_I, cur_pairs = pairs[0], pairs
                if not unicycle:
                    zc = ZR[nc]
                    vz = command.step(zc, k, pairs, out=VR[nc], move=track_move)
                else:
                    vc = command(q, k, pairs, out=cvel[nc, :n])
                    v_lin, omega = models.nid_inputs(theta, vc, s_nid)
                    heading = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
                    vcen = heading * v_lin[:, None]
                    cpos[nc, :n] = q
                    ccen[nc, :n] = pos
                    ccvel[nc, :n] = vcen
                cpm[nc] = min_pair = command.min_pair_distance
                # recording (decimated; the final state after the loop)
                if step == next_rec:
                    if unicycle:
                        vc = cvel[nc, :n]
                        record_frame(step, ids, pos, vcen, q, vc, theta)
                    else:
                        record_frame(step, ids, pos, cvel[nc, :n])
                    next_rec += rec_every
                # 5. one step of the model (core/integrate.py); "adaptive" is Euler unless a
                # margin is within what one step can consume (then the guarded sub-steps)
                guarded = False
                if adaptive:
                    if step >= next_single:
                        ms = guard.single_margin(_cz(q) if unicycle else ZR[nc])
                        near_single = ms < thr_single
                        next_single = step + (1 if near_single else
                                              max(1, int((ms - thr_single) / max_move)))
                    guarded = near_single or min_pair < thr_pair
                if unicycle:
                    if guarded:
                        (pos, theta), _ = adaptive_state_step(
                            (pos, theta), _cz(q), vc, dt, uni_move, uni_rhs(k, pairs), guard,
                            pairs, istats)
                    else:
                        pos, theta = models.unicycle_step(pos, theta, v_lin, omega, dt)
                elif guarded:
                    adaptive_step(ZR[nc], vz, dt, rhs_of(k, pairs), guard, pairs, istats,
                                  out=ZR[nc + 1])
                    pos = PR[nc + 1]
                elif rk4:
                    rk4_step(ZR[nc], vz, dt, rhs_of(k, pairs), out=ZR[nc + 1])
                    pos = PR[nc + 1]
                else:  # (Single) p + dt v_c, on x + iy (models._single_step, inlined)
                    zn = ZR[nc + 1]
                    np.multiply(vz, dt_z, zn)  # (dt as complex: what numpy casts it to)
                    np.add(zc, zn, zn)
                    pos = PR[nc + 1]
                nc, step = nc + 1, step + 1  # the step is done (and in the buffer)
                if step >= next_progress and progress is not None:
                    progress(step * dt, n_steps * dt, n, self.m - n)
                    next_progress = step + progress_every
                if not quiet:
                    continue
                # the steps before the next event (exit check, neighbour list, metric chunk,
                # frame, last step, leg/obstacle margin check, progress): the same steps as
                # above with nothing else to do (single integrator, euler or adaptive)
                end = min(next_exit_check, next_verlet, step + chunk - nc, next_rec,
                          n_steps, next_single if adaptive else n_steps,
                          n_steps if progress is None else next_progress)
                if route_tr is not None:  # no hand-over can be due before this
                    end = min(end, step + route_tr.quiet_calls(track_move))
                while step < end:
                    if tracker is not None:
                        k = sub_update(pos, track_move)
                    zc = ZR[nc]
                    vz = cstep(zc, k, pairs, VR[nc], track_move)
                    cpm[nc] = min_pair = command.min_pair_distance
                    nc += 1
                    if adaptive and (near_single or min_pair < thr_pair):
                        adaptive_step(zc, vz, dt, rhs_of(k, pairs), guard, pairs, istats,
                                      out=ZR[nc])
                    else:  # (Single), as above
                        zn = ZR[nc]
                        mul(vz, dt_z, zn)
                        add(zc, zn, zn)
                    pos = PR[nc]
                    step += 1
        except KeyboardInterrupt:
            self.interrupted = True
        self.wall_s = time.perf_counter() - start
        if not self.interrupted and n and last_rec != step:
            # the final state (t_end, after the last step): its exits (TraCondition), then its
            # frame with every robot still present, those just exited included
            q = models.nid_control_point(pos, theta, s_nid) if unicycle else pos
            gone = q @ n_c >= thresh
            if route_tr is not None:  # only from the last segment
                gone &= route_tr.segment == last_seg
            if gone.any():
                acc.add_exits(step * dt, ids[gone])
                self.exit_pos[ids[gone]] = q[gone]
                if rec is not None:
                    rec.log_exits(step * dt, step, ids[gone])
            if unicycle:
                record_frame(step, ids, pos, last_command(ccvel), q, last_command(cvel), theta)
            else:
                record_frame(step, ids, pos, last_command(cvel))
        flush(n, step)
        if rec is not None:
            send_metrics()
        self.steps_done = step
        self.t_end = step * dt
        if progress is not None and not self.interrupted:
            try:
                progress(self.t_end, n_steps * dt, self.m - self.acc.exited, self.acc.exited)
            except KeyboardInterrupt:
                self.interrupted = True

    # ----- result ---------------------------------------------------------------------------
    def result(self, part: Partition | None, info: dict[str, Any] | None = None) -> SimResult:
        f = self.frames
        metrics = StepMetrics.concatenate(self.parts)
        metrics_center = StepMetrics.concatenate(self.parts_center) if self.unicycle else None
        step_t = (np.concatenate(self.step_t_parts) if self.step_t_parts
                  else np.zeros(0))
        sc = self.scenario
        route = self.route
        plan: Any = part if route is None else route  # (both have .K and .triangles)
        summary = self.acc.summary(
            dt_s=self.dt,
            wall_s=round(self.wall_s, 6),
            us_per_step=round(1e6 * self.wall_s / max(self.steps_done, 1), 3),
            duration_s=self.n_steps * self.dt,
            t_end_s=self.t_end,
            all_exited=self.acc.exited == self.m,
            interrupted=self.interrupted,
            controller=self.controller,
            model=sc.robots.model,
            record_every=self.record_every,
            frames=f,
            segments=1 if route is None else route.S,
            sub_tubes=1 if plan is None or self.controller == "apf" else plan.K,
            obstacles=len(sc.obstacles),
            remark5=[] if plan is None else [
                tri.obstacle for tri in plan.triangles if tri.remark5 is not None
            ],
            apex_distances_m=[] if plan is None else [  # h_k flown ("auto": core/plan.py)
                next((t.h for t in plan.triangles if t.obstacle == i), None)
                for i in range(len(sc.obstacles))],
            **(info or {"integrator": self.integrator}),
            integrator_stats=self.istats.as_dict(),
        )
        return SimResult(
            scenario=sc,
            controller=self.controller,
            dt=self.dt,
            record_every=self.record_every,
            t=self.rec_t[:f],
            pos=self.rec_pos[:f],
            vel=self.rec_vel[:f],
            exit_time_s=self.acc.exit_time_s.copy(),
            step_t=step_t,
            metrics=metrics,
            metrics_center=metrics_center,
            summary=summary,
            partition=part,
            route=route,
            control_pos=self.rec_cpos[:f] if self.unicycle else None,
            control_vel=self.rec_cvel[:f] if self.unicycle else None,
            heading=self.rec_head[:f] if self.unicycle else None,
            interrupted=self.interrupted,
            exit_pos=self.exit_pos.copy(),
        )
