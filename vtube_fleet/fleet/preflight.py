"""The preflight stages: everything between "connect" and "arm", for one vehicle or a fleet.

A :class:`Preflight` runs the stages over a list of pilots (the supervisor's fleet, or an MQTT
agent's one vehicle) and reports through an event sink; every failure is a one-line
:class:`PreflightError` (nothing armed) naming each vehicle and the numbers:

1. :meth:`~Preflight.connect` every link (``connect_timeout_s``, at most :data:`CONNECT_WINDOW`
   at a time);
2. :meth:`~Preflight.ready`: heartbeat, positions, home, GPS origin, health;
3. :meth:`~Preflight.audit_params`: the PX4 parameters the mission relies on
   (:mod:`vtube_fleet.fleet.onboard`; ``--fix-params`` sets them);
4. the safety budget: :func:`wait_accuracy`, :func:`measure_budget_links` (round trip, position
   age, reported accuracy) and :func:`preflight_report` (the paper's and the junctions'
   conditions with the flown radii and the vehicles' actual positions, the apex look-ahead);
5. :meth:`~Preflight.install_fences`: the route's outline as every vehicle's PX4 geofence (one
   inclusion polygon per segment: PX4 takes their union);
6. :meth:`~Preflight.check_batteries`: every vehicle's reported charge covers the mission
   (:func:`battery_problems`);
7. :meth:`~Preflight.check_loop`: the control loop keeps its rate before anything arms.

:func:`audit_and_fence` is stages 3 and 5 for a pilot flying alone (``VehiclePilot.fly``, which
then checks its battery too).
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.core.route import Route
from vtube_fleet.core.validation import flown_symbols, validate_route
from vtube_fleet.errors import PROBLEMS_SHOWN, UserError, join_problems
from vtube_fleet.fleet.budget import (
    LOOP_CHECK_S,
    LOOP_MIN_S,
    LinkMeasurement,
    budget_latency_s,
    budget_problems,
    latency_over,
    loop_problem,
)
from vtube_fleet.link.base import LinkTimeout, VehicleLink

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.fleet.pilot import VehiclePilot
    from vtube_fleet.fleet.tick import ControlClock

__all__ = [
    "CONNECT_WINDOW",
    "FleetError",
    "MEASURE_TRIES",
    "Preflight",
    "PreflightError",
    "BATTERY_WAIT_S",
    "audit_and_fence",
    "battery_problems",
    "measure_budget_links",
    "measure_links",
    "preflight_report",
    "wait_accuracy",
]

log = logging.getLogger(__name__)

#: Links connecting at once (:meth:`Preflight.connect`).
CONNECT_WINDOW = 64
#: Rate of the ground-truth stream asked for with ``truth=True`` (HIL_STATE_QUATERNION).
TRUTH_RATE_HZ = 20.0


class FleetError(UserError):
    """The fleet could not start (connect / ready / preflight); nothing armed."""


class PreflightError(FleetError):
    """The vehicles' positions or the safety budget break the paper's conditions."""


async def _raise(result: object) -> None:
    """Re-raise a result of ``gather(..., return_exceptions=True)`` inside a coroutine."""
    if isinstance(result, BaseException):
        raise result


#: Seconds of sensing used to measure link latency + position-sample age before the safety
#: budget δ is fixed (supervisor and standalone agent alike).
MEASURE_S = 1.0


async def measure_links(pilots: Sequence[VehiclePilot], period_s: float,
                        duration_s: float = MEASURE_S) -> LinkMeasurement:
    """Round trips (every link at once), then ``duration_s`` of position-sample ages and
    accuracies sampled every ``period_s``."""
    trips = await asyncio.gather(*(p.link.measure_round_trip_s() for p in pilots),
                                 return_exceptions=True)
    rtts = [float(r) for r in trips if isinstance(r, int | float) and math.isfinite(r)]
    lat = [p.link.latency_s for p in pilots if p.link.latency_s is not None]
    one_way = max([r / 2.0 for r in rtts] + [float(x) for x in lat], default=0.0)
    loop = asyncio.get_running_loop()
    ages: list[float] = []
    acc = [math.nan] * len(pilots)
    end = loop.time() + duration_s
    while loop.time() < end:
        now = time.monotonic()
        ages.extend(p.sample_age_s(now) for p in pilots)
        for i, p in enumerate(pilots):
            a = p.position_accuracy_m()
            if math.isfinite(a):
                acc[i] = a  # the latest report (it only settles downwards after boot)
        await asyncio.sleep(period_s)  # the sampling period of the measurement
    a = np.asarray(ages, dtype=float)
    a = a[np.isfinite(a)]
    known = [x for x in acc if math.isfinite(x)]
    return LinkMeasurement(float(np.percentile(a, 95)) if a.size else 0.0, one_way,
                           max(known) if known else math.nan, tuple(acc))


#: Measurements :func:`measure_budget_links` takes before a measured L that is too large
#: refuses the mission.
MEASURE_TRIES = 3


async def measure_budget_links(
    pilots: Sequence[VehiclePilot], mission: Mission, duration_s: float = MEASURE_S, *,
    too_slow: Callable[[LinkMeasurement], str | None] | None = None,
    on_wait: Callable[[str], None] | None = None,
) -> tuple[LinkMeasurement, list[str]]:
    """:func:`measure_links` and :func:`~vtube_fleet.fleet.budget.budget_problems`; while the
    measured L is too large (above ``max_latency_s``, or ``too_slow(measured)`` returns the
    caller's reason: the MQTT agent's, that the run's δ does not cover it), measured again,
    up to :data:`MEASURE_TRIES` times. A fleet's processes all start their flight at once
    (planning, recordings, every agent at the same moment), and a second of that load is not
    the link's latency. The budget is built on the measurement returned (the last), and the
    in-flight watch (:class:`~vtube_fleet.fleet.budget.BudgetWatch`) judges L against it from
    then on. A refusal names every try's L. ``on_wait``: where the "measuring again" line goes
    (the supervisor's events; default: the log, as a warning)."""
    period_s = mission.config.period_s
    tries: list[LinkMeasurement] = []
    while True:
        measured = await measure_links(pilots, period_s, duration_s)
        tries.append(measured)
        over = latency_over(mission, measured)
        reason = None if too_slow is None else too_slow(measured)
        if not (over or reason) or len(tries) >= MEASURE_TRIES:
            break
        limit = (f"> max_latency_s = {1000 * mission.config.max_latency_s:.0f} ms" if over
                 else "too large for the run")
        (on_wait or log.warning)(
            f"link latency L = {1000 * budget_latency_s(mission, measured):.0f} ms {limit}: "
            f"measuring again ({len(tries) + 1} of {MEASURE_TRIES})")
    problems = budget_problems(mission, measured)
    if reason:
        problems.append(reason)
    if (over or reason) and len(tries) > 1:
        problems.append(
            f"the same in {len(tries)} measurements of {duration_s:g} s (L = "
            + ", ".join(f"{1000 * budget_latency_s(mission, m):.0f}" for m in tries) + " ms)")
    return measured, problems


#: Seconds :func:`wait_accuracy` waits for ESTIMATOR_STATUS before it accepts GNSS h_acc.
ESTIMATOR_WAIT_S = 5.0
#: The reported accuracy counts as settled when it changed by at most 10 % in this long.
SETTLE_S = 1.0


async def wait_accuracy(pilots: Sequence[VehiclePilot], max_m: float, timeout_s: float,
                        on_wait: Callable[[str], None] | None = None) -> None:
    """Wait until every vehicle reports a horizontal accuracy of at most ``max_m`` and it has
    settled (PX4's estimate settles for a few seconds after boot: 14 → 0.3 m);
    :class:`PreflightError` naming the vehicles above ``max_m`` after ``timeout_s``."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    end = start + timeout_s
    said = False
    history: list[tuple[float, list[float]]] = []
    while True:
        # the estimator's own accuracy first; a vehicle that sends none for ESTIMATOR_WAIT_S
        # is judged by its GNSS receiver's (GPS_RAW_INT h_acc, larger)
        now = loop.time()
        gnss = now - start > ESTIMATOR_WAIT_S
        now_acc = [p.position_accuracy_m(allow_gnss=gnss) for p in pilots]
        bad = [(p, a) for p, a in zip(pilots, now_acc, strict=True)
               if not (math.isfinite(a) and a <= max_m)]
        # settled: within 10 % (or 2 cm) of what it was SETTLE_S ago (PX4 after boot:
        # 14 → 2.0 → 0.6 → 0.33 → 0.30 m over ~6 s)
        history.append((now, now_acc))
        while len(history) > 1 and history[1][0] <= now - SETTLE_S:
            history.pop(0)
        old_t, old_acc = history[0]
        settled = now - old_t >= SETTLE_S and all(
            abs(a - b) <= max(0.02, 0.1 * b) for a, b in zip(now_acc, old_acc, strict=True))
        if not bad and settled:
            return
        if loop.time() >= end and not bad:
            return  # within the bound, still settling: the budget takes the latest value
        if loop.time() >= end:
            raise PreflightError(
                f"{len(bad)} vehicle(s) do not report a horizontal position accuracy of at most "
                f"max_position_accuracy_m = {max_m:g} m within {timeout_s:g} s: " + "; ".join(
                    f"{p.name} {'none reported' if not math.isfinite(a) else f'{a:.2f} m'}"
                    for p, a in bad))
        if not said and on_wait is not None and now - start > 0.5:
            said = True
            shown = bad or list(zip(pilots, now_acc, strict=True))
            on_wait("waiting for the reported position accuracy to settle: " + ", ".join(
                f"{p.name} {'none yet' if not math.isfinite(a) else f'{a:.2f} m'}"
                for p, a in shown[:4]) + (" …" if len(shown) > 4 else ""))
        await asyncio.sleep(0.2)



def preflight_report(
    mission: Mission,
    flown: Any,
    positions: np.ndarray,
    names: Sequence[str],
    *,
    where: str = "on the ground",
    route: Route | None = None,
) -> tuple[Route | None, list[str]]:
    """Validate the (inflated) route with the vehicles' actual positions
    (:func:`~vtube_fleet.core.validation.validate_route`: the paper's conditions per segment,
    the junction conditions, Assumption 1 of each vehicle in the segment it starts in) and the
    apex look-ahead the fleet flies (:func:`~vtube_fleet.fleet.margin.lookahead_violations`:
    no vehicle starts inside a side tube's barrier) — ``check``'s conditions, on the vehicles'
    positions; ``flown``: the parameters with the flown radii r_s', r_a' (the plan's
    ``flown``); ``route``: the route planned before (at altitude: only the positions are
    checked against it, nothing is planned while the vehicles fly).

    Returns (the planned route, with the look-ahead, or None; problems). Each problem is one
    line naming the vehicles (``robot i`` / ``slot i`` becomes ``vehicle i (endpoint)``) with
    the numbers.
    """
    from vtube_fleet.fleet.margin import lookahead_violations

    sc = mission.scenario
    res = validate_route(sc.corridor, flown, positions,
                         keep_out=mission.slots,  # "auto": plan on the slots
                         lookahead=True, route=route)
    violations = list(res.violations)
    if res.route is not None:
        violations += lookahead_violations(res.route, positions, names)

    def one(text: str) -> str:
        i = int(text)
        return names[i] if 0 <= i < len(names) else f"robot {i}"

    problems = []
    for v in violations:
        msg = re.sub(r"\brobots (\d+) and (\d+)",
                     lambda m: f"{one(m.group(1))} and {one(m.group(2))}", v.message)
        msg = re.sub(r"\brobot (\d+)", lambda m: one(m.group(1)), msg)
        problems.append(f"{flown_symbols(msg)} ({where}, r_s' = {flown.r_s:.3f} m: the "
                        f"physical r_s = {sc.robots.r_s:g} m + δ)")
    return res.route, problems




#: Seconds :meth:`Preflight.check_batteries` waits for every vehicle's first battery report
#: (PX4 sends SYS_STATUS at 5 Hz from half a second after boot, BATTERY_STATUS at 0.5 Hz).
BATTERY_WAIT_S = 5.0


def battery_problems(pilots: Sequence[VehiclePilot], mission: Mission) -> list[str]:
    """One line per vehicle whose reported charge does not cover the mission:
    :attr:`~vtube_fleet.config.mission.Mission.battery_needed_pct` (``battery_reserve_pct``
    + ``battery_drain_pct_per_min`` × ``expected_airborne_s``), or that reports none."""
    need = mission.battery_needed_pct
    out = []
    for p in pilots:
        pct = 100.0 * p.link.state.battery_remaining
        if math.isnan(pct):
            out.append(f"{p.name}: reports no battery charge")
        elif pct < need:
            out.append(f"{p.name}: battery {pct:.0f} % < {need:.1f} % needed")
    return out


def battery_needs(mission: Mission) -> str:
    """What :func:`battery_problems` requires, with the numbers (for its messages)."""
    cfg = mission.config
    return (f"battery_reserve_pct {cfg.battery_reserve_pct:g} % + battery_drain_pct_per_min "
            f"{cfg.battery_drain_pct_per_min:g} %/min × {mission.expected_airborne_s:.0f} s "
            f"expected in the air = {mission.battery_needed_pct:.1f} %")


#: ``event(text, vehicle_id=None, level="info", echo=True)``: where the stages report.
Events = Callable[..., None]


def _log_event(text: str, vehicle_id: int | None = None, level: str = "info",
               echo: bool = True) -> None:
    getattr(log, "warning" if level in ("warning", "error") else "info")("%s", text)


class Preflight:
    """The preflight stages (module docstring) of ``pilots`` flying ``mission``; ``event``:
    the sink (the supervisor's events; default: the log); ``backend``: named in messages;
    ``onboard``: the summary's record of the fence and the parameter audit (filled in)."""

    def __init__(self, pilots: Sequence[VehiclePilot], mission: Mission, *,
                 event: Events | None = None, backend: str = "mavlink",
                 onboard: dict[str, Any] | None = None) -> None:
        self.pilots = list(pilots)
        self.mission = mission
        self.cfg = mission.config
        self.event: Events = event or _log_event
        self.backend = backend
        self.names = [p.name for p in self.pilots]
        #: summary "onboard": fence ("uploaded" / "off" / "unsupported" / None = not reached),
        #: fence_items, gf_action, px4_params (per vehicle, as read), params_fixed
        self.onboard: dict[str, Any] = onboard if onboard is not None else {
            "fence": None, "fence_items": 0, "gf_action": None, "px4_params": [],
            "params_fixed": {}}
        self.param_restore: list[dict[str, float]] = []
        #: summary "battery": what the check before arming required and found
        #: (:meth:`check_batteries`; None: not reached)
        self.battery: dict[str, Any] | None = None

    # -- reporting -------------------------------------------------------------------------------
    def listed(self, problems: Sequence[str]) -> str:
        """The problems for a one-line error (:func:`~vtube_fleet.errors.join_problems`); when
        some are left out of it, every one is recorded as an event first (not echoed: the
        error line is what the terminal shows)."""
        if len(problems) > PROBLEMS_SHOWN:
            for text in problems:
                self.event(text, level="error", echo=False)
        return join_problems(problems)

    async def gather_named(self, what: str, coros: Sequence[Any], limit: int | None = None,
                           pilots: Sequence[VehiclePilot] | None = None) -> list[str]:
        """One problem line per pilot whose coroutine failed (``coros[k]`` is ``pilots[k]``'s,
        default: every pilot's); ``limit``: at most that many running at once
        (:func:`~vtube_fleet.fleet.onboard.gather_bounded`)."""
        if limit is None:
            results = await asyncio.gather(*coros, return_exceptions=True)
        else:
            from vtube_fleet.fleet.onboard import gather_bounded

            results = await gather_bounded(coros, limit)
        problems = []
        for p, r in zip(self.pilots if pilots is None else pilots, results, strict=True):
            if isinstance(r, asyncio.CancelledError):
                raise r
            if isinstance(r, BaseException):
                if not isinstance(r, UserError | OSError):
                    log.error("%s: %s failed", p.name, what, exc_info=r)
                msg = str(r)
                problems.append(msg if p.link.endpoint.url in msg else f"{p.name}: {msg}")
        return problems

    # -- 1. connect, 2. ready ------------------------------------------------------------------
    async def connect(self) -> None:
        """Connect every link within ``connect_timeout_s``, at most :data:`CONNECT_WINDOW` at
        a time: a link binds its socket only when its turn comes, so the vehicles not reached
        yet are not heard (their default streams, ATTITUDE at 100 Hz among them, would
        otherwise flood this process before the first links have turned them off)."""
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        deadline = loop.time() + cfg.connect_timeout_s

        async def one(link: VehicleLink) -> None:  # runs when its turn in the window comes
            left = deadline - loop.time()
            if left <= 0:
                raise LinkTimeout(f"not tried: connect_timeout_s = "
                                  f"{cfg.connect_timeout_s:g} s ran out while connecting "
                                  f"the others (at most {CONNECT_WINDOW} at a time)")
            await link.connect(timeout_s=left)

        problems = await self.gather_named("connect", [one(p.link) for p in self.pilots],
                                           limit=CONNECT_WINDOW)
        if problems:
            # before the deadline: a link refused at once (a port in use, a bad address)
            when = (f"did not connect within connect_timeout_s = {cfg.connect_timeout_s:g} s"
                    if loop.time() >= deadline - 0.05 else "could not connect")
            raise FleetError(f"{len(problems)} of {len(self.pilots)} vehicles {when}: "
                             + self.listed(problems))
        self.event(f"connected {len(self.pilots)} vehicles ({self.backend})")

    async def ready(self) -> None:
        """Every vehicle READY (``VehiclePilot.wait_ready``; the control clock runs)."""
        problems = await self.gather_named("ready", [p.wait_ready() for p in self.pilots])
        if problems:
            raise FleetError(f"{len(problems)} of {len(self.pilots)} vehicles not ready: "
                             + self.listed(problems))

    # -- 3. the PX4 parameters ------------------------------------------------------------------
    async def audit_params(self, fix: bool = False) -> None:
        """The PX4 parameter audit (:func:`~vtube_fleet.fleet.onboard.audit_fleet`): hard
        mismatches refuse to arm with the numbers, soft ones warn; ``fix`` sets them (the old
        values are kept in :attr:`param_restore` for :meth:`restore_params`)."""
        from vtube_fleet.fleet.onboard import audit_fleet

        res = await audit_fleet([p.link for p in self.pilots], self.mission, fix=fix)
        self.param_restore = res.changed
        self.onboard["px4_params"] = res.values
        self.onboard["params_fixed"] = {self.names[i]: old for i, old in enumerate(res.changed)
                                        if old}
        if res.unsupported:
            self.event(f"PX4 parameter audit skipped: the {self.backend} backend cannot read "
                       f"PX4 parameters (use --backend mavlink)", level="warning")
        for w in res.warnings:  # what --fix-params set is routine (info), the rest warns
            self.event(w, level="info" if "; --fix-params set " in w else "warning")
        if res.problems:
            raise PreflightError("preflight failed, nothing armed: PX4 parameters: "
                                 + self.listed(res.problems)
                                 + " (vtube-fleet run --fix-params sets them for the flight)")
        if not res.unsupported:
            self.event(f"PX4 parameters checked on {len(self.pilots)} vehicles"
                       + (" (--fix-params)" if fix else ""))

    async def restore_params(self) -> None:
        """Set back what :meth:`audit_params` with ``fix`` changed (every exit path)."""
        if not any(self.param_restore):
            return
        from vtube_fleet.fleet.onboard import restore_params

        fails = await restore_params([p.link for p in self.pilots], self.param_restore)
        for line in fails:
            self.event(line, level="error")
        if not fails:
            self.event("--fix-params: the PX4 parameters are restored")
        self.param_restore = []

    async def request_truth(self) -> None:
        """Ask every vehicle for its SITL ground truth (``--truth``); refusals are errors."""
        problems = await self.gather_named(
            "ground truth", [p.link.request_truth(TRUTH_RATE_HZ) for p in self.pilots])
        if problems:
            raise PreflightError(f"--truth: {len(problems)} vehicle(s) do not send their "
                                 f"ground truth (HIL_STATE_QUATERNION; PX4 SITL and the mock "
                                 f"do, real vehicles do not): " + self.listed(problems))
        self.event(f"ground truth (HIL_STATE_QUATERNION) requested at {TRUTH_RATE_HZ:g} Hz")

    # -- 5. the fence ------------------------------------------------------------------------
    async def install_fences(self, fence: bool = True) -> None:
        """The route's outline as every vehicle's geofence (GF_ACTION, upload, read back,
        compare: one inclusion polygon per segment, their union; an exclusion circle per
        obstacle); a vehicle that refuses it keeps the fleet on the ground; ``fence`` False:
        none, with :data:`~vtube_fleet.fleet.onboard.NO_FENCE_WARNING`."""
        from vtube_fleet.fleet.onboard import (
            GF_ACTION_VALUES,
            NO_FENCE_WARNING,
            fence_geometry,
            fence_items,
            gather_bounded,
            install_fence,
        )
        from vtube_fleet.link.base import LinkUnsupported

        if not fence:
            self.onboard["fence"] = "off"
            self.event(NO_FENCE_WARNING, level="warning")  # a safety layer turned off
            return
        geom = fence_geometry(self.mission)
        positions = np.array([p.xy for p in self.pilots]).reshape(-1, 2)
        problems = geom.problems(positions, self.names)
        if problems:
            raise PreflightError("preflight failed, nothing armed: the fence would be breached "
                                 "at once: " + self.listed(problems))
        items = fence_items(self.mission, geom)
        action = self.cfg.fence_action
        results = await gather_bounded(
            [install_fence(p.link, items, GF_ACTION_VALUES[action]) for p in self.pilots])
        if any(isinstance(r, LinkUnsupported) for r in results):
            self.onboard["fence"] = "unsupported"
            self.event(f"fence NOT uploaded: the {self.backend} backend cannot upload PX4 "
                       f"fences (use --backend mavlink, or --no-fence to silence this)",
                       level="warning")
            return
        problems = await self.gather_named("fence", [_raise(r) for r in results])
        if problems:
            raise PreflightError(f"preflight failed, nothing armed: {len(problems)} of "
                                 f"{len(self.pilots)} vehicles refused the fence: "
                                 + self.listed(problems))
        self.onboard.update(fence="uploaded", fence_items=len(items), gf_action=action)
        polys = geom.polygons
        shape = (f"{len(polys[0])}-vertex polygon" if len(polys) == 1 else
                 f"{len(polys)} inclusion polygons, one per segment ("
                 + " + ".join(str(len(q)) for q in polys) + " vertices; PX4 allows their union)")
        self.event(f"fence on {len(self.pilots)} vehicles: {shape} (legs + "
                   f"{geom.widen_m:.2f} m, {geom.back_m:.2f} m behind the start, "
                   f"{geom.exit_m:.2f} m past the finish), {geom.circle_radii.size} exclusion "
                   f"circle(s); GF_ACTION = {GF_ACTION_VALUES[action]} ({action})")

    # -- 6. the batteries ---------------------------------------------------------------------
    async def check_batteries(self) -> None:
        """Before arming: every vehicle reports at least the charge the mission needs
        (:func:`battery_problems`; waits up to :data:`BATTERY_WAIT_S` for the first reports);
        one line per vehicle that does not, with the numbers. Off when the mission needs
        nothing (``battery_reserve_pct`` and ``battery_drain_pct_per_min`` both 0)."""
        mission, cfg = self.mission, self.cfg
        need = mission.battery_needed_pct
        self.battery = {"reserve_pct": cfg.battery_reserve_pct,
                        "drain_pct_per_min": cfg.battery_drain_pct_per_min,
                        "expected_airborne_s": round(mission.expected_airborne_s, 1),
                        "needed_pct": round(need, 1), "at_arming_pct": None}
        if need <= 0.0:
            self.event("battery check off (battery_reserve_pct and battery_drain_pct_per_min "
                       "are 0)", level="warning")
            return
        loop = asyncio.get_running_loop()
        end = loop.time() + BATTERY_WAIT_S
        while (any(math.isnan(p.link.state.battery_remaining) for p in self.pilots)
               and loop.time() < end):
            await asyncio.sleep(0.2)  # the next SYS_STATUS (5 Hz)
        found = [100.0 * p.link.state.battery_remaining for p in self.pilots]
        self.battery["at_arming_pct"] = [None if math.isnan(x) else round(x, 1) for x in found]
        problems = battery_problems(self.pilots, mission)
        if problems:
            raise PreflightError(f"preflight failed, nothing armed: {len(problems)} of "
                                 f"{len(self.pilots)} vehicles' batteries do not cover the "
                                 f"mission ({battery_needs(mission)}): "
                                 + self.listed(problems))
        low = min(found)
        self.event(f"batteries: at least {low:.0f} % on every vehicle, {need:.1f} % needed "
                   f"({battery_needs(mission)})")

    # -- 7. the control loop -----------------------------------------------------------------------
    async def check_loop(self, clock: ControlClock) -> None:
        """Before arming: :func:`~vtube_fleet.fleet.budget.loop_problem` over the last
        LOOP_CHECK_S of clock time (at least LOOP_MIN_S: waits for it); a failure is judged
        once more on the next LOOP_CHECK_S (one stall, e.g. a GC pause, is not a slow loop),
        and a second one refuses to arm."""
        loop = asyncio.get_running_loop()
        started = clock.starts_s[0] if clock.starts_s else loop.time()
        if (wait := started + LOOP_MIN_S - loop.time()) > 0:
            await asyncio.sleep(wait)  # the clock must have run LOOP_MIN_S to be judged

        def judged() -> str | None:
            now = loop.time()
            return loop_problem(clock.starts_s, clock.lateness_s, clock.durations_s,
                                self.cfg.period_s, len(self.pilots), now_s=now,
                                window_s=min(LOOP_CHECK_S, now - started))

        if (problem := judged()) is None:
            return
        self.event(f"{problem}; judging the next {LOOP_CHECK_S:g} s once more", level="warning")
        await asyncio.sleep(LOOP_CHECK_S)  # a fresh window of ticks, not a synchronisation
        if (problem := judged()) is not None:
            raise PreflightError(f"preflight failed, nothing armed: {problem}")


async def audit_and_fence(pilots: Sequence[VehiclePilot], mission: Mission, *,
                          fence: bool = True, fix: bool = False) -> Preflight:
    """The parameter audit and the fence (:meth:`Preflight.audit_params`,
    :meth:`Preflight.install_fences`) for pilots flying on their own (an MQTT agent), reporting
    through their own events."""
    first = pilots[0] if pilots else None

    def event(text: str, vehicle_id: int | None = None, level: str = "info",
              echo: bool = True) -> None:
        if first is not None:
            first.event(text, level)

    pre = Preflight(pilots, mission, event=event)
    await pre.audit_params(fix=fix)
    await pre.install_fences(fence)
    return pre
