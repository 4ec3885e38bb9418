"""Routes (docs/route.md): the geometry of chained trapezoids, the junction conditions, the
route format in scenario and mission files, the switching rule with hand-overs, and the
simulator flying a route."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtube_fleet.cli import main
from vtube_fleet.config.scenario import load_scenario, parse_scenario
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.partition import partition
from vtube_fleet.core.route import (
    Corridor,
    Route,
    RouteError,
    RouteGeometry,
    Waypoint,
    junction_checks,
)
from vtube_fleet.core.tube import Obstacle, Trapezoid
from vtube_fleet.core.validation import route_fixes, validate_route
from vtube_fleet.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
ROUTE_MOCK = ROOT / "configs" / "route_mock.toml"
PAPER_ROUTE = ROOT / "configs" / "paper_route.toml"
SITL_ROUTE = ROOT / "configs" / "px4_sitl_route.toml"

#: the mock fleet's vehicles (configs/mock_fleet.toml), physical radii
MOCK = ControllerParams(r_s=0.3, r_a=1.0, v_min=0.3, v_max=1.6, v=1.0, v_max_prime=0.5)
#: the paper's (Section V-A)
PAPER = ControllerParams(r_s=0.25, r_a=0.5, v_min=0.5, v_max=3.5, v=2.0, v_max_prime=1.5)


def bend(deg: float, w: float = 10.0, length: float = 30.0, **wp2: Any) -> RouteGeometry:
    """Two segments of ``length`` and half-width ``w``: along x, then turning ``deg`` (left)."""
    th = math.radians(deg)
    c1 = np.array([length, 0.0])
    return RouteGeometry.from_waypoints([
        Waypoint(np.array([0.0, 0.0]), w), Waypoint(c1, w, **wp2),
        Waypoint(c1 + length * np.array([math.cos(th), math.sin(th)]), w)])


def checks(geo: RouteGeometry, params: ControllerParams = MOCK, obstacles=()):
    return junction_checks(Route.plan(Corridor(geo, tuple(obstacles)), params))


# ----------------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------------
def test_two_waypoints_are_the_trapezoid_between_their_base_lines() -> None:
    geo = RouteGeometry.from_waypoints([Waypoint(np.array([0.0, 0.0]), 10.0),
                                        Waypoint(np.array([40.0, 0.0]), 10.0)])
    (t,) = geo.segments
    for got, want in ((t.p_h0, [0, 10]), (t.p_h1, [40, 10]), (t.p_r0, [0, -10]),
                      (t.p_r1, [40, -10])):
        np.testing.assert_array_equal(got, want)
    assert not geo.junctions and geo.is_single
    # a heading makes an oblique trapezoid: the bases perpendicular to it, not to c0 → c1
    geo = RouteGeometry.from_waypoints([Waypoint(np.array([0.0, 0.0]), 2.0, heading=0.0),
                                        Waypoint(np.array([10.0, 3.0]), 1.0)])
    (t,) = geo.segments
    np.testing.assert_allclose(t.n_c, [1, 0], atol=1e-15)
    np.testing.assert_allclose([t.p_h1, t.p_r1], [[10, 4], [10, 2]])


@pytest.mark.parametrize("deg", [-75.0, -30.0, 15.0, 45.0, 60.0, 89.0])
def test_a_bend_is_mitred(deg: float) -> None:
    """Both segments are prolonged by w tan(|θ|/2) along their legs: they meet at the outer
    corner of the corridor, and their union is the corridor with a mitred corner."""
    geo = bend(deg)
    a, b = geo.segments
    (jn,) = geo.junctions
    e = 10.0 * math.tan(abs(math.radians(deg)) / 2)
    assert jn.prolong_m == pytest.approx((e, e)) and jn.theta_deg == pytest.approx(deg)
    assert a.length == pytest.approx(30 + e) and b.length == pytest.approx(30 + e)
    # the outer corner is shared: a's prolonged finishing base and b's prolonged start base
    outer_a, outer_b = (a.p_r1, b.p_r0) if deg > 0 else (a.p_h1, b.p_h0)
    np.testing.assert_allclose(outer_a, outer_b, atol=1e-9)
    left, right = geo.mitre_corners(0)
    np.testing.assert_allclose(right if deg > 0 else left, outer_a, atol=1e-9)


@pytest.mark.parametrize(("wps", "match"), [
    ([((0, 0), 5)], "at least 2 waypoints"),
    ([((0, 0), 5), ((0, 0), 5)], "waypoints 1 and 2 coincide"),
    ([((0, 0), 5, 180.0), ((10, 0), 5)], "waypoint 2 is not ahead of waypoint 1"),
    ([((0, 0), 5), ((10, 0), 5, 30.0)], "waypoint 2 \\(the finishing line\\): heading 30.0°"),
    ([((0, 0), 5), ((10, 0), 5), ((0, 1), 5)], "a bend of 174.3° is refused"),
])
def test_waypoints_that_make_no_route_are_refused(wps: list, match: str) -> None:
    def wp(item: tuple) -> Waypoint:
        h = math.radians(item[2]) if len(item) > 2 else None
        return Waypoint(np.array(item[0], float), item[1], h)

    with pytest.raises(RouteError, match=match):
        RouteGeometry.from_waypoints([wp(x) for x in wps])


@pytest.mark.parametrize(("pts", "w", "match"), [
    # a spiral: S4 flies back down through S1
    ([(0, 0), (40, 0), (40, 30), (20, 30), (20, -20)], 10.0,
     r"segments S1 \(waypoints 1 → 2\) and S4 \(waypoints 4 → 5\) overlap: 400.0 m² of "
     r"corridor around \(20.0, 0.0\)"),
    # a U-turn whose legs come closer than the corridor is wide: S1 and S3 share a 2 m strip
    ([(0, 0), (40, 0), (40, 14), (0, 14)], 8.0,
     r"segments S1 \(waypoints 1 → 2\) and S3 \(waypoints 3 → 4\) overlap: .* must not "
     r"cross or fold back onto itself"),
])
def test_a_route_that_crosses_or_folds_onto_itself_is_refused(pts: list, w: float,
                                                               match: str) -> None:
    """Found: check called a route valid whose fourth segment crossed its first (a vehicle
    flying S4 knows neither S1's legs nor its obstacles)."""
    with pytest.raises(RouteError, match=match):
        RouteGeometry.from_waypoints([Waypoint(np.array(p, float), w) for p in pts])
    # the same U-turn with room between its legs is a route
    RouteGeometry.from_waypoints([Waypoint(np.array(p, float), 8.0)
                                  for p in [(0, 0), (40, 0), (40, 17), (0, 17)]])


# ----------------------------------------------------------------------------------------------
# the junction conditions
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("deg", [10.0, 30.0, 45.0, 60.0, 80.0, 90.0])
def test_the_handover_margin_at_a_bend_is_the_formula(deg: float) -> None:
    """docs/route.md: with the mitre, the best hand-over line leaves every vehicle lane
    min((w − r_s)(1 − cos θ), r_s (1 − cos θ)/cos θ) beyond r_s inside the next segment."""
    (c,) = checks(bend(deg))
    th, w, r = math.radians(deg), 10.0, MOCK.r_s
    want = (w - r) * (1 - abs(math.cos(th)))
    if math.cos(th) > 1e-12:
        want = min(want, r * (1 - math.cos(th)) / math.cos(th))
    assert c.ok, c.violations
    assert c.handover_margin_m == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert c.progress_m_s == pytest.approx(MOCK.v - MOCK.v_max_prime)
    assert c.command_jump_m_s == pytest.approx(2 * MOCK.v * math.sin(th / 2))
    assert c.corridor_margin_m >= -1e-9


def test_a_60_degree_bend_is_flyable_with_the_flown_radii() -> None:
    """The shipped mock route's 60° bend, checked as the fleet flies it (r_s' ≈ 1.93 m)."""
    flown = ControllerParams(r_s=1.93, r_a=2.63, v_min=0.3, v_max=1.6, v=1.0, v_max_prime=0.5)
    (c,) = checks(bend(60.0), flown)
    assert c.ok and c.handover_margin_m == pytest.approx(1.93)  # r_s'(1 − cos 60°)/cos 60°


def test_a_bend_sharper_than_90_degrees_is_refused_with_numbers_and_a_fix() -> None:
    corridor = Corridor(bend(120.0))
    res = validate_route(corridor, MOCK)
    (v,) = res.violations
    assert v.condition == "Junction4"
    assert "waypoint 2 (S1 → S2): the overlap of S2 reaches 10.0 m outside S1's part" in \
        v.message and "bend 120.0°" in v.message
    fixes = route_fixes(corridor, MOCK, None, res.violations)
    assert [f.text for f in fixes] == [
        "split the 120.0° bend at waypoint 2 into two of at most 90° (a waypoint before it, "
        "turning half-way)"]
    # the fix works: two bends of 60°
    c1, c2 = np.array([30.0, 0.0]), np.array([30.0 + 20 * math.cos(math.pi / 3),
                                              20 * math.sin(math.pi / 3)])
    c3 = c2 + 30.0 * np.array([math.cos(2 * math.pi / 3), math.sin(2 * math.pi / 3)])
    geo = RouteGeometry.from_waypoints([Waypoint(np.array([0.0, 0.0]), 10.0),
                                        Waypoint(c1, 10.0), Waypoint(c2, 10.0),
                                        Waypoint(c3, 10.0)])
    assert [round(j.theta_deg, 9) for j in geo.junctions] == [60.0, 60.0]
    assert validate_route(Corridor(geo), MOCK).ok


def test_a_junction_without_overlap_is_refused_with_the_overlap_it_needs() -> None:
    corridor = Corridor(bend(60.0, overlap_m=0.0))
    res = validate_route(corridor, MOCK)
    assert [v.condition for v in res.violations] == ["Junction1"]
    msg = res.violations[0].message
    assert msg.startswith("Junction1 violated at waypoint 2 (S1 → S2): no line across S1 "
                          "reaches into S2's entry region")
    fixes = route_fixes(corridor, MOCK, None, res.violations)
    (fix,) = fixes
    assert fix.parameter == "waypoint 2 overlap_m" and fix.text.startswith("overlap_m ≥ ")
    # the value printed works, and a little less does not (it is the nearest)
    ok = validate_route(Corridor(bend(60.0, overlap_m=fix.value)), MOCK)
    assert not [v for v in ok.violations if v.condition == "Junction1"]
    short = validate_route(Corridor(bend(60.0, overlap_m=fix.value - 0.05)), MOCK)
    assert [v.condition for v in short.violations] == ["Junction1"]


def test_an_obstacle_too_close_to_a_junction_is_refused_and_moved() -> None:
    """Junction2: the next segment's triangle may not reach into where vehicles hand over;
    the fix moves the obstacle downstream by the least that works."""
    geo = bend(60.0)
    b = geo.segments[1]
    # 14.5 m past the waypoint on S2's centreline: clear of S1 (Junction5), but its triangle
    # (h = 1.3 h_min = 4.8 m) reaches back to where vehicles enter S2
    ob = Obstacle(geo.junctions[0].center + b.n_c * 14.5, 1.5)
    corridor = Corridor(geo, (ob,))
    assert corridor.owner == (1,)
    res = validate_route(corridor, MOCK)
    assert [v.condition for v in res.violations] == ["Junction2"]
    assert "the triangle of obstacle #1 (S2) reaches into the hand-over region by" in \
        res.violations[0].message
    fixes = route_fixes(corridor, MOCK, None, res.violations)
    (fix,) = fixes
    assert fix.text.startswith("move obstacle #1 ") and "m downstream" in fix.text
    moved = Corridor(geo, (Obstacle(ob.center + b.n_c * fix.value, 1.5),))
    assert validate_route(moved, MOCK).ok


def test_the_move_out_of_a_junction_finds_a_narrow_window() -> None:
    """Found: an obstacle 12 m past a 45° bend, flown with a mission's radii and the apex
    look-ahead, works only moved 14.8–20 m downstream (nearer, its triangle and look-ahead zone
    reach into the hand-over; further, the tube after it is too short). The scan with doubling
    steps tried 13.9 m, then the end of the segment, and printed no fix at all; the violation
    said 11.253 m."""
    flown = ControllerParams(r_s=2.043, r_a=2.743, v_min=0.3, v_max=1.6, v=1.0,
                             v_max_prime=0.5)
    geo = bend(45.0, length=40.0)
    b = geo.segments[1]
    ob = Obstacle(geo.junctions[0].center + b.n_c * 12.0, 0.5)
    corridor = Corridor(geo, (ob,))
    res = validate_route(corridor, flown, lookahead=True)
    assert [v.condition for v in res.violations] == ["Junction2"]
    (fix,) = route_fixes(corridor, flown, None, res.violations, lookahead=True)
    assert fix.text.startswith("move obstacle #1 ") and "m downstream" in fix.text
    assert 14.0 < fix.value < 16.0
    # the violation says how far the triangle and its look-ahead zone reach in: the move needed
    # (it said 11.253 m: the zone as cut at S2's start)
    reach = float(re.search(r"reaches into the hand-over region by ([\d.]+) m",
                            res.violations[0].message).group(1))
    assert reach == pytest.approx(fix.value, abs=0.02)
    moved = Corridor(geo, (Obstacle(ob.center + b.n_c * fix.value, 0.5),))
    assert validate_route(moved, flown, lookahead=True).ok


@pytest.mark.parametrize(("pts", "widths", "why"), [
    # 6 m segments between 20° bends: the mitres at both ends of S2 leave it too little room
    ([(0, 0), (15, 0), (20.638, 2.052), (25.235, 5.909), (28.235, 11.105)], [10.0] * 5,
     "S2 is too short for the bends at both its ends: the overlap reaches 0.618 m past its "
     "other end; lengthen S2 or make the bends gentler"),
    # a 90° bend where the corridor narrows: its legs meet at more than 90°
    ([(0, 0), (40, 0), (40, 40)], [8.0, 10.0, 8.0],
     "the legs meet at more than 90° where the corridor's width changes at the bend"),
    ([(0, 0), (40, 0), (20, 34.641)], [10.0] * 3,
     "beyond 90° the prolonged segments leave the corridor"),
])
def test_junction4_says_why_the_overlap_leaves_the_corridor(pts: list, widths: list,
                                                            why: str) -> None:
    """Found: a chain of short segments with 20° bends was refused 'beyond 90° or with an
    overlap_m above the mitre', neither of which it had."""
    geo = RouteGeometry.from_waypoints([Waypoint(np.array(p, float), w)
                                        for p, w in zip(pts, widths, strict=True)])
    msgs = [v.message for c in checks(geo) for v in c.violations if v.condition == "Junction4"]
    assert msgs and why in msgs[0], msgs


def test_an_obstacle_in_a_junction_belongs_to_no_single_segment() -> None:
    geo = bend(60.0)
    centre = geo.junctions[0].center  # in both prolonged segments
    res = validate_route(Corridor(geo, (Obstacle(centre, 0.5),)), MOCK)
    assert any(v.condition == "Junction5" and "lies in the overlap of S1 and S2" in v.message
               for v in res.violations)


def test_progress_condition_names_v_max_prime() -> None:
    """Junction3: v cos β − v'_max > 0 in the next segment (β its steepest narrowing leg)."""
    p = ControllerParams(r_s=0.3, r_a=1.0, v_min=0.0, v_max=2.0, v=1.0, v_max_prime=1.0)
    corridor = Corridor(bend(45.0))
    res = validate_route(corridor, p)
    assert [v.condition for v in res.violations] == ["Junction3"]
    fix = route_fixes(corridor, p, None, res.violations)
    assert [f.text for f in fix] == ["v'_max ≤ 0.99 (now 1.0)"]


# ----------------------------------------------------------------------------------------------
# the format
# ----------------------------------------------------------------------------------------------
def test_a_tube_is_a_one_segment_route() -> None:
    sc = load_scenario(ROOT / "configs" / "paper.toml")
    assert sc.corridor.S == 1 and not sc.is_route and sc.corridor.tube is sc.tube
    route = Route.plan(sc.corridor, sc.controller, keep_out=sc.robots.positions)
    part = partition(sc.tube, sc.obstacles, sc.controller, keep_out=sc.robots.positions)
    assert route.sub_tubes == route.segments[0].partition.sub_tubes and route.K == part.K
    for a, b in zip(route.sub_tubes, part.sub_tubes, strict=True):
        np.testing.assert_array_equal(a.polygon(), b.polygon())
    p = np.random.default_rng(0).uniform([-2, -10], [35, 10], size=(500, 2))
    np.testing.assert_array_equal(route.locate(p)[1], part.locate(p))
    np.testing.assert_array_equal(route.finished(p), sc.tube.finished(p, sc.controller.eps_0))


def _route_doc(**extra: Any) -> dict[str, Any]:
    doc = {
        "route": {"waypoints": [{"position": [0.0, 0.0], "half_width": 10.0},
                                {"position": [40.0, 0.0], "half_width": 10.0},
                                {"position": [55.0, 25.980762], "half_width": 10.0}]},
        "robots": {"r_s": 0.3, "r_a": 1.0, "v_min": 0.3, "v_max": 1.6,
                   "positions": [[3.0, 0.0]]},
        "controller": {"v": 1.0, "v_max_prime": 0.5},
    }
    doc.update(extra)
    return doc


def test_route_waypoints_in_metres_and_in_latitude_longitude_agree() -> None:
    mission = {"origin_lat_deg": 47.397742, "origin_lon_deg": 8.545594, "origin_alt_m": 488.0,
               "heading_deg": 30.0, "altitude_m": 3.0}
    metres = parse_scenario(_route_doc(mission=mission), "m.toml", extra_sections=("mission",))
    from vtube_fleet.frames import TubeFrame

    frame = TubeFrame(47.397742, 8.545594, 488.0, 30.0)
    doc = _route_doc(mission=mission)
    for w in doc["route"]["waypoints"]:
        lat, lon, _ = frame.tube_to_geodetic(*w.pop("position"), 0.0)
        w["lat_lon"] = [float(lat), float(lon)]
    geo = parse_scenario(doc, "g.toml", extra_sections=("mission",))
    for a, b in zip(metres.geometry.segments, geo.geometry.segments, strict=True):
        np.testing.assert_allclose(a.polygon(), b.polygon(), atol=1e-6)
    # a compass bearing is the frame heading turned: 30° − bearing (x at compass 30°)
    doc = _route_doc(mission=mission)
    doc["route"]["waypoints"][0]["bearing_deg"] = 30.0  # = along x
    sc = parse_scenario(doc, "b.toml", extra_sections=("mission",))
    np.testing.assert_allclose(sc.geometry.segments[0].n_c, [1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize(("edit", "pattern"), [
    (lambda d: d.update(tube={"p_h0": [0, 1], "p_h1": [1, 1], "p_r0": [0, 0], "p_r1": [1, 0]}),
     r"\[route\]: give either \[tube\] \(one trapezoid\) or \[route\] \(waypoints\), not both"),
    (lambda d: d["route"]["waypoints"][1].pop("half_width"),
     r"\[\[route.waypoints\]\]\[1\]\.half_width: missing required key"),
    (lambda d: d["route"]["waypoints"][1].update(lat_lon=[47.0, 8.0]),
     r"\[\[route.waypoints\]\]\[1\]: give exactly one of position"),
    (lambda d: d["route"]["waypoints"][1].update(overlap_m=-1.0),
     r"\[\[route.waypoints\]\]\[1\]\.overlap_m: must be >= 0, got -1\.0"),
    (lambda d: d["route"]["waypoints"][0].update(wind=3),
     r"\[\[route.waypoints\]\]\[0\]\.wind: unknown key \(allowed: position, lat_lon, "),
    (lambda d: d["route"].update(waypoints=d["route"]["waypoints"][:1]),
     r"\[route\]\.waypoints: a route needs 2 to 100 waypoints, got 1"),
    (lambda d: d["route"]["waypoints"][2].update(position=[40.0, 0.0]),
     r"\[route\]: waypoints 2 and 3 coincide"),
])
def test_bad_routes_are_refused_naming_the_key(edit: Any, pattern: str) -> None:
    doc = _route_doc()
    edit(doc)
    with pytest.raises(ConfigError, match=pattern):
        parse_scenario(doc, "r.toml")


def test_latitude_longitude_need_a_mission_anchor() -> None:
    doc = _route_doc()
    w = doc["route"]["waypoints"][1]
    w.pop("position")
    w["lat_lon"] = [47.4, 8.5]
    with pytest.raises(ConfigError, match=r"r\.toml: \[\[route.waypoints\]\]\[1\]\.lat_lon: "
                                          r"latitude/longitude need the geodetic anchor of a "
                                          r"\[mission\] table"):
        parse_scenario(doc, "r.toml")


def test_a_route_scenario_refuses_where_one_tube_is_expected() -> None:
    sc = parse_scenario(_route_doc(), "r.toml")
    assert sc.is_route and sc.corridor.S == 2
    with pytest.raises(RouteError, match="this is a route of 2 segments, not one trapezoid"):
        _ = sc.tube


# ----------------------------------------------------------------------------------------------
# the switching rule over a route: hand-overs
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def paper_route() -> Route:
    sc = load_scenario(PAPER_ROUTE)
    res = validate_route(sc.corridor, sc.controller, sc.robots.positions)
    assert res.ok, res.violations
    return res.route


_POINTS = st.lists(st.tuples(st.floats(-5.0, 70.0), st.floats(-12.0, 36.0)), min_size=1,
                   max_size=40)


@settings(max_examples=60, deadline=None)
@given(pts=_POINTS, seg0=st.lists(st.integers(0, 2), min_size=40, max_size=40))
def test_locate_hands_over_forward_only_into_the_next_segments_entry(
        paper_route: Route, pts: list, seg0: list) -> None:
    route = paper_route
    p = np.array(pts, dtype=float)
    cur = np.array(seg0[: len(p)], dtype=np.intp)
    seg, k = route.locate(p, cur)
    assert (seg >= cur).all()
    assert (route.segment_of[k] == seg).all()  # the sub-tube is one of its segment's
    r_s = route.params.r_s
    for i in np.flatnonzero(seg > cur):
        t = route.segments[int(seg[i])].tube
        deep = r_s + route.handover_depths[int(seg[i]) - 1]  # r_s + μ/2 of the junction
        assert t.d_Th(p[i]) > deep and t.d_Tr(p[i]) > deep and -1e-9 <= t.xi(p[i]) <= t.length
        sub = route.sub_tubes[int(k[i])]
        assert sub.d_Th(p[i]) > r_s and sub.d_Tr(p[i]) > r_s
    # no further hand-over is due at the same points (locate is idempotent)
    again, k2 = route.locate(p, seg)
    np.testing.assert_array_equal(again, seg)
    np.testing.assert_array_equal(k2, k)
    # the segment's own sub-tube: the §5 rule of its partition
    for i in range(len(p)):
        s = route.segments[int(seg[i])]
        assert k[i] == s.offset + int(s.partition.locate(p[i]))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30))
def test_the_tracker_is_locate_along_random_walks(paper_route: Route, seed: int,
                                                  n: int) -> None:
    """RouteTracker (the simulator's incremental form) gives exactly locate's sub-tubes and
    segments along walks, with exits (keep) on the way; follow() replays the same."""
    rng = np.random.default_rng(seed)
    route = paper_route
    p = rng.uniform([0, -6], [8, 6], size=(n, 2))
    tr = route.tracker(p)
    seg = route.start_segments(p)
    np.testing.assert_array_equal(tr.segment, seg)
    path = [p.copy()]
    step = 0.4
    target = route.segments[-1].tube.p_h1 * 0.5 + route.segments[-1].tube.p_r1 * 0.5
    for it in range(260):
        d = target - p
        mv = step * (0.6 * d / np.linalg.norm(d, axis=1)[:, None]
                     + 0.4 * rng.normal(size=p.shape))
        norm = np.linalg.norm(mv, axis=1)[:, None]
        p = p + mv * np.minimum(1.0, 1.5 * step / norm)  # (update's promise: no point moves
        k = tr.update(p, 1.5 * step)                      # farther than 1.5 step per call)
        seg, k_ref = route.locate(p, seg)
        np.testing.assert_array_equal(k, k_ref)
        np.testing.assert_array_equal(tr.segment, seg)
        path.append(p.copy())
        if it == 130 and n > 1:  # one robot leaves
            keep = np.ones(len(p), bool)
            keep[0] = False
            tr.keep(keep)
            p, seg = p[keep], seg[keep]
            path = [q[keep] for q in path]
    np.testing.assert_array_equal(route.follow(np.array(path))[-1], seg)


def test_finished_is_the_last_finishing_line_of_the_last_segment(paper_route: Route) -> None:
    route = paper_route
    last = route.segments[-1].tube
    beyond = (last.p_h1 + last.p_r1) / 2 + last.n_c
    p = np.array([beyond, beyond])
    np.testing.assert_array_equal(route.finished(p, np.array([2, 1])), [True, False])
    with pytest.raises(ValueError, match="needs the points' segments"):
        route.finished(p)


def test_with_lost_replans_only_the_segments_the_lost_obstacle_meets(paper_route: Route) -> None:
    route = paper_route
    calls = []

    def replan(tube: Trapezoid, fixed: Any, lost: Any, params: Any) -> Any:
        calls.append((tube.name, len(fixed), len(lost)))
        return partition(tube, tuple(fixed) + tuple(lost), params)

    s2 = route.segments[1].tube
    in_s2 = Obstacle(s2.p_h0 + s2.n_c * 22.0 + s2.m * 6.0, 0.75)  # 22 m into S2, centred
    new = route.with_lost([in_s2], replan=replan)
    assert calls == [("S2", 1, 1)]
    assert new.segments[0].partition is route.segments[0].partition
    assert new.segments[2].partition is route.segments[2].partition
    assert new.segments[1].obstacle_ids == (2, 5)  # its configured #3, then the lost one
    assert [t.obstacle for t in new.triangles] == [0, 1, 2, 3, 4, 5]
    # one stopped in the junction's overlap belongs to both segments
    calls.clear()
    jn = route.corridor.junctions[0]
    new = route.with_lost([Obstacle(jn.center, 0.75)], replan=lambda *a: replan(*a))
    assert [c[0] for c in calls] == ["S1", "S2"]


# ----------------------------------------------------------------------------------------------
# the simulator and the record
# ----------------------------------------------------------------------------------------------
def test_a_one_segment_route_flies_exactly_as_its_tube() -> None:
    tube_doc = {"tube": {"p_h0": [0.0, 10.0], "p_h1": [40.0, 10.0], "p_r0": [0.0, -10.0],
                         "p_r1": [40.0, -10.0]},
                "obstacles": [{"center": [22.0, 0.0], "radius": 0.5}],
                "robots": {"r_s": 0.3, "r_a": 1.0, "v_min": 0.3, "v_max": 1.6,
                           "grid": {"origin": [3.0, -6.75], "rows": 3, "cols": 4,
                                    "spacing": 4.5}},
                "controller": {"v": 1.0, "v_max_prime": 0.5}}
    route_doc = json.loads(json.dumps(tube_doc))
    del route_doc["tube"]
    route_doc["route"] = {"waypoints": [{"position": [0.0, 0.0], "half_width": 10.0},
                                        {"position": [40.0, 0.0], "half_width": 10.0}]}
    from vtube_fleet.sim import simulate

    a = simulate(parse_scenario(tube_doc), dt=0.01, duration=8.0)
    b = simulate(parse_scenario(route_doc), dt=0.01, duration=8.0)
    np.testing.assert_array_equal(a.pos, b.pos)
    np.testing.assert_array_equal(a.vel, b.vel)
    for key, val in a.metrics.as_dict().items():
        np.testing.assert_array_equal(val, getattr(b.metrics, key, b.metrics.as_dict()[key]))


#: A short route for the simulator and its recording: 12 robots packed closer than r_s + r_a
#: (so every pair metric is in range), a 45° bend, an obstacle in each segment.
SIM_ROUTE = {
    "route": {"waypoints": [{"position": [0.0, 5.0], "half_width": 5.0},
                            {"position": [18.0, 5.0], "half_width": 5.0},
                            {"position": [30.727922, 17.727922], "half_width": 4.5}]},
    "obstacles": [{"center": [11.0, 5.5], "radius": 0.6},
                  {"center": [26.27, 15.11], "radius": 0.6}],
    "partition": {"apex_distance": "auto"},
    "robots": {"r_s": 0.2, "r_a": 0.6, "v_min": 0.5, "v_max": 3.5,
               "grid": {"origin": [0.8, 3.9], "rows": 3, "cols": 4, "spacing": 0.75}},
    "controller": {"v": 2.0, "v_max_prime": 1.5},
    "sim": {"dt": 0.01, "duration": 25.0, "record_every": 1},
}


@pytest.fixture(scope="module")
def route_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    from vtube_fleet.recording.writer import open_recorder
    from vtube_fleet.sim import simulate

    sc = parse_scenario(json.loads(json.dumps(SIM_ROUTE)), "sim_route.toml")
    assert validate_route(sc.corridor, sc.controller, sc.robots.positions).ok
    out = tmp_path_factory.mktemp("route")
    with open_recorder(out / "recording.rrd", kind="sim", decimate=1) as rec:
        result = simulate(sc, recorder=rec)
    return result, out / "recording.rrd"


def test_the_simulator_flies_a_route_safely(route_run: tuple[Any, Path]) -> None:
    result, _ = route_run
    s = result.summary
    r = result.scenario.robots
    assert s["exited"] == s["robots"] == 12 and s["segments"] == 2
    assert s["violations"] == 0, s["violations_by_condition"]
    assert r.v_min - 1e-9 <= s["min_speed_m_s"] <= s["max_speed_m_s"] <= r.v_max + 1e-9
    assert s["min_pair_distance_m"] > 2 * r.r_s
    assert min(s["min_left_leg_distance_m"], s["min_right_leg_distance_m"]) > r.r_s
    assert s["sub_tubes"] == result.route.K and len(s["apex_distances_m"]) == 2
    # every robot crossed the route's last finishing line: the last segment's
    last = result.route.segments[-1].tube
    for i in range(12):
        xs = result.pos[:, i][np.isfinite(result.pos[:, i, 0])]
        assert last.n_c @ xs[-1] >= last.finish_threshold(0.01) - 2 * 3.5 * 0.01
    # the leg distance judged is to each robot's own segment: recomputed from the
    # trajectory with the segments it flew (follow), the run's own minima
    from vtube_fleet.core.metrics import SafetyMonitor

    seg = result.route.follow(result.pos)
    d = [result.route.leg_distances(result.pos[f], seg[f]) for f in range(len(result.t))]
    left = np.nanmin([np.nanmin(x[0]) if np.isfinite(x[0]).any() else np.inf for x in d])
    assert left == pytest.approx(s["min_left_leg_distance_m"], abs=1e-12)
    first_only = SafetyMonitor.from_params(result.route.segments[0].tube, (), result.route.params)
    assert first_only.evaluate(result.pos).min_left_leg_distance_m.min() < 0  # S2 is elsewhere


def test_the_recording_and_review_of_a_route_agree_with_the_run(
        route_run: tuple[Any, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    from vtube_fleet.recording.reader import load_recording
    from vtube_fleet.recording.review import review

    result, path = route_run
    d = load_recording(path)
    assert len(d.meta["route"]["segments"]) == 2 and d.meta["route"]["junctions"][0][
        "theta_deg"] == pytest.approx(45.0)
    assert d.static_rows.get("world/junctions", 0) >= 1
    corridor = d.corridor()
    for a, b in zip(corridor.segments, result.route.corridor.segments, strict=True):
        np.testing.assert_array_equal(a.polygon(), b.polygon())
    res = review(path, out_dir=tmp_path)
    assert not res.differences, res.differences
    assert res.verdict.safe
    assert (tmp_path / "recording-trajectories.png").exists()
    assert main(["review", str(path), "--no-plots"]) == 0
    assert "matches the run's own summary" in capsys.readouterr().out


def test_check_and_sim_accept_the_shipped_routes(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """configs/route_mock.toml (a mission: checked with the flown radii of its budget) and
    configs/px4_sitl_route.toml are valid; check prints every segment's partition and every
    junction's conditions."""
    for path in (ROUTE_MOCK, SITL_ROUTE):
        assert main(["check", str(path)]) == 0
        out = capsys.readouterr().out
        assert "\nvalid\nmargin: valid up to L ≤ " in out, out
        assert "flown: r_s' = " in out and "junctions:" in out and "[Junction1]" in out
    out_dir = tmp_path / "sim"
    rc = main(["sim", str(SITL_ROUTE), "--out", str(out_dir), "--dt", "0.01", "--no-rerun",
               "--no-plots", "--quiet"])
    assert rc == 0
    s = json.loads((out_dir / "summary.json").read_text())
    assert s["exited"] == 3 and s["violations"] == 0 and s["segments"] == 2


def test_check_refuses_a_failing_junction_with_the_numbers_and_the_fix(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = ROUTE_MOCK.read_text().replace(
        "position = [40.0, 0.0]       # bend 60° left",
        "position = [40.0, 0.0]       # bend 60° left\noverlap_m = 1.0")
    assert "overlap_m = 1.0" in text
    path = tmp_path / "route.toml"
    path.write_text(text)
    assert main(["check", str(path)]) == 2
    out = capsys.readouterr().out
    assert "INVALID: 1 violation:" in out
    assert ("[Junction1] Junction1 violated at waypoint 2 (S1 → S2): no line across S1 reaches "
            "into S2's entry region") in out
    fixes = out.split("nearest fixes (each alone, the rest unchanged):\n")[1].splitlines()
    assert fixes[0].startswith("  overlap_m ≥ ") and fixes[0].endswith(
        " m at waypoint 2 (now 1.0 m)")


def test_the_route_fence_holds_the_whole_flight(route_run: tuple[Any, Path]) -> None:
    """core/fence.route_fence: one inclusion polygon per segment (their union), obstacle
    circles; every recorded position of the route's flight is allowed; one segment is
    tube_fence's polygon."""
    from vtube_fleet.core.fence import route_fence, tube_fence

    result, _ = route_run
    sc = result.scenario
    fence = route_fence(sc.corridor, sc.robots.r_s, slots=sc.robots.positions)
    assert len(fence.polygons) == 2
    pts = result.pos.reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    assert fence.contains(pts).all()
    outside = sc.corridor.segments[1].p_r1 + np.array([5.0, -5.0])
    assert not fence.contains(outside[None])[0]
    tube = sc.corridor.segments[0]
    one = route_fence(Corridor.single(tube), 0.3, slots=sc.robots.positions)
    np.testing.assert_array_equal(one.polygons[0],
                                  tube_fence(tube, (), 0.3, slots=sc.robots.positions).polygon)
