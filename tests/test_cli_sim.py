"""``vtube-fleet check`` and ``vtube-fleet sim`` via the CLI dispatcher and the console script."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from vtube_fleet.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper.toml"
ROBOTARIUM = ROOT / "configs" / "robotarium.toml"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

SUMMARY_KEYS = {
    "robots", "exited", "last_exit_s", "median_exit_s", "min_pair_distance_m",
    "min_obstacle_center_distance_m", "min_left_leg_distance_m", "min_right_leg_distance_m",
    "min_speed_m_s", "max_speed_m_s", "steps", "dt_s", "wall_s", "violations",
}


def _toml(d: dict) -> str:
    """A tiny TOML writer for the scenario documents used here."""
    def val(v: object) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(x)}" for k, x in v.items()) + " }"
        return repr(v)

    lines = []
    for name, table in d.items():
        if isinstance(table, list):
            for item in table:
                lines.append(f"[[{name}]]")
                lines += [f"{k} = {val(v)}" for k, v in item.items()]
        else:
            lines.append(f"[{name}]")
            lines += [f"{k} = {val(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture
def paper_data() -> dict:
    with open(PAPER, "rb") as fh:
        return tomllib.load(fh)


def test_check_paper_prints_partition(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PAPER)]) == 0
    out = capsys.readouterr().out
    assert "sub-tubes: 15" in out
    assert "T_o1 " in out and "T_o15" in out
    assert "Remark 5 used by obstacle(s): #2 (left)" in out
    assert "120 single_integrator" in out
    assert out.rstrip().endswith("valid")


def test_check_robotarium(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(ROBOTARIUM)]) == 0
    out = capsys.readouterr().out
    assert "sub-tubes: 7" in out and "Remark 5 used by obstacle(s): none" in out
    assert "7 unicycle" in out and "NID s = 0.02 m" in out


def test_check_invalid_scenario_lists_violations(
    tmp_path: Path, paper_data: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    paper_data["controller"]["v"] = 2.5  # v + v'_max = 4.0 > v_max = 3.5
    paper_data["robots"]["grid"]["origin"] = [9.0, -4.4]  # overlaps obstacle #1
    cfg = tmp_path / "bad.toml"
    cfg.write_text(_toml(paper_data))
    assert main(["check", str(cfg)]) == 2
    cap = capsys.readouterr()
    out = cap.out
    assert "INVALID" in out
    assert "[Constraint1]" in out and "4" in out
    assert "[Assumption1]" in out
    # the report, and one line on stderr as every user error ends (README), with the numbers
    n = out.count("\n  [")
    assert n >= 2
    assert cap.err == (f"error: {cfg}: invalid scenario: [Constraint1] Constraint1 violated: "
                       f"v + v'_max = 4.0 > v_max = 3.5 (v = 2.5, v'_max = 1.5) (and {n - 1} "
                       f"more violation"
                       f"{'s' if n > 2 else ''} above)\n")


def test_user_errors_are_one_line(tmp_path: Path, paper_data: dict,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    paper_data["robots"]["r_s"] = "abc"
    cfg = tmp_path / "typo.toml"
    cfg.write_text(_toml(paper_data))
    for argv in (["check", str(cfg)], ["sim", str(cfg), "--out", str(tmp_path / "o")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err == f'error: {cfg}: [robots].r_s: expected a number, got "abc"\n'
    assert main(["sim", str(tmp_path / "missing.toml")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["sim", str(PAPER), "--robots", "500", "--out", str(tmp_path / "o")]) == 2
    assert "--robots must be between 1 and 120" in capsys.readouterr().err
    for argv, message in ((["--robots", "0"], "argument --robots: must be >= 1, got 0"),
                          (["--dt", "-1"], "argument --dt: must be >= 1e-06, got -1.0")):
        with pytest.raises(SystemExit) as info:  # declared options: refused by the parser
            main(["sim", str(PAPER), *argv, "--out", str(tmp_path / "o")])
        assert info.value.code == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_sim_writes_all_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    argv = ["sim", str(PAPER), "--out", str(out), "--robots", "12", "--dt", "0.002",
            "--duration", "25", "--record-every", "5"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "robots 12, exited 12" in printed and "violations 0" in printed
    s = json.loads((out / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(s)
    assert s["robots"] == 12 and s["exited"] == 12 and s["violations"] == 0
    assert s["dt_s"] == 0.002 and s["record_every"] == 5
    with np.load(out / "trajectory.npz") as z:
        t, pos, vel = z["t"], z["pos"], z["vel"]
        assert pos.shape == (t.size, 12, 2) and vel.shape == pos.shape
        np.testing.assert_allclose(np.diff(t)[:-1], 0.01)  # + the final state
        assert t[-1] == pytest.approx(s["t_end_s"]) and 0 < t[-1] - t[-2] <= 0.01
        assert np.isnan(pos[-1]).sum() > 0  # exited robots are NaN
        grid = np.array([[0.5, -4.4 + 0.8 * j] for j in range(12)])
        np.testing.assert_allclose(pos[0], grid)
    with np.load(out / "metrics.npz") as z:
        assert z["t"].size == s["steps"] and z["violation"].sum() == 0
    for png in ("safety.png", "snapshots.png"):
        assert (out / png).read_bytes()[:8] == PNG_MAGIC


def _outsider_exit_check(out: Path, config: Path) -> tuple[int, int]:
    """Judge the exits as someone without vtube_fleet would: from the TOML's tube, the
    summary.json and the raw trajectory.npz → (robots absent or past the line in the last
    frame, robots past it at their recorded exit point)."""
    with config.open("rb") as fh:
        doc = tomllib.load(fh)
    ph0, ph1, pr1 = (np.array(doc["tube"][k], dtype=float) for k in ("p_h0", "p_h1", "p_r1"))
    eps_0 = doc["controller"]["eps_0"]
    along = pr1 - ph1
    normal = np.array([along[1], -along[0]]) / np.hypot(*along)
    if normal @ (ph1 - ph0) < 0:  # pointing out of the tube, through the finishing line
        normal = -normal
    s = json.loads((out / "summary.json").read_text())
    with np.load(out / "trajectory.npz") as z:
        t, pos, exit_t, exit_pos = z["t"], z["pos"], z["exit_time_s"], z["exit_pos"]
    assert t[-1] == pytest.approx(s["t_end_s"])  # the last frame is the final state
    last = pos[-1]
    absent = np.isnan(last[:, 0])
    past = (last - pr1) @ normal >= -eps_0  # (TraCondition): within eps_0 of the line or past
    exited = ~np.isnan(exit_t)
    assert exited.sum() == s["exited"]
    # every robot the summary counts as exited left before (absent) or is past the line now;
    # every other robot is still in the tube, before the line
    assert np.all((absent | past)[exited]) and not np.any((absent | past)[~exited])
    assert np.all(exit_t[absent & exited] < t[-1]) and np.all(exit_t[past & ~absent] == t[-1])
    crossed = (exit_pos[exited] - pr1) @ normal >= -eps_0
    return int((absent | past).sum()), int(crossed.sum())


@pytest.mark.parametrize("duration", [None, 16.24])
def test_trajectory_npz_shows_every_exit_the_summary_counts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], duration: float | None) -> None:
    """Issue 31: the trajectory stopped one step before the end, so an outside checker found
    119/120 robots out of the tube where the summary said 120. The last frame is now the final
    state: the run that ends with the last exit, and one that ends by its duration at the very
    step a robot reaches the line (16.24 s: it counts, and is past the line)."""
    out = tmp_path / "run"
    argv = ["sim", str(PAPER), "--out", str(out), "--robots", "12", "--dt", "0.002",
            "--no-plots", "--no-rerun", "--quiet"]
    if duration is not None:
        argv += ["--duration", str(duration)]
    code = main(argv)
    capsys.readouterr()
    s = json.loads((out / "summary.json").read_text())
    assert code == (0 if duration is None else 1)
    assert s["exited"] == (12 if duration is None else 4)
    assert s["last_exit_s"] == pytest.approx(s["t_end_s"])  # someone exits in the last step
    assert _outsider_exit_check(out, PAPER) == (s["exited"], s["exited"])


def test_sim_not_finished_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "short"
    assert main(["sim", str(PAPER), "--out", str(out), "--robots", "5", "--duration", "0.2",
                 "--no-plots", "--quiet"]) == 1
    s = json.loads((out / "summary.json").read_text())
    assert s["exited"] == 0 and s["steps"] == 200 and not s["all_exited"]
    assert not (out / "safety.png").exists()
    assert "duration reached" not in capsys.readouterr().err  # --quiet: no progress bar


def test_sim_refuses_too_many_steps_from_the_command_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--dt and --duration are each within bounds, together 8.6e10 steps: refused in one line
    before anything is simulated (the scenario file's [sim] has the same bound)."""
    out = tmp_path / "long"
    assert main(["sim", str(PAPER), "--out", str(out), "--dt", "1e-6", "--duration", "86400",
                 "--no-rerun", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "1e8 steps" in err and "8.64e+10" in err
    assert not (out / "summary.json").exists()


def test_sim_old_controller_breaks_min_speed(tmp_path: Path) -> None:
    out = tmp_path / "old"
    # (Oldcontroller) on a reduced paper scenario: still safe, but slower than v_min somewhere
    code = main(["sim", str(PAPER), "--controller", "old", "--out", str(out), "--robots", "40",
                 "--dt", "0.002", "--duration", "30", "--no-plots", "--quiet"])
    s = json.loads((out / "summary.json").read_text())
    assert code == 1 and s["controller"] == "old" and s["exited"] == 40
    assert s["min_speed_m_s"] < 0.5
    assert s["violations_by_condition"]["pair"] == 0
    assert s["violations_by_condition"]["obstacle"] == 0


def test_console_script_robotarium(tmp_path: Path) -> None:
    exe = shutil.which("vtube-fleet")
    cmd = [exe] if exe else [sys.executable, "-m", "vtube_fleet"]
    out = tmp_path / "rob"
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.run([*cmd, "sim", str(ROBOTARIUM), "--out", str(out)], capture_output=True,
                          text=True, timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "robots 7, exited 7" in proc.stdout and "violations 0" in proc.stdout
    assert "all robots exited" in proc.stderr  # the progress bar's final line
    s = json.loads((out / "summary.json").read_text())
    assert s["model"] == "unicycle" and s["violations"] == 0 and s["violations_center"] == 0
    with np.load(out / "trajectory.npz") as z:
        assert {"control_pos", "control_vel", "heading"} <= set(z.files)


# ----------------------------------------------------------------------------------------------
# the authors' geometry (issue 11, item 4) and the integrator option
# ----------------------------------------------------------------------------------------------
AUTHORS = ROOT / "configs" / "paper_authors.toml"


def test_authors_geometry_is_refused_by_check(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(AUTHORS)]) == 2
    cap = capsys.readouterr()
    out = cap.out
    assert "INVALID" in out and "Assumption 3'" in out and "obstacle #3" in out
    # issue 31: the report on stdout, then the one error line (cause and numbers) on stderr
    assert cap.err.count("\n") == 1 and cap.err.startswith(
        f"error: {AUTHORS}: invalid scenario: [Partition] Partition failed: obstacle #3 at "
        "(20.0, -2.0) r_o=0.9: ")
    assert "ξ = 17.843 < ξ_s + 2 r_a = 20.65" in cap.err


def test_authors_geometry_sim_needs_uncertified(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    assert main(["sim", str(AUTHORS), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Assumption 3'" in err and "obstacle #3" in err
    assert not out.exists()


def test_authors_geometry_uncertified_sim(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A shortened run (the full 15 s, 120 robots with RK4 is docs/config.md's measurement)."""
    from vtube_fleet.recording.reader import load_recording

    out = tmp_path / "authors"
    rc = main(["sim", str(AUTHORS), "--uncertified", "--duration", "1.5", "--robots", "40",
               "--out", str(out), "--no-plots", "--quiet"])
    assert rc == 1  # robots are still in the tube after 1.5 s
    printed = capsys.readouterr().out
    assert "certified: false (triangles about O)" in printed and "Assumption 3'" in printed
    assert "(rk4)" in printed
    s = json.loads((out / "summary.json").read_text())
    assert s["certified"] is False and s["triangles_about"] == "O"
    assert s["integrator"] == "rk4" and s["sub_tubes"] == 16 and s["remark5"] == []
    failed = s["failed_conditions"]
    assert failed and any("Assumption 3'" in f["message"] and "obstacle #3" in f["message"]
                          for f in failed)
    # and what the flown partition itself breaks: a side tube of #4, O' for every triangle
    assert any(f["condition"] == "Assumption3'" and "left of obstacle #4" in f["message"]
               for f in failed)
    assert sum(f["condition"] == "ExtObstacle" for f in failed) == 5
    assert s["violations"] == 0 and s["steps"] == 1500
    meta = load_recording(out / "recording.rrd").meta
    assert meta["certified"] is False and meta["failed_conditions"] == failed
    assert meta["integrator"] == "rk4"


def test_certified_scenario_says_so(tmp_path: Path) -> None:
    out = tmp_path / "p"
    assert main(["sim", str(PAPER), "--uncertified", "--robots", "3", "--duration", "0.05",
                 "--integrator", "euler", "--out", str(out), "--no-plots", "--no-rerun",
                 "--quiet"]) == 1
    s = json.loads((out / "summary.json").read_text())
    assert s["certified"] is True and s["failed_conditions"] == [] and s["integrator"] == "euler"
    assert s["triangles_about"] == "O'"


def test_run_never_accepts_uncertified(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", str(ROOT / "configs" / "mock_fleet.toml"), "--uncertified"])
    assert exc.value.code == 2
    assert "unrecognized arguments: --uncertified" in capsys.readouterr().err
