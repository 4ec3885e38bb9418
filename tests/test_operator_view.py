"""What an operator looks at: the recording's blueprint and display entities (built and read back
without a viewer), and the live terminal view."""

from __future__ import annotations

import io
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vtube_fleet.core.metrics import SafetyLimits
from vtube_fleet.recording.layout import (
    METRIC_COLORS,
    OBSTACLE_COLOR,
    PHASE_CLASSES,
    SUB_TUBE_COLOR,
    TRIANGLE_COLOR,
    TUBE_COLOR,
    VELOCITY_COLOR,
    class_of,
)
from vtube_fleet.recording.reader import load_recording
from vtube_fleet.recording.writer import default_blueprint, open_recorder
from vtube_fleet.state import Phase

sys.path.insert(0, str(Path(__file__).parent))
from test_recording import motion, scenario  # noqa: E402


# ---------------------------------------------------------------------------------------------
# reading what was written (no viewer)
# ---------------------------------------------------------------------------------------------
def _rows(path: Path) -> dict[str, list[tuple[bool, Any]]]:
    """Entity path → [(static, record batch)] of the recording in ``path``."""
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    out: dict[str, list[tuple[bool, Any]]] = {}
    for ch in r.stream(store=r.recordings()[0]).to_chunks():
        out.setdefault(str(ch.entity_path).lstrip("/"), []).append(
            (ch.is_static, ch.to_record_batch()))
    return out


def _column(parts: list[tuple[bool, Any]], name: str, *, static: bool | None = None
            ) -> list[tuple[int | None, Any]]:
    """(tick, value list or None) of every row of ``name`` in ``parts``, ordered by tick."""
    out = []
    for is_static, rb in parts:
        if static is not None and is_static != static:
            continue
        if name not in rb.schema.names:
            continue
        ticks = (rb.column("tick").to_pylist() if "tick" in rb.schema.names
                 else [None] * rb.num_rows)
        out += list(zip(ticks, rb.column(name).to_pylist(), strict=True))
    return sorted(out, key=lambda r: -1 if r[0] is None else r[0])


def _blueprint(path: Path) -> dict[str, Any]:
    """The views and panels of the blueprint sent last (the one the viewer activates):
    {"views": {name: {...}}, "panels": {...}}."""
    from rerun.chunk import RrdReader

    r = RrdReader(path)

    def sent_at(store: Any) -> int:
        return max(max(ch.to_record_batch().column("log_time").cast("int64").to_pylist())
                   for ch in r.stream(store=store).to_chunks())

    store = max(r.blueprints(), key=sent_at)
    ents: dict[str, dict[str, Any]] = {}
    for ch in r.stream(store=store).to_chunks():
        rb = ch.to_record_batch()
        row = ents.setdefault(str(ch.entity_path), {})
        for n in rb.schema.names:
            if ":" in n:
                row[n.split(":", 1)[1]] = rb.column(n).to_pylist()[-1]
            if n == "TimeAxis:view_range":  # the boundary kinds (Infinite, Absolute, ...)
                rng = rb.column(n).flatten()[-1:]
                row["view_range_kinds"] = tuple(
                    u.type.field(u.type.type_codes.index(u.type_codes[0].as_py())).name
                    for u in (rng.field("start"), rng.field("end")))
    views: dict[str, dict[str, Any]] = {}
    for ent, row in ents.items():
        if ent.startswith("/view/") and ent.count("/") == 2:
            name = row["display_name"][0]
            sub = {k.split("/")[-1]: v for k, v in ents.items() if k.startswith(ent + "/")}
            views[name] = {
                "class": row["class_identifier"][0], "origin": row["space_origin"][0],
                "contents": sub.get("ViewContents", {}).get("query", []),
                "bounds": (sub.get("VisualBounds2D", {}).get("range") or [None])[0],
                "y_range": (sub.get("ScalarAxis", {}).get("range") or [None])[0],
                "legend": (sub.get("PlotLegend", {}).get("corner") or [None])[0],
                "x_range": sub.get("TimeAxis", {}).get("view_range_kinds"),
            }
    panels = {k.strip("/"): v for k, v in ents.items() if k.endswith("_panel")}
    return {"views": views, "panels": panels}


def _rgb(c: int) -> np.ndarray:
    return np.array([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], dtype=float)


# ---------------------------------------------------------------------------------------------
# the blueprint
# ---------------------------------------------------------------------------------------------
LIMITS = {"min_pair_distance_m": (0.5,), "min_left_leg_distance_m": (0.25,),
          "min_right_leg_distance_m": (0.25,), "min_speed_m_s": (0.5,), "max_speed_m_s": (3.5,),
          "min_obstacle_center_distance_m": (1.15, 1.25)}
FLEET_KEYS = ["min_pair_distance_m", "min_left_leg_distance_m", "min_right_leg_distance_m",
              "min_speed_m_s", "max_speed_m_s", "tick_duration_s", "link_latency_s",
              "truth_min_pair_distance_m"]


def test_blueprint_is_built_and_saved_without_a_viewer(tmp_path: Path) -> None:
    bp = default_blueprint((-2.0, -1.0, 35.0, 12.0), "fleet", limits=LIMITS,
                           metric_keys=FLEET_KEYS,
                           extremes={"min_pair_distance_m": (1.07, 8.0),
                                     "min_left_leg_distance_m": (0.3, 8.1),
                                     "max_speed_m_s": (2.0, 3.9)})
    bp.save("vtube_fleet", tmp_path / "bp.rbl")
    b = _blueprint(tmp_path / "bp.rbl")
    views = b["views"]
    tube = next(v for n, v in views.items() if n.startswith("tube"))
    # the tube frame as it is (no mirror): origin /world, bounds exactly the frame given
    assert tube["class"] == "2D" and tube["origin"] == "/world"
    assert tube["bounds"] == {"x_range": [-2.0, 35.0], "y_range": [-1.0, 12.0]}
    assert "other metrics" not in views  # every key has its view: no empty panel
    pair = views["min pair distance [m]"]
    assert {"/metrics/min_pair_distance_m", "/metrics/truth_min_pair_distance_m",
            "/limits/min_pair_distance_m"} <= set(pair["contents"])
    lo, hi = pair["y_range"]
    assert lo <= 0.0 and hi >= 2.0 * 1.07 and hi >= 4 * 0.5  # the limit and the lowest value
    legs = views["min leg distances [m]"]
    assert lo <= 0.0 and legs["y_range"][1] < 8.0  # not stretched by the end-of-run jump
    assert sum(c.startswith("/limits/") for c in legs["contents"]) == 1  # r_s once
    speed = views["speed min / max [m/s]"]
    assert speed["y_range"][0] <= 0.5 and speed["y_range"][1] >= 3.9  # both bounds, the max
    assert pair["legend"] is not None and speed["legend"] is not None
    assert "tick duration [s]" in views and "link latency [s]" in views
    # every time series shows the whole run, on either timeline (rerun's default: a window
    # around the time cursor, a narrow one on `tick`, "+0s" as the only label)
    plots = [v for v in views.values() if v["class"] == "TimeSeries"]
    assert len(plots) >= 5
    assert all(v["x_range"] == ("Infinite", "Infinite") for v in plots)
    # side panels collapsed, the time panel (collapsed: its slider) on mission_time
    assert b["panels"]["blueprint_panel"]["state"] == [2]  # PanelState.Collapsed
    assert b["panels"]["selection_panel"]["state"] == [2]
    assert b["panels"]["time_panel"]["timeline"] == ["mission_time"]
    assert b["panels"]["time_panel"]["state"] == [2]


def test_legends_go_to_the_corner_the_curves_leave_free(tmp_path: Path) -> None:
    """At close the recorder knows each curve's shape: a pair curve that ends far above its
    range (vehicles spreading out after the line) leaves the top right to itself, so the
    legend goes top left; a curve that starts high and comes down keeps the top right."""
    import rerun.blueprint as rrb

    from vtube_fleet.recording.writer import _legend_corner

    t = np.linspace(0.0, 60.0, 121)
    jump = [(a, 2.0 if a < 50.0 else 8.0) for a in t]
    falling = [(a, 3.0 - a / 30.0) for a in t]
    low = [(a, 0.2) for a in t]  # near the bottom, where the limit line also is
    assert _legend_corner([jump], [0.6], (0.0, 4.0)) == "LeftTop"
    assert _legend_corner([falling], [0.6], (0.0, 4.0)) == "RightTop"
    assert _legend_corner([low], [0.3], (0.0, 4.0)) == "RightTop"
    assert _legend_corner([], [0.6], (0.0, 4.0)) == "RightTop"  # nothing known: the default
    bp = default_blueprint(None, "fleet", limits=LIMITS, metric_keys=FLEET_KEYS,
                           extremes={"min_pair_distance_m": (2.0, 8.0),
                                     "min_left_leg_distance_m": (1.0, 3.0)},
                           shapes={"min_pair_distance_m": jump, "min_left_leg_distance_m": falling})
    bp.save("vtube_fleet", tmp_path / "bp.rbl")
    views = _blueprint(tmp_path / "bp.rbl")["views"]
    assert views["min pair distance [m]"]["legend"] == rrb.Corner2D.LeftTop.value
    assert views["min leg distances [m]"]["legend"] == rrb.Corner2D.RightTop.value


def test_other_metrics_only_when_there_are_any(tmp_path: Path) -> None:
    default_blueprint(None, "sim", limits=LIMITS, metric_keys=["min_pair_distance_m",
                                                               "my_gauge"]).save(
        "vtube_fleet", tmp_path / "bp.rbl")
    views = _blueprint(tmp_path / "bp.rbl")["views"]
    assert views["other metrics"]["contents"] == ["/metrics/my_gauge"]
    assert "tick duration [s]" not in views  # the simulator has no control loop
    default_blueprint(None, "sim", metric_keys=None).save("vtube_fleet", tmp_path / "b2.rbl")
    assert "other metrics" not in _blueprint(tmp_path / "b2.rbl")["views"]


def test_phase_classes_are_named_and_distinct() -> None:
    phases = [p.value for p in Phase]
    assert {p for _, p, _, _ in PHASE_CLASSES} >= set(phases)
    assert len({cid for cid, *_ in PHASE_CLASSES}) == len(PHASE_CLASSES)
    assert all(class_of(p) != class_of("?") for p in phases)
    cols = {p: c for _, p, _, c in PHASE_CLASSES if p}
    scene = {"triangles": TRIANGLE_COLOR, "sub-tubes": SUB_TUBE_COLOR, "tube": TUBE_COLOR,
             "obstacles": OBSTACLE_COLOR, "velocity": VELOCITY_COLOR}
    for a in cols:
        for b in cols:
            if a < b:
                assert np.linalg.norm(_rgb(cols[a]) - _rgb(cols[b])) >= 60, (a, b)
        for name, c in scene.items():
            assert np.linalg.norm(_rgb(cols[a]) - _rgb(c)) >= 60, (a, name)
    # the two curves of a view differ (left / right leg, min / max speed)
    for a, b in (("min_left_leg_distance_m", "min_right_leg_distance_m"),
                 ("min_speed_m_s", "max_speed_m_s")):
        assert np.linalg.norm(_rgb(METRIC_COLORS[a]) - _rgb(METRIC_COLORS[b])) >= 120


# ---------------------------------------------------------------------------------------------
# a fleet recording, as the viewer reads it
# ---------------------------------------------------------------------------------------------
def _fleet_recording(path: Path, extra_metric: str | None = None) -> None:
    rec = open_recorder(path, kind="fleet", display_period_s=1e9, display_max_ticks=5)
    rec.log_scene(scenario(3), meta={"rate_hz": 20.0})
    for k in range(40):
        ids = np.array([1, 2, 3])
        pos, vel = motion(k, 3)
        pos[0, 0] = 0.9 * k  # vehicle 1 flies on past the finishing line (x = 30) to 35.1
        phases = ["in_tube", "in_tube", "in_tube"]
        if k == 20:  # the owner tells the change (the pilot), then the tick shows it
            rec.log_event(0.05 * k, "in_tube → exited (crossed the finishing line at t = 1.00 s)",
                          vehicle_id=2)
            rec.log_exits(0.05 * k, k, [2])
        if k >= 20:
            phases[1] = "exited"
        if k >= 30:
            pos[1] = np.nan  # gone from the rows: its point must not stay drawn
        if k >= 25:
            phases[2] = "lost"  # nobody told it: the recorder does, as a warning
        metrics = {"min_pair_distance_m": 1.2 + 0.01 * k, "tick_duration_s": 0.001}
        if extra_metric:
            metrics[extra_metric] = 1.0
        rec.log_tick(t_s=0.05 * k, tick=k, ids=ids, pos=pos, vel=vel, phases=phases,
                     metrics=metrics)
    rec.close()


def test_fleet_recording_per_vehicle_entities_trails_and_legend(tmp_path: Path) -> None:
    path = tmp_path / "fleet.rrd"
    _fleet_recording(path)
    rows = _rows(path)
    # no hidden mirror at "world"; one annotation class per phase there
    assert not any("Transform3D" in n for _, rb in rows["world"] for n in rb.schema.names)
    (_, ctx), = _column(rows["world"], "AnnotationContext:context", static=True)
    got = {c["class_id"]: (c["class_description"]["info"]["label"],
                           c["class_description"]["info"]["color"]) for c in ctx[0]}
    assert got == {cid: (label, color) for cid, _, label, color in PHASE_CLASSES}
    # one display entity per vehicle: point (phase class), velocity arrow, trail
    for vid in (1, 2, 3):
        assert f"world/vehicles/{vid}" in rows
    p3 = _column(rows["world/vehicles/3"], "Points2D:class_ids", static=False)
    assert [c for _, c in p3] == [[class_of("in_tube")]] * 25 + [[class_of("lost")]] * 15
    arrows = _column(rows["world/vehicles/1"], "Arrows2D:vectors", static=False)
    assert len(arrows) == 40 and all(len(a) == 1 for _, a in arrows)
    # vehicle 2 is cleared where it left (an empty row), not drawn at its last position
    p2 = _column(rows["world/vehicles/2"], "Points2D:positions", static=False)
    assert [len(v) for _, v in p2] == [1] * 30 + [0] and p2[-1][0] == 30
    # trails: the recent path, ending at the vehicle's position at that tick
    trail = _column(rows["world/vehicles/1"], "LineStrips2D:strips", static=False)
    assert len(trail) >= 5
    tick, strips = trail[-1]
    (strip,) = strips
    assert len(strip) >= 2 and strip[-1][0] == pytest.approx(0.9 * tick, abs=1e-5)
    span = strip[-1][0] - strip[0][0]
    assert 0 < span <= 0.9 * (3.0 / 0.05) + 1e-6  # at most the last TRAIL_S = 3 s
    # the whole flight, static (shown at any time cursor): vehicle 1 flew x = 0.9 t for 40 ticks,
    # vehicle 2 until it left at tick 30; a point every PATH_STEP_S
    (_, paths), = _column(rows["world/vehicles/1/path"], "LineStrips2D:strips", static=True)
    (whole,) = paths
    assert whole[0][0] == pytest.approx(0.0) and whole[-1][0] == pytest.approx(0.9 * 39, abs=1.0)
    assert len(whole) == pytest.approx(39 * 0.05 / 0.5 + 1, abs=1)
    (_, paths2), = _column(rows["world/vehicles/2/path"], "LineStrips2D:strips", static=True)
    assert paths2[0][-1][0] <= 0.9 * 29 + 1e-5
    # only the point is labelled (its id): a trail carrying the phase class must not draw the
    # class label too (in the viewer: "connecting" written over every id)
    (_, shown), = _column(rows["world/vehicles/1"], "LineStrips2D:show_labels", static=True)
    assert shown == [False]
    (_, ids), = _column(rows["world/vehicles/1"], "Points2D:labels", static=True)
    assert ids == ["1"]
    # the axis key: short labels on the arrows (a long one on the vertical arrow at the
    # frame's left edge was cut off), the sentence as one label centred above the frame
    arrow_labels = _column(rows["world/axes"], "Arrows2D:labels", static=True)[-1][1]  # last
    assert arrow_labels == ["+x", "+y"]
    line = _column(rows["world/axes"], "Points2D:labels", static=True)[-1][1]
    assert "y to the left of the heading (drawn downwards" in line[0]
    # the phase legend, labelled, under the frame
    labels = _column(rows["world/legend"], "Points2D:labels", static=True)[-1][1]  # last
    assert "in tube" in labels and "LOST" in labels and "exited" in labels
    # the last blueprint frames the tube ∪ the flown extent (vehicle 1 reached x = 35.1)
    views = _blueprint(path)["views"]
    assert "other metrics" not in views
    tube = next(v for n, v in views.items() if n.startswith("tube"))
    (x0, x1), (y0, y1) = tube["bounds"]["x_range"], tube["bounds"]["y_range"]
    assert x0 < 0.0 and x1 >= 35.1 and y0 < 0.0 and y1 > 10.0
    # the recording still reads back exactly (review's data is unchanged)
    d = load_recording(path)
    assert d.exits == {2: pytest.approx(1.0)}
    assert np.isnan(d.pos[30:, list(d.ids).index(2)]).all()


def test_other_metrics_view_appears_for_an_unknown_metric(tmp_path: Path) -> None:
    path = tmp_path / "fleet.rrd"
    _fleet_recording(path, extra_metric="battery_min_v")
    views = _blueprint(path)["views"]
    assert views["other metrics"]["contents"] == ["/metrics/battery_min_v"]
    rows = _rows(path)
    (_, names), = _column(rows["metrics/battery_min_v"], "SeriesLines:names", static=True)
    assert names == ["battery_min_v"]
    (_, names), = _column(rows["metrics/min_pair_distance_m"], "SeriesLines:names", static=True)
    assert names == ["min pair distance"]


def test_one_event_per_fact_and_warn_only_for_alarms(tmp_path: Path) -> None:
    path = tmp_path / "fleet.rrd"
    _fleet_recording(path)
    d = load_recording(path)
    about_2 = [e for e in d.events if ("vehicle 2" in e[3] or "vehicles 2" in e[3])
               and "exited" in e[3]]
    assert [e[3] for e in about_2] == [
        "vehicle 2: in_tube → exited (crossed the finishing line at t = 1.00 s)"]
    about_3 = [e for e in d.events if "vehicle 3" in e[3]]
    assert [(e[2], e[3]) for e in about_3] == [("INFO", "vehicle 3: in_tube"),
                                              ("WARN", "vehicle 3: in_tube → lost")]
    assert all(e[2] == "INFO" for e in d.events if "lost" not in e[3])


def test_sim_exits_are_told_once(tmp_path: Path) -> None:
    path = tmp_path / "sim.rrd"
    with open_recorder(path, kind="sim") as rec:
        rec.log_scene(scenario(3))
        for k in range(10):
            pos, vel = motion(k, 3)
            if k >= 6:
                pos[0] = np.nan
            rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(3), pos=pos, vel=vel)
    d = load_recording(path)
    assert [e[3] for e in d.events] == ["vehicle 0 exited"]
    rows = _rows(path)
    assert "world/legend" not in rows  # one colour, no phases: nothing to explain
    assert "| id | x [m] |" in _column(rows["status"], "TextDocument:text")[0][1][0]


def test_y_range_contains_every_value_below_the_limit(tmp_path: Path) -> None:
    """A run that breaks a limit (or goes negative) is never clipped at the bottom."""
    from vtube_fleet.recording.writer import _y_range

    lo, hi = _y_range(("min_pair_distance_m",), LIMITS, {"min_pair_distance_m": (-0.2, 3.0)})
    assert lo <= -0.2 and hi >= 2.0
    assert _y_range(("tick_duration_s",), LIMITS, {}) is None
    assert math.isfinite(_y_range(("min_speed_m_s", "max_speed_m_s"), LIMITS, {})[1])


# ---------------------------------------------------------------------------------------------
# review's figures
# ---------------------------------------------------------------------------------------------
def _curve_range(ax: Any) -> tuple[float, float]:
    """Finite y range of the curves (not the horizontal limit lines) drawn in ``ax``."""
    ys = [np.asarray(ln.get_ydata(), dtype=float) for ln in ax.lines
          if len(ln.get_xdata()) > 2]
    y = np.concatenate(ys)
    y = y[np.isfinite(y)]
    return float(y.min()), float(y.max())


def _hlines(ax: Any) -> list[float]:
    return [float(ln.get_ydata()[0]) for ln in ax.lines
            if len(ln.get_ydata()) == 2 and ln.get_ydata()[0] == ln.get_ydata()[1]]


def test_safety_figure_never_clips_a_curve_and_draws_the_limits() -> None:
    from vtube_fleet.plots import safety_figure

    t = np.linspace(0.0, 20.0, 400)
    pair = 1.07 + 0.2 * np.sin(t)  # the mock fleet's story: 1.07–1.3 m ...
    pair[350:] = 6.0 + t[350:]  # ... and an end-of-run jump
    pair[10:20] = np.nan  # a gap (nobody within range)
    legs = np.where(t < 18, 0.3 + 0.1 * np.cos(t), 8.0)
    below = 0.2 + 0.0 * t  # below its limit r_s = 0.25: must be visible too
    metrics = {"min_pair_distance_m": pair, "min_obstacle_center_distance_m": 1.5 + t,
               "min_left_leg_distance_m": legs, "min_right_leg_distance_m": below,
               "min_speed_m_s": 0.4 + 0.0 * t, "max_speed_m_s": 3.6 + 0.0 * t}
    fig = safety_figure(t, metrics, r_s=0.25, v_min=0.5, v_max=3.5, obstacle_radii=[0.9, 1.0],
                        pair_search_m=1.3)
    axes = fig.axes
    limits = [[0.5], [1.15, 1.25], [0.25], [0.25], [0.5, 3.5]]
    for ax, key, lim in zip(axes, list(metrics)[:4] + ["speed"], limits, strict=True):
        lo, hi = ax.get_ylim()
        c_lo, c_hi = _curve_range(ax)
        assert lo < c_lo and c_hi < hi, (key, (lo, hi), (c_lo, c_hi))  # no curve clipped
        assert set(lim) <= set(_hlines(ax)), key  # the limits are drawn ...
        assert all(lo < v < hi for v in lim), key  # ... inside the plot
    assert _curve_range(axes[0]) == (pytest.approx(np.nanmin(pair)), pytest.approx(26.0))
    assert 1.3 in _hlines(axes[0])  # the summary's pair search radius, as the curve passes it
    # an end-of-run jump far above the story (26 m vs ~1.2 m) puts the panel on a log scale, so
    # the part near the limit stays readable; the speeds (no jump) stay linear
    assert [ax.get_yscale() for ax in axes] == ["log", "linear", "log", "linear", "linear"]


def test_trajectory_figure_holds_every_path_and_the_tube() -> None:
    from vtube_fleet.core.tube import Obstacle, Trapezoid
    from vtube_fleet.plots import trajectory_figure

    tube = Trapezoid(np.array([0.0, 0.0]), np.array([30.0, 2.0]), np.array([0.0, 10.0]),
                     np.array([30.0, 8.0]), name="T")
    t = np.linspace(0.0, 10.0, 50)
    pos = np.full((50, 4, 2), np.nan)
    pos[:, 0] = np.stack([4.0 * t, 5.0 + 0.0 * t], -1)  # flies on to x = 40 past the line
    pos[:30, 1] = np.stack([t[:30], -3.0 + 0.0 * t[:30]], -1)  # takes off outside, y = -3
    pos[20:, 2] = np.stack([t[20:], 3.0 + 0.0 * t[20:]], -1)  # joins late
    fig = trajectory_figure(tube, t, pos, ids=[4, 5, 6, 7], r_s=0.25,
                            obstacles=[Obstacle(np.array([15.0, 5.0]), 1.0)])
    (ax,) = fig.axes
    paths = [ln for ln in ax.lines if str(ln.get_gid()).startswith("path ")]
    assert sorted(ln.get_gid() for ln in paths) == ["path 4", "path 5", "path 6"]  # 7: no data
    assert len({tuple(np.round(ln.get_color(), 3)) for ln in paths}) == 3  # one colour each
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert x0 < 0.0 and x1 > 40.0 and y0 < -3.0 and y1 > 10.0


def test_review_pair_curve_is_not_cut_at_the_search_radius(tmp_path: Path) -> None:
    """The summary searches pairs within r_s + r_a (0.75 m here): review's curve covers every
    step, also where the vehicles stayed farther apart."""
    from vtube_fleet.recording.review import full_pair_curve, step_metrics

    path = tmp_path / "far.rrd"
    with open_recorder(path, kind="sim") as rec:
        rec.log_scene(scenario(3))
        for k in range(20):
            pos, vel = motion(k, 3)  # 1.5 m apart: never within 0.75 m
            rec.log_tick(t_s=0.1 * k, tick=k, ids=np.arange(3), pos=pos, vel=vel)
    d = load_recording(path)
    _, sm = step_metrics(d)
    assert not np.isfinite(sm.min_pair_distance_m).any()  # the summary's series: empty
    curve = full_pair_curve(d)
    assert np.isfinite(curve).all() and curve == pytest.approx(1.5, abs=0.01)
    from vtube_fleet.recording.review import write_review_plots

    written = write_review_plots(d, tmp_path / "plots")
    assert [p.name for p in written] == ["far-safety.png", "far-snapshots.png",
                                         "far-trajectories.png"]
    assert all(p.stat().st_size > 10_000 for p in written)


# ---------------------------------------------------------------------------------------------
# the live terminal view
# ---------------------------------------------------------------------------------------------
def _status(n: int = 3, **kw: Any) -> Any:
    from vtube_fleet.fleet.view import FleetStatus, VehicleRow

    rows = [VehicleRow(vehicle_id=i, phase="in_tube", sub_tube=f"T_o{1 + i % 4}", x_m=1.0 + i,
                       y_m=0.5 * i, speed_m_s=1.5, neighbour_m=1.2, obstacle_m=3.0,
                       obstacle_limit_m=1.15, leg_m=0.9, link_age_s=0.05, accuracy_m=0.02)
            for i in range(n)]
    base = dict(t_s=12.5, stage="in_tube", vehicles=n, connected=n, armed=n, in_tube=n,
                phases={"in_tube": n},
                min_pair_m=1.07, pair_limit_m=0.5, min_obstacle_m=1.6, obstacle_limit_m=1.15,
                min_leg_m=0.43, leg_limit_m=0.25, delta_m=0.1, tick_p50_ms=0.4,
                tick_p99_ms=1.2, rate_hz=20.0, on_time=0.998, latency_ms=3.0, rows=rows)
    base.update(kw)
    return FleetStatus(**base)


def _plain(renderable: Any, width: int = 160) -> str:
    from rich.console import Console

    out = io.StringIO()
    Console(file=out, width=width, color_system=None, force_terminal=False).print(renderable)
    return out.getvalue()


def test_plain_lines_when_stdout_is_not_a_terminal() -> None:
    from vtube_fleet.fleet.view import FleetView

    out = io.StringIO()
    view = FleetView(out, tty=None, log_every_s=0.0)  # StringIO is no terminal
    assert not view.tty
    view.update(_status())
    view.message("[   1.0s] WARNING slot 2: setpoint not sent")
    st = _status(min_pair_m=0.45)  # below 2 r_s = 0.5
    view.update(st, force=True)
    view.close()
    lines = out.getvalue().splitlines()
    assert "\x1b" not in out.getvalue()  # no escape codes in a log
    # headline, clearance flown, worst vehicles; the event; the forced status; the final one
    assert len(lines) == 3 + 1 + 3 + 3
    assert lines[0] == ("t=12.5s in_tube: 3 vehicles (3 connected): 3 in tube | tick p99 1.20 "
                        "ms, 20.00 Hz, on time 99.8%, link 3.00 ms")
    assert lines[1].startswith("  flown: pair 1.07 m (> 0.50) · obstacle centre 1.60 m")
    assert lines[2].startswith("  worst now: pair #0 1.20 m · obstacle #0 3.00 m · leg #0 0.90 m")
    assert lines[3] == "[ 1.0s] WARNING slot 2: setpoint not sent"
    assert "pair 0.45 m (> 0.50) BROKEN" in lines[5]
    assert "BROKEN" not in "".join(lines[:3])
    assert max(len(ln) for ln in lines) < 150  # was one line of ~350 characters


def test_plain_lines_name_the_worst_vehicle_per_limit() -> None:
    from vtube_fleet.fleet.view import FleetView

    st = _status(12, truth_pair_m=1.1, truth_obstacle_m=1.5, truth_leg_m=0.4)
    st.rows[7].neighbour_m = 0.45  # below 2 r_s = 0.5
    st.rows[3].obstacle_m = 1.2  # within 20 % above r_o + r_s = 1.15
    st.rows[5].leg_m = 0.5
    st.rows[9].link_age_s = 0.8
    st.rows[2].accuracy_m = 0.3
    lines = FleetView.lines(st)
    assert len(lines) == 4 and lines[2].startswith("  truth: pair 1.10 m")
    assert lines[3] == ("  worst now: pair #7 0.45 m BROKEN · obstacle #3 1.20 m near its limit · "
                        "leg #5 0.50 m · link age #9 0.80 s · accuracy #2 0.30 m")


def test_table_one_row_per_vehicle_and_problems_stand_out() -> None:
    from vtube_fleet.fleet.view import FleetView

    st = _status(4)
    st.rows[1].neighbour_m = 0.45  # below 2 r_s
    st.rows[2].leg_m = 0.27  # within 20 % above r_s
    st.rows[3].phase = "lost"
    st.rows[3].link_age_s = 3.2
    tab = FleetView.table(st)
    text = _plain(tab)
    head = "\n".join(ln for ln in text.splitlines()[:2])
    for col in ("id", "phase", "sub-", "tube", "x", "y", "v", "neighbour", "obstacle", "leg",
                "link age", "accuracy", "[m]", "[m/s]", "[s]"):
        assert col in head
    assert "battery" not in head  # nobody reports one: no empty column
    body = [ln.split() for ln in text.splitlines() if ln.strip()[:1].isdigit()]
    assert [r[0] for r in body] == ["0", "1", "2", "3"]
    assert body[1][:7] == ["1", "in_tube", "T_o2", "2.00", "0.50", "1.50", "0.45"]
    cells = {str(c.header).replace("\n", " "): c._cells for c in tab.columns}
    assert cells["neighbour [m]"][1].style == "bold red"
    assert cells["neighbour [m]"][0].style == ""
    assert cells["leg [m]"][2].style == "yellow"
    assert cells["phase"][3].style == "bold red" and cells["link age [s]"][3].style == "bold red"
    st.rows[0].battery = 0.1
    assert "battery" in _plain(FleetView.table(st))


def test_header_is_compact_and_marks_broken_limits() -> None:
    from vtube_fleet.fleet.view import FleetView

    text = _plain(FleetView.header(_status(min_leg_m=0.2, unsafe=True)))
    lines = text.splitlines()
    assert len(lines) == 3
    assert "3 vehicles: 3 connected · 3 armed · 3 in tube · 0 exited · 0 lost" in lines[0]
    assert "pair 1.07 (> 0.50)" in lines[1] and "legs 0.20 (> 0.25) BROKEN" in lines[1]
    assert "UNSAFE" in lines[1] and "20.00 Hz" in lines[2]


def test_fifty_vehicles_fit_problems_first() -> None:
    from vtube_fleet.fleet.view import FleetView

    st = _status(50)
    st.rows[37].neighbour_m = 0.3
    text = _plain(FleetView.table(st, max_rows=20))
    body = [ln.split() for ln in text.splitlines() if ln.strip()[:1].isdigit()]
    assert len(body) == 19 and body[0][0] == "37"  # the problem first, then by id
    assert [r[0] for r in body[1:4]] == ["0", "1", "2"]
    assert "… and 31 more vehicles without a problem" in text
    assert len(_plain(FleetView.table(_status(50))).splitlines()) <= 54  # all 50 fit on 60


def test_the_table_fits_100_columns() -> None:
    """Every column, with the widest values each takes (a 10-letter phase, 3-digit negative
    coordinates, a battery), within 100 terminal columns and nothing cut."""
    from vtube_fleet.fleet.view import COLUMNS, FleetView

    st = _status(12)
    for r in st.rows:
        r.phase, r.x_m, r.y_m, r.speed_m_s = "connecting", -123.45, -99.99, 10.25
        r.neighbour_m, r.obstacle_m, r.leg_m, r.link_age_s, r.accuracy_m = (
            123.45, 123.45, 12.34, 12.34, 10.12)
        r.battery, r.sub_tube = 0.55, "T_o12"
    st.rows[0].vehicle_id = 999
    text = _plain(FleetView.table(st), width=100)
    lines = text.splitlines()
    assert max(len(ln) for ln in lines) <= 100
    assert len(lines) == 2 + 1 + 12  # two header lines, the rule, one line per vehicle
    for v in ("connecting", "-123.45", "-99.99", "10.25", "123.45", "12.34", "10.12", "55 %",
              "T_o12", "999"):
        assert v in text
    assert len(COLUMNS) == 13  # every column shown: a route's segment and a battery


def test_live_table_on_a_terminal() -> None:
    from vtube_fleet.fleet.view import FleetView

    out = io.StringIO()
    view = FleetView(out, tty=True, width=150, height=40)
    view.update(_status())
    view.message("[  13.0s] ERROR ABORT: link lost")
    view.close()
    raw = out.getvalue()
    assert "\x1b[" in raw  # drawn in place, with colours
    assert "neighbour" in raw and "in_tube" in raw and "ABORT: link lost" in raw
    assert raw.index("ABORT") < raw.rindex("neighbour")  # the event above the table


def test_vehicle_rows_from_pilots() -> None:
    from types import SimpleNamespace

    from vtube_fleet.core.params import ControllerParams
    from vtube_fleet.core.route import Corridor, Route
    from vtube_fleet.core.tube import Obstacle, Trapezoid
    from vtube_fleet.fleet.view import vehicle_rows

    tube = Trapezoid(np.array([0.0, 0.0]), np.array([30.0, 0.0]), np.array([0.0, 10.0]),
                     np.array([30.0, 10.0]), name="T")

    def pilot(i: int, phase: Phase, xy: tuple[float, float], last: float | None) -> Any:
        state = SimpleNamespace(last_packet_s=last, last_heartbeat_s=last)
        return SimpleNamespace(vehicle_id=i, phase=phase, position=lambda: np.array(xy),
                               vel_xy=np.array([3.0, 4.0]), link=SimpleNamespace(state=state),
                               position_accuracy_m=lambda: 0.05)

    pilots = [pilot(0, Phase.IN_TUBE, (5.0, 2.0), 99.0),
              pilot(1, Phase.IN_TUBE, (8.0, 6.0), 99.5),
              pilot(2, Phase.READY, (5.0, 2.5), None),  # on the ground: no neighbour
              pilot(3, Phase.LANDING, (40.0, 6.0), 100.0)]  # out of the tube: no leg
    route = Route.plan(Corridor.single(tube, [Obstacle(np.array([5.0, 5.0]), 1.0)]),
                       ControllerParams(r_s=0.25, r_a=0.5, v_min=1.0, v_max=2.0, v=1.5,
                                        v_max_prime=0.5), strict=False)
    rows = vehicle_rows(pilots, route, SafetyLimits(0.25, 1.0, 2.0), now_mono=100.0)
    # the sub-tube the switching rule puts each vehicle in the tube in (by name)
    assert route.K > 1
    assert [r.sub_tube for r in rows] == [
        route.sub_tubes[int(route.locate(np.array([[5.0, 2.0]]))[1][0])].name,
        route.sub_tubes[int(route.locate(np.array([[8.0, 6.0]]))[1][0])].name, "", ""]
    assert [r.phase for r in rows] == ["in_tube", "in_tube", "ready", "landing"]
    assert rows[0].speed_m_s == pytest.approx(5.0)
    assert rows[0].neighbour_m == pytest.approx(5.0) and math.isnan(rows[2].neighbour_m)
    assert rows[3].neighbour_m == pytest.approx(32.0)
    assert rows[0].obstacle_m == pytest.approx(3.0) and rows[0].obstacle_limit_m == 1.25
    assert rows[0].leg_m == pytest.approx(min(tube.d_Th(np.array([[5.0, 2.0]]))[0],
                                              tube.d_Tr(np.array([[5.0, 2.0]]))[0]))
    assert math.isnan(rows[3].leg_m) and math.isnan(rows[2].link_age_s)
    assert rows[0].link_age_s == pytest.approx(1.0) and rows[1].accuracy_m == 0.05


def test_the_table_shows_each_vehicles_route_segment() -> None:
    """A route of several segments: each row names the segment the vehicle flies (the fleet
    table's column; a vehicle never sensed: where its position starts), its leg distance is to
    that segment's legs; a one-segment route has no segment column."""
    from types import SimpleNamespace

    from vtube_fleet.config.mission import load_mission
    from vtube_fleet.fleet.budget import SafetyBudget
    from vtube_fleet.fleet.flight_plan import FlightPlan
    from vtube_fleet.fleet.view import FleetStatus, FleetView, vehicle_rows

    mission = load_mission(Path(__file__).resolve().parents[1] / "configs" / "route_mock.toml")
    sc = mission.scenario
    flown = SafetyBudget.compute(sc.controller, period_s=0.05, latency_s=0.02, dead_time_s=0.3,
                                 t63_s=1.0).inflate(sc.controller)
    route = FlightPlan.for_mission(mission, flown).route

    def pilot(i: int, xy: tuple[float, float]) -> Any:
        state = SimpleNamespace(last_packet_s=99.0, last_heartbeat_s=99.0)
        return SimpleNamespace(vehicle_id=i, phase=Phase.IN_TUBE, position=lambda: np.array(xy),
                               vel_xy=np.array([1.0, 0.0]), link=SimpleNamespace(state=state),
                               position_accuracy_m=lambda: 0.3)

    s2 = sc.corridor.segments[1]
    mid2 = 0.5 * (s2.lh(10.0) + s2.lr(10.0))
    pilots = [pilot(0, (10.0, 0.0)), pilot(1, tuple(mid2)), pilot(2, (20.0, 3.0))]
    rows = vehicle_rows(pilots, route, SafetyLimits(0.3, 0.3, 1.6), np.array([0, 1, -1]),
                        now_mono=100.0)
    assert [r.segment for r in rows] == [0, 1, 0]
    dh, dr = route.leg_distances(mid2[None], np.array([1]))
    assert rows[1].leg_m == pytest.approx(min(dh[0], dr[0]))
    tab = FleetView.table(FleetStatus(rows=rows, pair_limit_m=0.6, leg_limit_m=0.3))
    text = _plain(tab)
    head = text.splitlines()
    assert "seg-" in head[0] and "ment" in head[1]  # the header: name over unit
    body = [ln.split() for ln in text.splitlines() if ln.strip()[:1].isdigit()]
    assert [r[2] for r in body] == ["S1", "S2", "S1"]
    # the sub-tube within its segment (the switching rule of that segment's partition)
    _, k = route.locate(np.array([[10.0, 0.0], mid2]), np.array([0, 1]))
    assert [rows[0].sub_tube, rows[1].sub_tube] == [
        route.sub_tubes[int(j)].name.split(".", 1)[-1] for j in k]
    single = FlightPlan.for_mission(load_mission(
        Path(__file__).resolve().parents[1] / "configs" / "mock_fleet.toml"), flown).route
    rows = vehicle_rows(pilots[:1], single, SafetyLimits(0.3, 0.3, 1.6), now_mono=100.0)
    assert rows[0].segment == -1
    assert "seg-" not in _plain(FleetView.table(FleetStatus(rows=rows)))
