"""``vtube-fleet check``'s library function: validate a scenario or a mission file and describe
the partition it would fly, or why there is none and what would fix it.

* A **scenario** is validated as configured (:func:`vtube_fleet.core.validation.
  validate_scenario`, the unicycles' control points as positions).
* A **mission** (a scenario plus ``[mission]``, ``docs/fleet.md``) is validated as the fleet
  validates it before arming, with the *flown* radii r_s' = r_s + δ, r_a' = r_a + δ of its
  safety budget (:func:`vtube_fleet.fleet.budget.mission_budget`, the one home of δ) and the
  start slots as positions. The budget needs the link latency and the position accuracy the
  vehicles will report; before any vehicle is connected they are the mission's ``latency_s`` /
  ``position_accuracy_m`` if set, else ``latency_s`` / ``accuracy_m`` given here (defaults:
  what ``run`` measured on real PX4 SITL, :func:`~vtube_fleet.fleet.margin.
  assumed_measurement`: L = 0.124 s, to which the mission's ``latency_headroom_s`` is added as
  in flight, and σ = 0.30 m; so that ``check`` predicts what ``run`` will accept there). The
  verdict is :func:`~vtube_fleet.fleet.margin.slot_violations`, the conditions of the
  fleet's preflight on the slots. The partition printed is the one the fleet builds from
  those radii (the same planner input: the slots); the fleet re-checks with what it measures
  before arming.
* A mission's **margin** (:func:`~vtube_fleet.fleet.margin.mission_margin`): the largest L and
  σ with which it still validates, printed after the verdict.
* When the partition is infeasible, the report names what binds (:func:`~vtube_fleet.core.
  validation.binding_constraints`) and the nearest single changes that fix it
  (:func:`~vtube_fleet.core.validation.nearest_fixes`).
* A **route** of several segments (docs/route.md) is checked by :func:`~vtube_fleet.core.
  validation.validate_route`: the paper's conditions and the partition of every segment, and
  the junction conditions of every junction with their margins; a failing one is named with
  its numbers and the nearest fixes (:func:`~vtube_fleet.core.validation.route_fixes`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vtube_fleet.config.scenario import Scenario, load_scenario
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import Partition, Violation
from vtube_fleet.core.route import Route, renumber_obstacles
from vtube_fleet.core.validation import (
    Fix,
    RouteValidation,
    binding_constraints,
    flown_symbols,
    further_failures,
    nearest_fixes,
    route_fixes,
    validate_route,
)

__all__ = ["CheckReport", "check_file", "describe_partition", "describe_route"]


@dataclass(frozen=True, eq=False)
class CheckReport:
    """What :func:`check_file` found. ``kind`` is ``"scenario"`` or ``"mission"``; ``params``
    the parameters validated (a mission's flown ones); ``budget`` a mission's
    :class:`~vtube_fleet.fleet.budget.SafetyBudget`; ``lines`` the description to print
    (without the verdict); ``violations``; ``binding`` and ``fixes`` when the partition is
    infeasible."""

    source: str
    kind: str
    scenario: Scenario
    params: ControllerParams
    partition: Partition | None
    violations: tuple[Violation, ...]
    lines: tuple[str, ...]
    budget: Any = None
    binding: tuple[str, ...] = ()
    fixes: tuple[Fix, ...] = field(default=())
    fixes_searched: bool = False
    #: the obstacles that fail after the first one (:func:`~vtube_fleet.core.validation.
    #: further_failures`), one line each
    further: tuple[str, ...] = ()
    #: a route of several segments: the planned route (``partition`` is then None) and the
    #: junction conditions (:class:`~vtube_fleet.core.route.JunctionCheck`)
    route: Route | None = None
    junctions: tuple[Any, ...] = ()
    #: a mission's :class:`~vtube_fleet.fleet.margin.BudgetMargin` (None for a scenario)
    margin: Any = None

    @property
    def ok(self) -> bool:
        return not self.violations

    def error_line(self) -> str | None:
        """One line for ``error: …`` (None when valid): the source, the first violation with
        its numbers, and how many more the report lists."""
        if self.ok:
            return None
        v = self.violations[0]
        more = len(self.violations) - 1
        return (f"{self.source}: invalid {self.kind}: [{v.condition}] {v.message}"
                + (f" (and {more} more violation{'s' if more != 1 else ''} above)"
                   if more else ""))

    def verdict_lines(self) -> list[str]:
        """The verdict: ``valid``, or ``INVALID: …`` with every violation, what binds and the
        fixes."""
        margin = [] if self.margin is None else self.margin.lines()
        if self.ok:
            return ["valid", *margin]
        n = len(self.violations)
        out = [f"INVALID: {n} violation{'s' if n != 1 else ''}:"]
        out += [f"  [{v.condition}] {v.message}" for v in self.violations]
        if self.further:
            out.append("further obstacles that fail (the construction continued without the "
                       "failing ones above):")
            out += [f"  {x}" for x in self.further]
        new = [b for b in self.binding  # a failed construction already names it above
               if not any(b in v.message for v in self.violations)]
        if new:
            out.append("binding:")
            out += [f"  {b}" for b in new]
        if self.fixes:
            out.append("nearest fixes (each alone, the rest unchanged):")
            out += [f"  {f.text}" for f in self.fixes]
        elif self.fixes_searched:
            out.append("nearest fixes: none found by changing k_t, r_a, the apex distances or "
                       "the binding obstacle's position alone")
        return out + margin


def _pt(p: np.ndarray) -> str:
    return f"({p[0]:.3f}, {p[1]:.3f})"


def _xi(x: float) -> str:
    return f"{x:8.3f}" if math.isfinite(x) else ("    -inf" if x < 0 else "     inf")


def describe_partition(scenario: Scenario, part: Partition, *, ids: tuple[int, ...] | None = None,
                       names: tuple[str, ...] | None = None) -> list[str]:
    """Human-readable lines describing the partition (sub-tubes, triangles, Remark 5, the
    apex distances the planner chose). ``ids``: the route numbers of the partition's obstacles
    (a segment of a route; default: the scenario's, in order), ``names`` its sub-tubes'."""
    lines = []
    tube = part.tube
    ids = tuple(range(len(scenario.obstacles))) if ids is None else ids
    names = tuple(t.name for t in part.sub_tubes) if names is None else names
    lines.append(f"sub-tubes: {part.K}")
    wn = max([6, *(len(n) for n in names)])
    for name, name_tube, xs, xe in zip(names, part.sub_tubes, part.xi_start, part.xi_end,
                                       strict=True):
        a, b = max(float(xs), 0.0), min(float(xe), tube.length)
        lines.append(
            f"  {name:{wn}s} xi [{_xi(float(xs))}, {_xi(float(xe))})  "
            f"start base {_pt(name_tube.p_h0)}–{_pt(name_tube.p_r0)}  "
            f"L:{'yes' if name_tube.has_L else 'no '} R:{'yes' if name_tube.has_R else 'no '}"
            f"  ({b - a:.2f} m long)"
        )
    r5 = [tri for tri in part.triangles if tri.remark5 is not None]
    lines.append(f"triangles: {len(part.triangles)}")
    for tri in part.triangles:
        gi = ids[tri.obstacle]
        ob = scenario.obstacles[gi] if gi < len(scenario.obstacles) else None
        note = "isosceles"
        if tri.remark5:
            beta = math.degrees(tri.beta)
            note = f"Remark 5: {tri.remark5} side tube dropped, beta = {beta:.2f} deg"
        how = " (auto)" if ob is not None and isinstance(ob.apex_distance, str) else ""
        r_o = f"{ob.radius:g}" if ob is not None else "(lost vehicle)"
        lines.append(
            f"  obstacle #{gi + 1} at {_pt(tri.center)} r_o = {r_o}: "
            f"h = {tri.h:.3f} m{how}, alpha = {math.degrees(tri.alpha):.2f} deg, apex "
            f"{_pt(tri.p_oth)}, base {_pt(tri.p_otu)}–{_pt(tri.p_otd)}; {note}"
        )
    if r5:
        lines.append("Remark 5 used by obstacle(s): "
                     + ", ".join(f"#{ids[tri.obstacle] + 1} ({tri.remark5})" for tri in r5))
    else:
        lines.append("Remark 5 used by obstacle(s): none")
    if part.apex is not None:
        lines.append(renumber_obstacles(part.apex.describe(), ids))
    return lines


def describe_route(scenario: Scenario, route: Route) -> list[str]:
    """The lines of a route of several segments: each segment (its waypoints, length, widths)
    and its partition (:func:`describe_partition`, sub-tubes named S2.T_o3, obstacles by their
    route numbers)."""
    lines = []
    k0 = 0
    for seg in route.segments:
        t = seg.tube
        j = seg.index
        lines.append(
            f"segment {seg.name} (waypoints {j + 1} → {j + 2}): heading "
            f"{math.degrees(math.atan2(t.n_c[1], t.n_c[0])):.1f} deg, length {t.length:.3f} m, "
            f"width {float(t.width(0.0)):.3f} -> {float(t.width(t.length)):.3f} m, obstacles "
            + (", ".join(f"#{i + 1}" for i in seg.obstacle_ids) or "none"))
        names = tuple(x.name for x in route.sub_tubes[k0:k0 + seg.K])
        lines += [f"  {x}" for x in describe_partition(scenario, seg.partition,
                                                       ids=seg.obstacle_ids, names=names)]
        k0 += seg.K
    return lines


def _header(sc: Scenario, params: ControllerParams) -> list[str]:
    r, c = sc.robots, params
    geo = sc.geometry
    if geo.is_single:
        tube = geo.segments[0]
        first = (f"tube: p_h0 {_pt(tube.p_h0)} p_h1 {_pt(tube.p_h1)} p_r0 {_pt(tube.p_r0)} "
                 f"p_r1 {_pt(tube.p_r1)}; length {tube.length:.3f} m, width "
                 f"{tube.width(0.0):.3f} -> {tube.width(tube.length):.3f} m")
    else:
        bends = ", ".join(f"{j.theta_deg:.1f} deg at waypoint {j.waypoint + 1}"
                          for j in geo.junctions)
        first = (f"route: {geo.S} segments through {len(geo.waypoints)} waypoints "
                 f"{', '.join(_pt(w.position) for w in geo.waypoints)}; bends {bends}")
    return [
        first,
        f"robots: {r.count} {r.model}, r_s = {r.r_s:g}, r_a = {r.r_a:g}, "
        f"speed in [{r.v_min:g}, {r.v_max:g}] m/s"
        + (f", NID s = {r.nid_distance:g} m" if r.model == "unicycle" else ""),
        f"controller: v = {c.v:g}, v'_max = {c.v_max_prime:g}, k_t = {c.k_t:g}, "
        f"eps_0 = {c.eps_0:g}; sim dt = {sc.sim.dt:g} s, duration = {sc.sim.duration:g} s",
        f"obstacles: {len(sc.obstacles)}",
    ]


def check_file(path: str | os.PathLike[str], *, latency_s: float | None = None,
               accuracy_m: float | None = None, fixes: bool = True) -> CheckReport:
    """Validate the scenario or mission file ``path`` (module docstring). ``latency_s``,
    ``accuracy_m``: a mission's assumed measured link latency and reported accuracy σ;
    ``fixes``: compute the nearest fixes when infeasible. Raises
    :class:`~vtube_fleet.errors.ConfigError` for a file that does not parse."""
    sc = load_scenario(path, extra_sections=("mission",))
    if "mission" not in sc.extra:
        if latency_s is not None or accuracy_m is not None:
            from vtube_fleet.errors import ConfigError

            raise ConfigError(f"{sc.source}: --latency-s and --accuracy-m apply to mission "
                              f"files (with a [mission] table) only")
        return _check(sc, "scenario", sc.controller, sc.robots.control_points(), None, [],
                      fixes, 0.0)
    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.margin import assumed_measurement, mission_margin, slot_violations
    from vtube_fleet.fleet.preflight import battery_needs

    mission = load_mission(path)
    sc = mission.scenario
    measured = assumed_measurement(latency_s, accuracy_m)
    budget, flown, res, violations = slot_violations(mission, measured)
    cfg = mission.config
    assumed = []
    if cfg.latency_s is None:
        assumed.append(f"measured latency {measured.latency_s:g} s"
                       + (" (--latency-s)" if latency_s is not None else " (default: what "
                          "PX4 SITL measures; --latency-s)")
                       + f" + latency_headroom_s {cfg.latency_headroom_s:g} s")
    if cfg.position_accuracy_m is None:
        assumed.append(f"σ = {measured.accuracy_m:g} m"
                       + (" (--accuracy-m)" if accuracy_m is not None else
                          " (default: what PX4 SITL reports; the vehicles report theirs "
                          "before arming; --accuracy-m)"))
    pre = [f"mission: {mission.count} vehicles at {cfg.rate_hz:g} Hz; safety budget "
           f"{budget.describe(sc.controller)}"
           + (f"; assumed {', '.join(assumed)}" if assumed else ""),
           f"flown: r_s' = {flown.r_s:.3f} m, r_a' = {flown.r_a:.3f} m (the partition below "
           f"is built with these, as the fleet builds it)",
           f"battery: every vehicle must report at least {mission.battery_needed_pct:.1f} % "
           f"before arming ({battery_needs(mission)})"]
    return _check(sc, "mission", flown, mission.slots, budget, pre, fixes, budget.delta_m,
                  found=(res, violations), margin=mission_margin(mission, measured))


def _check(sc: Scenario, kind: str, flown: ControllerParams, positions: np.ndarray,
           budget: Any, pre: list[str], want_fixes: bool, delta_m: float, *,
           found: tuple[RouteValidation, list[Violation]] | None = None,
           margin: Any = None) -> CheckReport:
    """``flown``: the parameters the checks use, with the flown radii r_s', r_a' (a mission's
    inflated by the safety budget; a scenario's are its own); ``found``: a mission's
    (validation, violations) from :func:`~vtube_fleet.fleet.margin.slot_violations`."""
    if not sc.geometry.is_single:
        return _check_route(sc, kind, flown, positions, budget, pre, want_fixes, delta_m,
                            found=found, margin=margin)
    corridor = sc.corridor  # one segment: its tube and obstacles
    tube, obstacles = corridor.tube, corridor.obstacles
    if found is None:
        res = validate_route(corridor, flown, positions)
        violations = list(res.violations)
    else:
        res, violations = found[0], list(found[1])
    part = None if res.route is None else res.route.segments[0].partition
    lines = [f"{sc.source}:"] + [f"  {x}" for x in _header(sc, sc.controller) + pre]
    if part is not None:
        lines += [f"  {x}" for x in describe_partition(sc, part)]
    binding: list[str] = []
    fixes: list[Fix] = []
    further: list[str] = []
    if any(v.condition == "Partition" and v.message.startswith("Partition failed")
           for v in violations):  # the construction stopped at one obstacle: the others
        further = further_failures(tube, obstacles, flown, positions)
        if kind == "mission":
            further = [flown_symbols(x) for x in further]
    partition_bad = any(v.condition in ("Partition", "Assumption3'", "Constraint3")
                        for v in violations)
    if partition_bad:
        binding = binding_constraints(tube, obstacles, flown, positions)
        if want_fixes:
            fixes = nearest_fixes(tube, obstacles, flown, positions, r_offset_m=delta_m)
    return CheckReport(sc.source, kind, sc, flown, part, tuple(violations), tuple(lines),
                       budget, tuple(binding), tuple(fixes), partition_bad and want_fixes,
                       tuple(further), margin=margin)


def _check_route(sc: Scenario, kind: str, flown: ControllerParams, positions: np.ndarray,
                 budget: Any, pre: list[str], want_fixes: bool, delta_m: float, *,
                 found: tuple[RouteValidation, list[Violation]] | None = None,
                 margin: Any = None) -> CheckReport:
    """:func:`_check` of a route of several segments (module docstring). A mission is checked
    as the fleet flies it: the flown radii and the apex look-ahead (``found``: its
    :func:`~vtube_fleet.fleet.margin.slot_violations`)."""
    mission = kind == "mission"
    if found is None:
        res = validate_route(sc.corridor, flown, positions, lookahead=mission)
        violations = list(res.violations)
    else:
        res, violations = found[0], list(found[1])
    lines = [f"{sc.source}:"] + [f"  {x}" for x in _header(sc, sc.controller) + pre]
    if res.route is not None:
        lines += [f"  {x}" for x in describe_route(sc, res.route)]
        lines.append("  junctions:")
        lines += [f"    {flown_symbols(c.describe()) if mission else c.describe()}"
                  for c in res.junctions]
    binding: list[str] = []
    further: list[str] = []
    fixes: list[Fix] = []
    fixable = ("Partition", "Assumption3'", "Constraint3", "Junction1", "Junction2",
               "Junction3", "Junction4", "Junction5")
    bad = any(v.condition in fixable for v in violations)
    seg_of = sc.corridor.start_segment_of(positions)
    for s in sorted({int(m) - 1 for v in violations
                     if v.condition in ("Partition", "Assumption3'", "Constraint3")
                     for m in _segments_named(v.message)}):
        ids, obs = sc.corridor.segment_obstacles(s)
        tube = sc.corridor.segments[s]
        mine = positions[seg_of == s]
        binding += [f"segment S{s + 1}: " + renumber_obstacles(b, ids)
                    for b in binding_constraints(tube, obs, flown, mine)]
        further += [f"segment S{s + 1}: " + renumber_obstacles(x, ids)
                    for x in further_failures(tube, obs, flown, mine)]
    if mission:
        binding = [flown_symbols(x) for x in binding]
        further = [flown_symbols(x) for x in further]
    if bad and want_fixes:
        fixes = route_fixes(sc.corridor, flown, positions, violations, r_offset_m=delta_m,
                            lookahead=mission)
    return CheckReport(sc.source, kind, sc, flown, None, tuple(violations), tuple(lines),
                       budget, tuple(binding), tuple(fixes), bad and want_fixes,
                       tuple(further), res.route, tuple(res.junctions), margin=margin)


def _segments_named(message: str) -> list[str]:
    import re

    return re.findall(r"segment S(\d+)", message)
