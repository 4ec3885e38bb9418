"""Scenario validation: every condition of the paper checked before anything moves.

:func:`validate_scenario` returns all violations, each a :class:`Violation` carrying the
condition's name and the numbers; :func:`check_scenario` raises :class:`ScenarioError` (a
:class:`~vtube_fleet.errors.UserError`) listing them. Checked:

* ``Parameters``: r_a > r_s > 0, v_max > v_min ≥ 0, v > 0, v'_max > 0, k_t ≥ 1, k2, k3 > 0,
  k4 ≥ 0 and every ε > 0;
* ``Constraint1``: v + v'_max ≤ v_max and v − v'_max ≥ v_min (Constraint1);
* ``Constraint2``: the main tube's narrowing legs, v‖n_c − t‖ ≤ v'_max (Constraint2);
* ``Assumption3``: the main tube (L ∩ R = ∅, M ≠ ∅, length > 2 r_a, room for one robot);
* ``pothk``: every obstacle with a configured apex distance satisfies (pothk);
* ``Partition``: the partition of Section IV can be built (:mod:`vtube_fleet.core.partition`);
* ``Assumption3'`` and ``Constraint3``: every sub-tube of the partition;
* ``Assumption1``: the initial positions — S_i ⊂ T (both leg distances ≥ r_s, centre between
  the bases), S_i ∩ S_j = ∅ (‖p_i − p_j‖ > 2 r_s, found with a k-d tree), S_i ∩ O_k = ∅
  (‖p_i − p_o,k‖ > r_o,k + r_s), and no robot starting inside a circumscribed triangle (it
  would belong to no sub-tube).

Robot indices in messages are 0-based (config order); obstacles are numbered from 1 (#1 is the
first obstacle of the config). Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.core.params import parameter_problems
from vtube_fleet.core.partition import (
    Partition,
    PartitionError,
    Violation,
    check_assumption3,
    check_constraint2,
    h_min,
    partition,
)
from vtube_fleet.core.plan import plan_apex
from vtube_fleet.core.route import (
    Corridor,
    JunctionCheck,
    Route,
    handover_line,
    junction_checks,
    obstacle_ownership,
    renumber_obstacles,
    segment_error,
    segment_keep_out,
)
from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.core.text import obstacle_label
from vtube_fleet.core.text import point_text as _pt
from vtube_fleet.core.tube import APEX_AUTO, Obstacle, Trapezoid
from vtube_fleet.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from vtube_fleet.core.params import ControllerParams

__all__ = [
    "FIX_ITERATIONS",
    "MAX_LISTED",
    "Fix",
    "RouteValidation",
    "ScenarioError",
    "Violation",
    "binding_constraints",
    "bisect_edge",
    "check_scenario",
    "flown_symbols",
    "further_failures",
    "nearest_fixes",
    "route_fixes",
    "validate_route",
    "validate_scenario",
]

#: At most this many robots (or robot pairs) are listed per kind of Assumption 1 violation; the
#: rest are summarised as "… and N more".
MAX_LISTED = 10

_TOL = 1e-9


_RADIUS_SYMBOL = re.compile(r"\b(r_s|r_a)\b(?!')")


def flown_symbols(text: str) -> str:
    """A message of :func:`validate_scenario` run with the *flown* parameters (the radii
    inflated by the safety budget) in their own symbols: ``r_s`` → ``r_s'``, ``r_a`` →
    ``r_a'`` ("2 r_s' = 3.91 m"), so that ``r_s`` keeps meaning the physical radius."""
    return _RADIUS_SYMBOL.sub(r"\1'", text)


def _ob(i: int, ob: Obstacle) -> str:
    return obstacle_label(i, ob)


class ScenarioError(UserError):
    """The scenario violates conditions of the paper. ``violations`` lists them; the message's
    first line is a summary, then one line per violation."""

    def __init__(self, violations: Sequence[Violation]) -> None:
        self.violations = tuple(violations)
        counts = Counter(v.condition for v in self.violations)
        kinds = ", ".join(f"{c} ×{n}" if n > 1 else c for c, n in counts.items())
        n = len(self.violations)
        summary = f"scenario rejected: {n} violation{'s' if n != 1 else ''} ({kinds})"
        super().__init__("\n".join([summary] + [f"  {v.message}" for v in self.violations]))


# ----------------------------------------------------------------------------------------------
# Individual checks
# ----------------------------------------------------------------------------------------------
def _check_parameters(params: Any) -> list[Violation]:
    """The parameters' domain (:func:`~vtube_fleet.core.params.parameter_problems`, the one
    check), reported as the "Parameters" condition."""
    names = ("r_s", "r_a", "v_min", "v_max", "v", "v_max_prime", "k2", "k3", "k4", "k_t",
             "eps_m", "eps_t", "eps_s", "eps_0", "eps_o")
    values = {n: getattr(params, n) for n in names if getattr(params, n, None) is not None}
    return [Violation("Parameters", f"Parameters invalid: {m}")
            for m in parameter_problems(values)]


def _check_constraint1(params: ControllerParams) -> list[Violation]:
    v, vp, v_min, v_max = params.v, params.v_max_prime, params.v_min, params.v_max
    out = []
    if v + vp > v_max + _TOL * max(1.0, abs(v_max)):
        out.append(Violation("Constraint1", (
            f"Constraint1 violated: v + v'_max = {_num(v + vp)} > v_max = {_num(v_max)} "
            f"(v = {_num(v)}, v'_max = {_num(vp)})")))
    if v - vp < v_min - _TOL * max(1.0, abs(v_min)):
        out.append(Violation("Constraint1", (
            f"Constraint1 violated: v - v'_max = {_num(v - vp)} < v_min = {_num(v_min)} "
            f"(v = {_num(v)}, v'_max = {_num(vp)})")))
    return out


def _check_pothk(obstacles: Sequence[Obstacle], params: ControllerParams) -> list[Violation]:
    out = []
    for i, ob in enumerate(obstacles):
        if ob.apex_distance is None or isinstance(ob.apex_distance, str):
            continue  # the default and "auto" (core/plan.py) satisfy (pothk) by construction
        hm = h_min(float(ob.radius), params)
        h = float(ob.apex_distance)
        if h < hm * (1.0 - _TOL):
            out.append(Violation("pothk", (
                f"pothk violated: {_ob(i, ob)}: apex_distance h = {_num(h)} m < h_min = "
                f"(r_o + r_s)/((v'_max/v)·√(1 − v'_max²/4v²)) = {_num(hm)} m")))
    return out


def _capped(n: int, describe: Callable[[int], str], more: str) -> list[Violation]:
    """Assumption1 violations for items 0..n-1: the first MAX_LISTED described one by one
    (only those are formatted), the rest summarised as "… and N more <more>"."""
    out = [Violation("Assumption1", f"Assumption1 violated: {describe(k)}")
           for k in range(min(n, MAX_LISTED))]
    if n > MAX_LISTED:
        out.append(Violation("Assumption1",
                             f"Assumption1 violated: … and {n - MAX_LISTED} more {more}"))
    return out


def _check_assumption1(
    tube: Trapezoid | None,
    obstacles: Sequence[Obstacle],
    params: ControllerParams,
    p: np.ndarray,
    part: Partition | Route | None,
    route: Route | None = None,
) -> list[Violation]:
    """Assumption 1 of the start positions ``p`` in ``tube`` (one tube) or, with ``route``,
    each in the segment it starts in (:meth:`Route.start_segments`)."""
    lim = SafetyLimits.from_params(params)
    r_s = lim.leg_m
    out: list[Violation] = []
    finite = np.all(np.isfinite(p), axis=1)
    bad = np.flatnonzero(~finite)
    out += _capped(len(bad), lambda k: f"robot {bad[k]} position {_pt(p[bad[k]])} is not a "
                   "finite point", "robots with non-finite positions")
    idx = np.flatnonzero(finite)
    q = p[idx]

    # S_i ⊂ T: d_Th ≥ r_s, d_Tr ≥ r_s and the centre between the bases (of its segment).
    if route is None:
        assert tube is not None
        d_h, d_r, xi = tube.d_Th(q), tube.d_Tr(q), tube.xi(q)
        L = np.full(q.shape[0], tube.length)
        where = np.full(q.shape[0], "T")
    else:
        seg = route.start_segments(q)
        d_h, d_r = route.leg_distances(q, seg)
        xi = route.xi(q, seg)
        L = np.array([route.segments[int(s)].tube.length for s in seg])
        where = np.array([f"its segment S{int(s) + 1}" for s in seg])
    outside = np.flatnonzero((d_h < r_s) | (d_r < r_s) | (xi < 0) | (xi > L))

    def not_in_T(n: int) -> str:
        k = outside[n]
        why = []
        if d_h[k] < r_s:
            why.append(f"distance to the left leg {_num(float(d_h[k]), 2)} m < r_s = "
                       f"{_num(r_s)} m")
        if d_r[k] < r_s:
            why.append(f"distance to the right leg {_num(float(d_r[k]), 2)} m < r_s = "
                       f"{_num(r_s)} m")
        if xi[k] < 0:
            why.append(f"ξ = {_num(float(xi[k]), 2)} m is before the start base")
        if xi[k] > L[k]:
            why.append(f"ξ = {_num(float(xi[k]), 2)} m is beyond the finishing line "
                       f"(L = {_num(float(L[k]), 2)} m)")
        return (f"robot {idx[k]} at {_pt(q[k])} is not inside {where[k]} (S_i ⊄ T): "
                + "; ".join(why))

    out += _capped(len(outside), not_in_T, "robots not inside T")

    # S_i ∩ S_j = ∅: ‖p_i − p_j‖ > 2 r_s (k-d tree, no O(M²) memory).
    if len(q) > 1:
        pairs = cKDTree(q).query_pairs(lim.pair_m, output_type="ndarray")
        if len(pairs):
            pairs = np.sort(idx[pairs], axis=1)
            pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

            def overlap(n: int) -> str:
                i, j = pairs[n]
                d = float(np.hypot(*(p[i] - p[j])))
                return (f"robots {i} and {j} overlap: distance {_num(d, 2)} m ≤ 2 r_s = "
                        f"{_num(lim.pair_m, 2)} m")

            out += _capped(len(pairs), overlap, "overlapping pairs")

    # S_i ∩ O_k = ∅: ‖p_i − p_o‖ > r_o + r_s.
    hits: list[tuple[int, int, float]] = []  # (robot row in q, obstacle index, distance)
    n_hits = 0
    for k_ob, ob in enumerate(obstacles):
        d = np.hypot(*(q - ob.center).T)
        rows = np.flatnonzero(d <= lim.obstacle_center_m(ob.radius))
        n_hits += len(rows)
        hits += [(int(k), k_ob, float(d[k])) for k in rows[:MAX_LISTED]]

    def on_obstacle(n: int) -> str:
        k, k_ob, d = hits[n]
        ob = obstacles[k_ob]
        return (f"robot {idx[k]} at {_pt(q[k])} overlaps {_ob(k_ob, ob)}: centre distance "
                f"{_num(d, 2)} m ≤ r_o + r_s = {_num(lim.obstacle_center_m(ob.radius), 2)} m")

    out += _capped(n_hits, on_obstacle, "robot–obstacle overlaps")

    # Not inside a circumscribed triangle (such a robot belongs to no sub-tube).
    if part is not None:
        in_tri = []  # (robot row in q, triangle)
        for tri in (route if route is not None else part).triangles:
            inside = tri.contains(q, tol=-1e-9) & (np.hypot(*(q - tri.center).T) > tri.radius_ext)
            in_tri += [(k, tri) for k in np.flatnonzero(inside)]

        def in_triangle(n: int) -> str:
            k, tri = in_tri[n]
            return (f"robot {idx[k]} at {_pt(q[k])} starts inside the circumscribed triangle "
                    f"of {_ob(tri.obstacle, obstacles[tri.obstacle])} (apex {_pt(tri.p_oth)}), "
                    f"i.e. in no sub-tube")

        out += _capped(len(in_tri), in_triangle, "robots inside circumscribed triangles")
    return out


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------
def validate_scenario(
    tube: Trapezoid,
    obstacles: Sequence[Obstacle],
    params: ControllerParams,
    positions: np.ndarray | None = None,
    keep_out: np.ndarray | None = None,
    part: Partition | None = None,
) -> tuple[Partition | None, list[Violation]]:
    """Check a scenario against the paper's conditions (module docstring) before anything
    moves. Returns (the partition, or ``None`` if it could not be built or the parameters are
    unusable; every violation found). ``positions`` (M, 2) are the robots' initial positions
    (``None``: Assumption 1 is not checked). ``keep_out``: the points the planner of
    ``"auto"`` apex distances keeps out of the triangles (default: ``positions``; the fleet
    passes its start slots so that every process plans the same partition). ``part``: the
    partition already built for these parameters (not planned again: the fleet at altitude
    checks the flown positions against the partition it planned on the ground)."""
    violations = _check_parameters(params)
    sane = not violations
    if all(math.isfinite(float(x)) for x in (params.v, params.v_max_prime, params.v_min,
                                            params.v_max)):
        violations += _check_constraint1(params)
    if sane:
        violations += check_constraint2(tube, params, "Constraint2")
        violations += check_assumption3(tube, params, "Assumption3")
        violations += _check_pothk(obstacles, params)
        if part is None:
            try:
                part = partition(tube, obstacles, params, strict=False,
                                 keep_out=positions if keep_out is None else keep_out)
            except PartitionError as e:
                violations.append(Violation("Partition", f"Partition failed: {e}"))
        if part is not None:
            violations += [_refused(w) for w in part.warnings]
    if positions is not None:
        p = np.asarray(positions, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"positions must have shape (M, 2), got {p.shape}")
        if float(params.r_s) > 0:
            violations += _check_assumption1(tube, obstacles, params, p, part)
    return part, violations


def check_scenario(
    tube: Trapezoid,
    obstacles: Sequence[Obstacle],
    params: ControllerParams,
    positions: np.ndarray | None = None,
) -> Partition:
    """:func:`validate_scenario`, raising :class:`ScenarioError` if anything is violated;
    returns the partition otherwise."""
    part, violations = validate_scenario(tube, obstacles, params, positions)
    if violations:
        raise ScenarioError(violations)
    assert part is not None
    return part


# ----------------------------------------------------------------------------------------------
# Infeasible: what binds, and the nearest single changes that fix it
# ----------------------------------------------------------------------------------------------
#: bisection steps per parameter in :func:`nearest_fixes` (the bracket shrinks 2^-N)
FIX_ITERATIONS = 12
#: The largest step (m) of the scan that moves an obstacle out of a junction
#: (:func:`route_fixes`): a window of working positions at least this wide is found.
MOVE_SCAN_STEP_M = 0.5

#: conditions a change of k_t, r_a, an obstacle's position or the apex distances can fix
_FIXABLE = ("Partition", "Assumption3'", "Constraint3")


@dataclass(frozen=True)
class Fix:
    """One computed change that makes the scenario feasible, the rest unchanged:
    ``parameter`` (``"k_t"``, ``"r_a"``, ``"apex_distance"``, ``"obstacle #4 lateral"``,
    ``"obstacle #4 along n_c"``), ``value`` (the new value, or the move in metres) and
    ``text``, e.g. ``k_t ≤ 2.31``."""

    parameter: str
    value: float
    text: str


def _fixable(violations: Sequence[Violation]) -> bool:
    return bool(violations) and all(
        v.condition in _FIXABLE or (v.condition == "Assumption1" and "triangle" in v.message)
        for v in violations)


def binding_constraints(tube: Trapezoid, obstacles: Sequence[Obstacle],
                        params: ControllerParams, positions: np.ndarray | None = None
                        ) -> list[str]:
    """What binds the partition, one line each: the obstacle whose construction fails and
    why, or the sub-tube and part of Assumption 3' with the smallest margin (and by how much
    it is violated), and the start positions inside triangles (:func:`vtube_fleet.core.plan.
    plan_apex` at the scenario's apex distances, or the planner's best for ``"auto"``)."""
    try:
        plan = plan_apex(tube, obstacles, params, positions, strict=False)
    except (PartitionError, ValueError) as e:  # pragma: no cover - the planner reports
        return [str(e)]
    out = []
    if plan.error:
        out.append(plan.error)
    elif plan.binding is not None:
        out.append(plan.binding.describe())
    if plan.inside:
        out.append(f"{plan.inside} start position(s) inside circumscribed triangles")
    return out


def further_failures(tube: Trapezoid, obstacles: Sequence[Obstacle],
                     params: ControllerParams, positions: np.ndarray | None = None
                     ) -> list[str]:
    """The obstacles that fail *after* the first one, one line each (``obstacle #5 at (33.0,
    0.0) r_o=0.9: the obstacle blocks the tube: …``): the construction stops at the first
    obstacle it cannot split around (:class:`PartitionError`, which :func:`validate_scenario`
    reports); here it is continued without that obstacle, and again without the next one to
    fail, until it builds. So each line holds with the obstacles named before it left out
    (fixing the first may change the rest). Empty when the partition builds, or fails for a
    reason not tied to one obstacle."""
    obstacles = tuple(obstacles)
    left = list(range(len(obstacles)))
    out: list[str] = []
    for n in range(len(obstacles)):
        try:
            partition(tube, [obstacles[i] for i in left], params, strict=False,
                      keep_out=positions)
        except PartitionError as e:
            if e.obstacle is None:
                break
            k = left[e.obstacle]  # the index among the obstacles left → the scenario's
            if n:  # the first failure is the violation already reported
                out.append(f"{obstacle_label(k, obstacles[k])}: {e.reason}")
            left.remove(k)
        except (UserError, ValueError):  # pragma: no cover - reported by validate_scenario
            break
        else:
            break
    return out


def nearest_fixes(tube: Trapezoid, obstacles: Sequence[Obstacle], params: ControllerParams,
                  positions: np.ndarray | None = None, *, r_offset_m: float = 0.0,
                  iterations: int = FIX_ITERATIONS) -> list[Fix]:
    """The nearest single changes that make an infeasible partition feasible, each computed
    on that one parameter with the rest fixed (every value returned was checked with
    :func:`validate_scenario`):

    * ``apex_distance = "auto"`` for every obstacle (when some are fixed);
    * the largest k_t (≥ 1) and the largest r_a (> r_s) that work;
    * the obstacle that binds (:func:`binding_constraints`): the smallest lateral move either
      way (towards the centreline, or towards a leg, where Remark 5 may apply), and the
      smallest move downstream or upstream along n_c (more room between it and its
      neighbour).

    Feasibility need not be monotone along a parameter (an obstacle moved too far hits the
    next one): each search scans from the current value with doubling steps to the first
    feasible value, then bisects between it and the last infeasible one.

    Empty when the scenario is feasible or fails for a reason none of these fix (the main
    tube, Constraint1, robots overlapping one another). ``r_offset_m`` is subtracted from the
    r_a shown (a mission's safety budget δ: ``params`` carry r_a' = r_a + δ)."""
    pos = None if positions is None else np.asarray(positions, dtype=float)
    obstacles = tuple(obstacles)

    def feasible(obs: Sequence[Obstacle], prm: ControllerParams) -> bool:
        try:
            _, v = validate_scenario(tube, obs, prm, pos)
        except UserError:
            return False
        return not v

    _, base = validate_scenario(tube, obstacles, params, pos)
    if not _fixable(base):
        return []

    def bisect(ok_at: float, bad_at: float, works: Callable[[float], bool]) -> float | None:
        return _nearest_working(works, bad_at, ok_at, iterations)

    out: list[Fix] = []
    if any(not isinstance(ob.apex_distance, str) for ob in obstacles):
        auto = tuple(dataclasses.replace(ob, apex_distance=APEX_AUTO) for ob in obstacles)
        if feasible(auto, params):
            out.append(Fix("apex_distance", math.nan,
                           'apex_distance = "auto" (every obstacle; [partition] apex_distance '
                           '= "auto")'))

    def with_params(**kw: float) -> ControllerParams:
        return dataclasses.replace(params, **kw)

    if params.k_t > 1.0:
        k = bisect(1.0, params.k_t, lambda x: feasible(obstacles, with_params(k_t=x)))
        if k is not None:
            k2 = math.floor(k * 100.0) / 100.0
            k = k2 if k2 >= 1.0 and feasible(obstacles, with_params(k_t=k2)) else k
            out.append(Fix("k_t", k, f"k_t ≤ {_num(k, 2)} (now {_num(params.k_t, 2)})"))
    lo_ra = params.r_s * (1.0 + 1e-6) + 1e-9
    if params.r_a > lo_ra:
        r = bisect(lo_ra, params.r_a, lambda x: feasible(obstacles, with_params(r_a=x)))
        if r is not None:
            r2 = math.floor(r * 100.0) / 100.0
            r = r2 if r2 > lo_ra and feasible(obstacles, with_params(r_a=r2)) else r
            out.append(Fix("r_a", r - r_offset_m,
                           f"r_a ≤ {_num(r - r_offset_m, 2)} m (now "
                           f"{_num(params.r_a - r_offset_m, 2)} m)"))

    j = _binding_obstacle(tube, obstacles, params, pos)
    if j is not None:
        out += _obstacle_fixes(tube, obstacles, j, params, feasible, bisect)
    return out


def _binding_obstacle(tube: Trapezoid, obstacles: Sequence[Obstacle], params: ControllerParams,
                      pos: np.ndarray | None) -> int | None:
    try:
        plan = plan_apex(tube, obstacles, params, pos, strict=False)
    except (PartitionError, ValueError):  # pragma: no cover
        return None
    if plan.failed_obstacle is not None:
        return int(plan.failed_obstacle)
    if plan.binding is not None and plan.binding.obstacle is not None:
        return int(plan.binding.obstacle)
    return None


def _obstacle_fixes(tube: Trapezoid, obstacles: tuple[Obstacle, ...], j: int,
                    params: ControllerParams, feasible: Callable[..., bool],
                    bisect: Callable[..., float | None]) -> list[Fix]:
    """Moves of obstacle ``j`` (lateral ±m; along ±n_c)."""
    ob = obstacles[j]
    n_c, m = tube.n_c, tube.m
    xi = float(tube.xi(ob.center))
    centre = 0.5 * (tube.lh(xi) + tube.lr(xi))
    lat = float(m @ (centre - ob.center))  # > 0: the centreline is towards +m
    label = f"obstacle #{j + 1}"

    def moved(d: np.ndarray) -> tuple[Obstacle, ...]:
        return tuple(dataclasses.replace(o, center=o.center + d) if i == j else o
                     for i, o in enumerate(obstacles))

    out: list[Fix] = []
    for sign in (1.0, -1.0):  # +m: towards the right leg
        u = m * sign
        leg = tube.lr(xi) if sign > 0 else tube.lh(xi)
        room = float(u @ (leg - ob.center))
        if room <= 1e-6:
            continue
        d = bisect(room, 0.0, lambda x, u=u: feasible(moved(u * x), params))
        if d is None:
            continue
        d = _round_up(d, lambda x, u=u: feasible(moved(u * x), params))
        toward = sign * lat > 0 and d <= abs(lat) + 1e-9
        where = "the centreline" if toward else ("the right leg" if sign > 0 else "the left leg")
        out.append(Fix(f"{label} lateral", sign * d,
                       f"move {label} {_num(d, 2)} m towards {where}"))
    R = float(ob.radius) + params.r_s
    prev = _previous_obstacle(tube, obstacles, j)
    for sign, word in ((1.0, "downstream"), (-1.0, "upstream")):
        room = (tube.length - R - xi) if sign > 0 else (xi - R)
        if room <= 1e-6:
            continue
        d = bisect(room, 0.0, lambda x, s=sign: feasible(moved(n_c * (s * x)), params))
        if d is None:
            continue
        d = _round_up(d, lambda x, s=sign: feasible(moved(n_c * (s * x)), params))
        text = f"move {label} {_num(d, 2)} m {word}"
        if sign > 0 and prev is not None:
            text += (f" (obstacles #{prev + 1} and #{j + 1} need {_num(d, 2)} m more between "
                     f"them)")
        out.append(Fix(f"{label} along n_c", sign * d, text))
    return out


def _round_up(x: float, works: Callable[[float], bool]) -> float:
    """``x`` rounded up to centimetres if that still works (else ``x``)."""
    r = math.ceil(x * 100.0 - 1e-9) / 100.0
    return r if r != x and works(r) else x


def _previous_obstacle(tube: Trapezoid, obstacles: Sequence[Obstacle], j: int) -> int | None:
    """The obstacle just upstream of ``j`` (largest ξ below j's), if any."""
    xj = float(tube.xi(obstacles[j].center))
    best, bx = None, -math.inf
    for i, o in enumerate(obstacles):
        x = float(tube.xi(o.center))
        if i != j and bx < x <= xj:
            best, bx = i, x
    return best


# ----------------------------------------------------------------------------------------------
# Routes: the paper's conditions per segment, the junction conditions (docs/route.md)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class RouteValidation:
    """What :func:`validate_route` found: the planned ``route`` (None when a segment could not
    be partitioned or the parameters are unusable), every violation, and the junction
    conditions with their margins (one :class:`~vtube_fleet.core.route.JunctionCheck` per
    junction, empty when the route could not be planned)."""

    route: Route | None
    violations: tuple[Violation, ...]
    junctions: tuple[JunctionCheck, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.violations


def validate_route(corridor: Corridor, params: ControllerParams,
                   positions: np.ndarray | None = None, keep_out: np.ndarray | None = None,
                   *, lookahead: bool = False, route: Route | None = None) -> RouteValidation:
    """Check a route: for one segment exactly :func:`validate_scenario`; for several, the
    paper's conditions per segment (Constraint2, Assumption3, its partition with Remark 6's
    planner, Assumption3'/Constraint3 of its sub-tubes; messages name the segment and the
    obstacles by their route numbers), (pothk), Constraint1, the junction conditions
    Junction1–5 and Assumption 1 of ``positions`` each in the segment it starts in.
    ``lookahead``: the route is flown with the apex look-ahead (Junction2 keeps its zones
    clear of the hand-over too). ``route``: the route already planned for these parameters
    (its partitions are not planned again: the fleet at altitude checks the flown positions
    against the route it planned on the ground)."""
    keep = positions if keep_out is None else keep_out
    planned = None if route is None else [s.partition for s in route.segments]
    if corridor.is_single:
        part, violations = validate_scenario(corridor.tube, corridor.obstacles, params,
                                             positions, keep_out,
                                             part=None if planned is None else planned[0])
        if route is None and part is not None:
            route = Route.from_partitions(corridor, params, [part], lookahead=lookahead)
        return RouteValidation(None if part is None else route, tuple(violations))
    violations = _check_parameters(params)
    sane = not violations
    if all(math.isfinite(float(x)) for x in (params.v, params.v_max_prime, params.v_min,
                                            params.v_max)):
        violations += _check_constraint1(params)
    checks: list[JunctionCheck] = []
    if not sane:
        route = None
    else:
        parts: list[Partition | None] = []
        for s, tube in enumerate(corridor.segments):
            label = f"segment S{s + 1}"
            violations += check_constraint2(tube, params, "Constraint2", label)
            violations += check_assumption3(tube, params, "Assumption3", label)
            ids, obs = corridor.segment_obstacles(s)
            if planned is not None:
                parts.append(planned[s])
                violations += [dataclasses.replace(w, message=f"{label}: "
                                                   + renumber_obstacles(w.message, ids))
                               for w in map(_refused, planned[s].warnings)]
                continue
            try:
                part = partition(tube, obs, params, strict=False,
                                 keep_out=segment_keep_out(corridor, s, params, keep))
            except PartitionError as e:
                violations.append(Violation("Partition", (
                    f"Partition failed: {segment_error(s, ids, e, True)}")))
                parts.append(None)
            else:
                violations += [dataclasses.replace(w, message=f"{label}: "
                                                   + renumber_obstacles(w.message, ids))
                               for w in map(_refused, part.warnings)]
                parts.append(part)
        violations += _check_pothk(corridor.obstacles, params)
        violations += obstacle_ownership(corridor, float(params.r_s))
        if route is None and all(p is not None for p in parts):
            route = Route.from_partitions(corridor, params, parts,  # type: ignore[arg-type]
                                          lookahead=lookahead)
        if route is not None:
            checks = junction_checks(route)
            for c in checks:
                violations += list(c.violations)
    if positions is not None:
        p = np.asarray(positions, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"positions must have shape (M, 2), got {p.shape}")
        if float(params.r_s) > 0 and route is not None:
            violations += _check_assumption1(None, route.obstacles, params, p, route, route)
        elif float(params.r_s) > 0:  # no route: each robot in the segment that contains it
            seg = corridor.start_segment_of(p)
            for s, tube in enumerate(corridor.segments):
                rows = np.flatnonzero(seg == s)
                if rows.size:
                    vs = _check_assumption1(tube, corridor.obstacles, params, p[rows], None)
                    violations += [dataclasses.replace(v, message=_renumber_robots(
                        v.message, rows)) for v in vs]
    return RouteValidation(route, tuple(violations), tuple(checks))


def _renumber_robots(text: str, rows: np.ndarray) -> str:
    return re.sub(r"\brobots? (\d+)( and (\d+))?", lambda m: (
        f"robot {rows[int(m.group(1))]}" if m.group(2) is None else
        f"robots {rows[int(m.group(1))]} and {rows[int(m.group(3))]}"), text)


def _refused(w: Violation) -> Violation:
    """A warning of the lenient partition (an obstacle outside the tube, which it skips) as
    the validation reports it: a reason to refuse, so not "ignored"."""
    msg = w.message.removesuffix("; ignored")
    if msg == w.message:
        return w
    return dataclasses.replace(w, message=f"{msg}: move it into the tube or leave it out")


def _nearest_working(works: Callable[[float], bool], bad_at: float, ok_at: float,
                     iterations: int = FIX_ITERATIONS,
                     max_step: float | None = None) -> float | None:
    """The working value between ``bad_at`` and ``ok_at`` (either order) closest to
    ``bad_at``: the first working one of a scan from bad_at towards ok_at (steps doubling from
    1/256 of the range, at most ``max_step`` when given: a working window narrower than the
    steps can be jumped over), then bisection back towards the last failing one (None: nothing
    in the range works). How :func:`nearest_fixes` and :func:`route_fixes` find their values."""
    bad, good, step = bad_at, None, (ok_at - bad_at) / 256.0
    while True:
        x = bad + step if abs(step) < abs(ok_at - bad) else ok_at
        if works(x):
            good = x
            break
        if x == ok_at:
            return None
        bad, step = x, 2.0 * step
        if max_step is not None and abs(step) > max_step:
            step = math.copysign(max_step, step)
    return bisect_edge(works, good, bad, iterations=iterations)


def bisect_edge(works: Callable[[float], bool], good: float, bad: float, *,
                iterations: int | None = None, tol: float | None = None) -> float:
    """The edge between ``good`` (``works`` holds) and ``bad`` (it does not), either order, by
    bisection: the working end after ``iterations`` halvings, or once the interval is at most
    ``tol`` wide. The one bisection of the fixes (:func:`_nearest_working`) and the runtime's
    margins (fleet/margin.py)."""
    if (iterations is None) == (tol is None):
        raise ValueError("bisect_edge needs exactly one of iterations and tol")
    n = 0
    while (n < iterations) if iterations is not None else (abs(bad - good) > tol):
        mid = 0.5 * (good + bad)
        if works(mid):
            good = mid
        else:
            bad = mid
        n += 1
    return good


def _smallest(works: Callable[[float], bool], lo: float, hi: float,
              iterations: int = FIX_ITERATIONS, max_step: float | None = None) -> float | None:
    """The smallest x in (lo, hi] for which ``works`` holds (:func:`_nearest_working`)."""
    return _nearest_working(works, lo, hi, iterations, max_step)


def route_fixes(corridor: Corridor, params: ControllerParams, positions: np.ndarray | None,
                violations: Sequence[Violation], *, r_offset_m: float = 0.0,
                lookahead: bool = False) -> list[Fix]:
    """The nearest single changes that fix a route, each computed and checked on its one
    parameter: for a segment whose partition fails, :func:`nearest_fixes` of that segment
    (with the robots that start in it); for a failed junction condition, the overlap at its
    waypoint (Junction1, Junction4), the binding obstacle moved away from the junction
    (Junction2, Junction5), v'_max (Junction3), or splitting a bend sharper than 90°
    (Junction4)."""
    out: list[Fix] = []
    if corridor.is_single:
        return nearest_fixes(corridor.tube, corridor.obstacles, params, positions,
                             r_offset_m=r_offset_m)
    pos = None if positions is None else np.asarray(positions, dtype=float)
    bad_segments = sorted({int(m.group(1)) - 1 for v in violations
                           if v.condition in _FIXABLE
                           for m in [re.search(r"segment S(\d+)", v.message)] if m})
    seg_of = None if pos is None else corridor.start_segment_of(pos)
    for s in bad_segments:
        ids, obs = corridor.segment_obstacles(s)
        mine = None if pos is None else pos[seg_of == s]
        for f in nearest_fixes(corridor.segments[s], obs, params, mine, r_offset_m=r_offset_m):
            out.append(Fix(f"S{s + 1} " + renumber_obstacles(f.parameter, ids), f.value,
                           f"segment S{s + 1}: " + renumber_obstacles(f.text, ids)))
    conds = {v.condition for v in violations}
    geo = corridor.geometry
    wps = geo.waypoints
    r = float(params.r_s)

    def rebuilt(j_wp: int, **change: float) -> Corridor | None:
        from vtube_fleet.core.route import RouteError, RouteGeometry

        new = list(wps)
        new[j_wp] = dataclasses.replace(new[j_wp], **change)
        try:
            return Corridor(RouteGeometry.from_waypoints(new), corridor.obstacles)
        except RouteError:
            return None

    for jn in geo.junctions:
        j, wp = jn.index, jn.waypoint
        msgs = [v for v in violations if v.condition.startswith("Junction")
                and f"waypoint {wp + 1} " in v.message]
        names = {v.condition for v in msgs}
        if "Junction1" in names and wps:
            w = wps[wp].half_width

            def j1(e: float, wp: int = wp, j: int = j) -> bool:
                c = rebuilt(wp, overlap_m=e)
                if c is None:
                    return False
                s_, mu, _ = handover_line(c.segments[j], c.segments[j + 1], r)
                return s_ is not None and mu >= -1e-9
            e = _smallest(j1, min(jn.prolong_m), max(jn.prolong_m) + 4.0 * w)
            if e is not None:
                e = _round_up(e, j1)
                out.append(Fix(f"waypoint {wp + 1} overlap_m", e,
                               f"overlap_m ≥ {_num(e, 2)} m at waypoint {wp + 1} (now "
                               f"{_num(jn.overlap_m, 2)} m)"))
        if "Junction3" in names:
            # v cos β − v'_max > 0: v'_max below v cos β (Constraint1 keeps holding)
            vp = math.floor((params.v_max_prime + _progress_of(corridor, j, params)) * 100.0
                            - 1e-6) / 100.0
            if vp > 0:
                out.append(Fix("v_max_prime", vp, f"v'_max ≤ {_num(vp, 2)} (now "
                               f"{_num(params.v_max_prime, 2)})"))
        if "Junction4" in names:
            if abs(jn.theta_deg) > 90.0:
                out.append(Fix(f"waypoint {wp + 1} bend", abs(jn.theta_deg), (
                    f"split the {_num(abs(jn.theta_deg), 1)}° bend at waypoint {wp + 1} into "
                    f"two of at most 90° (a waypoint before it, turning half-way)")))
            elif wps and wps[wp].overlap_m is not None:
                mitre = rebuilt(wp, overlap_m=None)
                e = 0.0 if mitre is None else min(mitre.junctions[j].prolong_m)
                out.append(Fix(f"waypoint {wp + 1} overlap_m", e, (
                    f"leave overlap_m out at waypoint {wp + 1} (the mitre, "
                    f"{mitre.junctions[j].overlap_text() if mitre else '?'}; now "
                    f"{_num(jn.overlap_m, 2)} m)")))
        for v in msgs:
            if v.condition not in ("Junction2",):
                continue
            m = re.search(r"obstacle #(\d+)", v.message)
            if m:
                out += _move_obstacle_fix(corridor, params, int(m.group(1)) - 1, jn, pos,
                                          lookahead, "Junction2")
    if "Junction5" in conds:
        done = set()
        for v in violations:
            if v.condition != "Junction5":
                continue
            m = re.search(r"obstacle #(\d+)", v.message)
            if m and int(m.group(1)) not in done:
                done.add(int(m.group(1)))
                i = int(m.group(1)) - 1
                own = corridor.owner[i]
                jn = min(geo.junctions, key=lambda q: float(np.hypot(
                    *(q.center - corridor.obstacles[i].center))))
                out += _move_obstacle_fix(corridor, params, i, jn, pos, lookahead,
                                          "Junction5", own)
    return out


def _progress_of(corridor: Corridor, j: int, params: ControllerParams) -> float:
    from vtube_fleet.core.route import progress_speed

    return progress_speed(corridor.segments[j + 1], params)


def _move_obstacle_fix(corridor: Corridor, params: ControllerParams, i: int, jn: Any,
                       pos: np.ndarray | None, lookahead: bool, cond: str,
                       own: int | None = None) -> list[Fix]:
    """Obstacle ``i`` moved along its segment's n_c away from junction ``jn`` (downstream if
    it is in the segment after it, upstream otherwise) by the least distance that clears
    ``cond`` at that junction and keeps every segment partitioned."""
    own = corridor.owner[i] if own is None else own
    tube = corridor.segments[own]
    ob = corridor.obstacles[i]
    sign = 1.0 if own > jn.index else -1.0
    xi = float(tube.xi(ob.center))
    room = (tube.length - xi) if sign > 0 else xi
    if room <= 1e-6:
        return []

    def works(d: float) -> bool:
        obs = tuple(dataclasses.replace(o, center=o.center + tube.n_c * (sign * d))
                    if k == i else o for k, o in enumerate(corridor.obstacles))
        c = corridor.with_obstacles(obs)
        try:
            res = validate_route(c, params, None, pos, lookahead=lookahead)
        except UserError:
            return False
        return not any(v.condition == cond or v.condition == "Partition"
                       for v in res.violations)

    # the obstacle's triangle must clear the junction and still fit before the segment's end:
    # the positions that work are a window, which a doubling scan can jump over
    d = _smallest(works, 0.0, room, max_step=MOVE_SCAN_STEP_M)
    if d is None:
        return []
    d = _round_up(d, works)
    word = "downstream" if sign > 0 else "upstream"
    return [Fix(f"obstacle #{i + 1} along n_c", sign * d,
                f"move obstacle #{i + 1} {_num(d, 2)} m {word} (out of the junction at "
                f"waypoint {jn.waypoint + 1})")]
