"""``vtube-fleet review``: a run's recording gives back the run's own summary and figures.

End to end with the real simulator (here) and the real mock fleet (the 12-vehicle mission's
flight in tests/test_fleet_e2e.py reviews its recording with the helpers below): the run
records, the recording is read back, the summary is recomputed with the same metrics code, and
compared key by key with what the run itself reported.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vtube_fleet.cli import main
from vtube_fleet.core.metrics import METRIC_KEYS
from vtube_fleet.recording.layout import E_VEHICLES
from vtube_fleet.recording.reader import load_recording
from vtube_fleet.recording.review import compare_summaries, review
from vtube_fleet.recording.writer import open_recorder

ROOT = Path(__file__).resolve().parents[1]

#: A short scenario: 12 robots packed closer than r_s + r_a (so the pair metric is in range
#: from the start), one obstacle, a tube that narrows; every robot exits within ~10 s.
SCENARIO = {
    "tube": {"p_h0": [0.0, 0.0], "p_h1": [20.0, 1.0], "p_r0": [0.0, 10.0], "p_r1": [20.0, 9.0]},
    "obstacles": [{"center": [11.0, 5.0], "radius": 0.6}],
    "robots": {"r_s": 0.2, "r_a": 0.6, "v_min": 0.5, "v_max": 3.5,
               "grid": {"origin": [0.8, 3.9], "rows": 3, "cols": 4, "spacing": 0.75}},
    "controller": {"v": 2.0, "v_max_prime": 1.5},
    "sim": {"dt": 0.01, "duration": 14.0, "record_every": 1},
}


def _scenario(**sim: Any) -> Any:
    from vtube_fleet.config.scenario import parse_scenario

    doc = json.loads(json.dumps(SCENARIO))
    doc["sim"].update(sim)
    return parse_scenario(doc, "review_test.toml")


def _png_ok(path: Path) -> None:
    """A real, non-blank PNG."""
    from matplotlib.image import imread

    assert path.exists(), path
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = imread(path)
    assert img.shape[0] > 200 and img.shape[1] > 200
    assert float(np.std(img[..., :3])) > 0.02, f"{path} looks blank"


def _assert_same_summary(recomputed: dict[str, Any], run: dict[str, Any]) -> None:
    assert list(recomputed) == list(run)  # same keys, same order
    bad = compare_summaries(recomputed, run, rel=1e-9, abs_=1e-9)
    assert not bad, bad


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    from vtube_fleet.sim import simulate

    out = tmp_path_factory.mktemp("sim")
    with open_recorder(out / "recording.rrd", kind="sim") as rec:
        result = simulate(_scenario(), recorder=rec)
    return result, out / "recording.rrd"


def test_short_sim_recording_loads_back(sim_run: tuple[Any, Path]) -> None:
    result, path = sim_run
    s = result.summary
    assert s["exited"] == s["robots"] == 12 and not s["interrupted"]
    d = load_recording(path)
    assert d.kind == "sim" and d.meta["robots"] == 12 and d.meta["dt_s"] == 0.01
    # one recorded row per recorded frame of the run, every entity of the layout present
    assert len(d.tick) == s["frames"] == result.t.size
    assert d.entity_rows[E_VEHICLES] == s["frames"]
    # one display entity per robot (point, velocity arrow, trail), cleared when it exits
    assert all(d.entity_rows.get(f"world/vehicles/{i}", 0) > 0 for i in range(12))
    for key in ("min_pair_distance_m", "min_obstacle_center_distance_m",
                "min_left_leg_distance_m", "min_right_leg_distance_m", "min_speed_m_s",
                "max_speed_m_s"):
        assert d.entity_rows[f"metrics/{key}"] == s["steps"], key
    for ent in ("meta/scenario", "meta/summary", "world/tube", "world/obstacles"):
        assert d.static_rows.get(ent, 0) >= 1, ent
    assert d.entity_rows["world/sub_tubes"] == 1 and d.entity_rows["world/triangles"] == 1
    assert len(d.partitions[0][1]) == result.partition.K
    # the recorded trajectory is the simulator's, bit for bit
    np.testing.assert_allclose(d.t_s, result.t, atol=1e-9)
    np.testing.assert_array_equal(d.pos, result.pos)
    np.testing.assert_array_equal(d.vel, result.vel)
    # exits: the exact times the simulator saw
    exp = {i: float(t) for i, t in enumerate(result.exit_time_s) if math.isfinite(t)}
    assert d.exits.keys() == exp.keys()
    for i, t in exp.items():
        assert d.exits[i] == pytest.approx(t, abs=1e-9)
    assert d.summary == json.loads(json.dumps(s))


def test_review_json_is_exactly_the_run_summary(sim_run: tuple[Any, Path],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    result, path = sim_run
    assert main(["review", str(path), "--json", "--no-plots"]) == 0
    out = capsys.readouterr().out
    recomputed = json.loads(out)  # stdout is exactly one JSON document
    run = json.loads(json.dumps(result.summary))
    # every step is a frame here: the frames alone give the run's figures too
    from_frames = recomputed.pop("from_frames")
    assert from_frames == {k: recomputed[k] for k in from_frames} and "steps" in from_frames
    _assert_same_summary(recomputed, run)
    # the recomputed keys really were recomputed (not copied): change the stored summary's
    # copy in memory and the recomputation still gives the run's numbers
    res = review(path, plots=False)
    for key in ("robots", "exited", "steps", "violations", "min_pair_distance_m",
                "min_obstacle_center_distance_m", "median_exit_s", "max_speed_m_s"):
        assert key in res.recomputed_keys, key
    assert not res.differences


def test_review_text_and_plots(sim_run: tuple[Any, Path], tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    _, path = sim_run
    assert main(["review", str(path), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "the recomputed summary matches the run's own summary" in out
    assert "min_pair_distance_m" in out and "as the run reported them" in out
    _png_ok(tmp_path / "recording-safety.png")
    _png_ok(tmp_path / "recording-snapshots.png")


def test_decimated_recording_reports_its_limits(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    from vtube_fleet.sim import simulate

    with open_recorder(tmp_path / "r.rrd", kind="sim") as rec:
        result = simulate(_scenario(record_every=7), recorder=rec)
    d = load_recording(tmp_path / "r.rrd")
    assert len(d.tick) == result.summary["frames"] == result.t.size
    # the per-step series still hold every step's extremes: their minimum is the run's
    t_m, k_m, logged = d.metric_series["min_pair_distance_m"]
    # one value per recorded frame (but the final state, after the last step: none) ...
    np.testing.assert_array_equal(k_m, d.tick[:-1])
    assert np.nanmin(logged) == result.summary["min_pair_distance_m"]  # ... keeping the minimum
    assert np.nanmax(d.metric_series["max_speed_m_s"][2]) == result.summary["max_speed_m_s"]
    assert d.exits == pytest.approx(
        {i: float(t) for i, t in enumerate(result.exit_time_s) if math.isfinite(t)})
    assert main(["review", str(tmp_path / "r.rrd"), "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "from the 145 recorded frames alone (one every 7 steps" in out
    assert "the recomputed summary matches the run's own summary" in out
    res = review(tmp_path / "r.rrd", plots=False)
    # issue 31: the headline figures are the best the recording knows, the run's (the per-step
    # extremes; the counts as the run made them, confirmed by the per-step series) ...
    assert not res.differences
    _assert_same_summary({k: v for k, v in res.summary.items()}, json.loads(json.dumps(
        result.summary)))
    assert set(res.per_step_keys) == set(METRIC_KEYS)
    assert set(res.run_keys) == {"steps", "violations", "violations_by_condition",
                                 "first_violation_s"}
    # ... and the frames' own figures are kept apart: the judged frames (all but the final
    # state), minima over fewer samples can only be larger
    f = res.from_frames
    assert f["steps"] == result.summary["frames"] - 1 < res.summary["steps"]
    assert f["exited"] == result.summary["exited"]
    assert f["median_exit_s"] == result.summary["median_exit_s"]
    assert f["min_pair_distance_m"] >= result.summary["min_pair_distance_m"] - 1e-12


@pytest.mark.parametrize("controller", ["new", "old"])
def test_review_json_of_a_sim_agrees_with_the_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], controller: str) -> None:
    """Issue 31: ``sim configs/paper.toml --robots 30 --duration 6`` said min speed 0.6227 m/s,
    ``review --json`` 0.7099 m/s (the recorded frames, 1 in 40 steps). The JSON's headline
    figures are now the recording's per-step extremes, the run's; the frames' own figures are
    under ``from_frames``. (Oldcontroller) breaks v_min: the violations are the run's count,
    which its per-step series confirm, not the one frame that caught it."""
    out = tmp_path / "x"
    code = main(["sim", str(ROOT / "configs" / "paper.toml"), "--robots", "30", "--duration",
                 "6", "--out", str(out), "--controller", controller, "--no-plots", "--quiet"])
    assert code == 1  # robots left in the tube after 6 s (and, for "old", v_min broken)
    run = json.loads((out / "summary.json").read_text())
    capsys.readouterr()
    assert main(["review", str(out / "recording.rrd"), "--json", "--no-plots"]) == 0
    doc = json.loads(capsys.readouterr().out)
    frames = doc.pop("from_frames")
    _assert_same_summary(doc, run)  # every headline figure is the run's
    for key in ("min_speed_m_s", "min_pair_distance_m", "violations", "steps"):
        assert doc[key] == run[key], key
    assert frames["steps"] == 150 < run["steps"] == 6000  # 1 frame in 40 steps
    assert frames["min_speed_m_s"] > run["min_speed_m_s"]  # the frames missed the slowest step
    if controller == "new":
        assert run["min_speed_m_s"] == pytest.approx(0.6227, abs=1e-4)
        assert frames["min_speed_m_s"] == pytest.approx(0.7099, abs=1e-4)
        assert run["violations"] == frames["violations"] == 0
    else:
        assert run["violations"] > frames["violations"] > 0
        assert doc["violations_by_condition"] == run["violations_by_condition"]


def test_review_of_a_bad_file_is_a_one_line_error(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["review", str(tmp_path / "none.rrd")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'none.rrd'}: no such file"
    junk = tmp_path / "junk.rrd"
    junk.write_text("not a recording\n")
    assert main(["review", str(junk), "--json"]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.startswith("error: ") and cap.err.count("\n") == 1


def test_a_run_that_failed_at_connect_reviews_as_no_flight(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 31: ``run`` against an endpoint that never answers wrote a recording that
    ``review`` rejected as "not a vtube_fleet recording" (the scene is logged only once the
    fleet is ready to arm). It reviews as ``no flight: failed at connect (…)``."""
    import socket

    mission = tmp_path / "mission.toml"
    text = (ROOT / "configs" / "mock_fleet.toml").read_text()
    assert "connect_timeout_s = 15.0" in text
    mission.write_text(text.replace("connect_timeout_s = 15.0", "connect_timeout_s = 0.5"))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a port nobody sends to
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "run"
    assert main(["run", str(mission), "--endpoints", f"udpin://127.0.0.1:{port}", "--out",
                 str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "did not connect within connect_timeout_s = 0.5 s" in err
    rrd = out / "recording.rrd"
    assert main(["review", str(rrd)]) == 0
    text_out = capsys.readouterr().out
    reason = json.loads((out / "summary.json").read_text())["reason"]
    assert f"no flight: failed at connect ({reason})\n" in text_out
    assert "did not connect within connect_timeout_s = 0.5 s" in reason
    assert main(["review", str(rrd), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["no_flight"] == f"failed at connect ({reason})" and doc["outcome"] == "failed"
    assert not list(out.glob("*.png"))  # nothing flown, nothing drawn
    d = load_recording(rrd)
    assert not d.scene and d.last_stage == "connecting" and d.kind == "fleet"
