"""`check` predicts `run` (issue 34 part 7).

By default `check MISSION` assumes what `run` measured on real PX4 SITL (L = 0.124 s, σ =
0.30 m) and prints the margin, "valid up to L ≤ … s, σ ≤ … m". The margin must hold for `run`:
at the printed figures `run`'s own preflight (the supervisor's functions: the budget's
refusals, the accuracy it waits for, ``preflight_report`` on the slots, the apex look-ahead)
accepts, 1 ms / 1 mm past them it refuses, and the refusal note names the figure that went
past. End to end, a mock fleet behind a slow relay is refused by `run` where the margin says
it would be.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from pathlib import Path

import pytest
from fleet_ports import free_ports
from missions import COMPACT_12_PATH, MISSION_TABLE, PX4_SITL_3, write_mission
from udp_relay import UdpRelay

from vtube_fleet.cli import main
from vtube_fleet.config.mission import Mission, load_mission
from vtube_fleet.fleet.budget import (
    PX4_SITL_ACCURACY_M,
    PX4_SITL_LATENCY_S,
    LinkMeasurement,
    budget_problems,
    mission_budget,
)
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.margin import margin_note, mission_margin, refusal_note
from vtube_fleet.fleet.preflight import preflight_report


def run_refuses(mission: Mission, measured: LinkMeasurement) -> list[str]:
    """What `run`'s preflight refuses with the vehicles on their slots and the links measured
    as ``measured``: the budget's refusals, an accuracy it would wait for in vain, the
    supervisor's ``preflight_report`` with the flown radii, the apex look-ahead."""
    cfg = mission.config
    out = list(budget_problems(mission, measured))
    if cfg.position_accuracy_m is None and measured.accuracy_m > cfg.max_position_accuracy_m:
        out.append("σ > max_position_accuracy_m")
    sc = mission.scenario
    flown = mission_budget(mission, measured).inflate(sc.controller)
    names = [f"vehicle {i}" for i in range(mission.count)]
    route, problems = preflight_report(mission, flown, mission.slots, names)
    out += problems  # (the apex look-ahead's too)
    if route is None and not problems:
        out.append("no partition")
    return out


def printed_margin(path: Path, capsys: pytest.CaptureFixture[str], *extra: str
                   ) -> tuple[int, str, float, float]:
    rc = main(["check", str(path), *extra])
    out = capsys.readouterr().out
    m = re.search(r"^margin: valid up to L ≤ ([0-9.]+) s, σ ≤ ([0-9.]+) m", out, re.M)
    assert m, out
    return rc, out, float(m.group(1)), float(m.group(2))


def test_check_and_run_agree_on_the_shipped_sitl_mission(
        capsys: pytest.CaptureFixture[str]) -> None:
    mission = load_mission(PX4_SITL_3)
    rc, out, lmax, smax = printed_margin(PX4_SITL_3, capsys)
    assert rc == 0 and "\nvalid\nmargin: " in out
    assert ("assumed measured latency 0.124 s (default: what PX4 SITL measures; --latency-s) "
            "+ latency_headroom_s 0.05 s, σ = 0.3 m (default") in out
    a = LinkMeasurement(PX4_SITL_LATENCY_S, 0.0, PX4_SITL_ACCURACY_M)
    assert run_refuses(mission, a) == []  # same verdict at check's assumptions
    assert PX4_SITL_LATENCY_S < lmax and PX4_SITL_ACCURACY_M < smax
    # the printed margins hold: run accepts at them, refuses 1 ms / 1 mm past them
    inside_l, outside_l = (dataclasses.replace(a, position_age_s=x) for x in (lmax, lmax + 1e-3))
    inside_s, outside_s = (dataclasses.replace(a, accuracy_m=x) for x in (smax, smax + 1e-3))
    assert run_refuses(mission, inside_l) == [] and run_refuses(mission, inside_s) == []
    assert run_refuses(mission, outside_l) and run_refuses(mission, outside_s)
    # … and check at those figures says the same
    for flag, x, ok in (("--latency-s", lmax, 0), ("--latency-s", lmax + 1e-3, 2),
                        ("--accuracy-m", smax, 0), ("--accuracy-m", smax + 1e-3, 2)):
        assert main(["check", str(PX4_SITL_3), flag, f"{x:.4f}", "--no-fixes"]) == ok
        capsys.readouterr()
    # the refusal names the figure past the margin that check printed
    assert refusal_note(mission, outside_l) == (
        f"measured L = {lmax + 1e-3:.3f} s > the margin L ≤ {lmax:.3f} s that check printed")
    assert refusal_note(mission, outside_s) == (
        f"measured σ = {smax + 1e-3:.3f} m > the margin σ ≤ {smax:.3f} m that check printed")
    # both at their margin at once: each inside, together past δ_max
    both = LinkMeasurement(lmax, 0.0, smax)
    assert run_refuses(mission, both)
    note = refusal_note(mission, both)
    assert "are each within the margin" in note and "but together give δ = " in note, note
    margin = mission_margin(mission)
    delta = mission_budget(mission, both).delta_m
    assert delta > margin.delta_max_m >= mission_budget(mission, inside_l).delta_m
    assert f"both together while δ ≤ {margin.delta_shown_m:.3f} m" in out
    print(f"\npx4_sitl_3: {out.splitlines()[-3]}")


def test_the_budget_refusal_says_what_check_would_have_said(
        capsys: pytest.CaptureFixture[str]) -> None:
    """What refuses just past each figure is printed with the margin."""
    rc, out, lmax, smax = printed_margin(PX4_SITL_3, capsys)
    assert f"  past L ≤ {lmax:.3f} s: Budget refused: link latency L = " in out
    assert "> max_latency_s = 250 ms" in out  # on this mission the link binds, not the tube
    assert f"  past σ ≤ {smax:.3f} m: Assumption1 violated: robots 0 and 1 overlap" in out


TAPERED_AUTO = """
[tube]
p_h0 = [0.0, 18.0]
p_h1 = [50.0, 13.0]
p_r0 = [0.0, -18.0]
p_r1 = [50.0, -13.0]

[partition]
apex_distance = "auto"

[[obstacles]]
center = [20.0, 0.5]
radius = 0.6

[[obstacles]]
center = [36.0, -2.0]
radius = 0.5

[robots]
r_s = 0.3
r_a = 1.0
v_min = 0.3
v_max = 1.8
positions = [[3.0, -9.0], [3.0, -4.5], [3.0, 0.0], [3.0, 4.5], [3.0, 9.0]]

[controller]
v = 1.2
v_max_prime = 0.5
"""


def test_the_margin_holds_with_auto_apex_distances(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """With "auto" apex distances the partition is planned again for every δ: the margin is
    found with the same planning, and holds for run's preflight."""
    mission = write_mission(tmp_path, TAPERED_AUTO + MISSION_TABLE)
    path = tmp_path / "mission.toml"
    t0 = time.perf_counter()
    rc, out, lmax, smax = printed_margin(path, capsys)
    took = time.perf_counter() - t0
    assert rc == 0
    a = LinkMeasurement(PX4_SITL_LATENCY_S, 0.0, PX4_SITL_ACCURACY_M)
    for x, ok in ((lmax, True), (lmax + 1e-3, False)):
        assert (run_refuses(mission, dataclasses.replace(a, position_age_s=x)) == []) is ok
    for x, ok in ((smax, True), (smax + 1e-3, False)):
        assert (run_refuses(mission, dataclasses.replace(a, accuracy_m=x)) == []) is ok
    print(f"\nauto apex: {out.splitlines()[-3]} (check took {took:.2f} s)")


def test_no_margin_when_check_refuses_and_figures_the_mission_fixes(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the 12-vehicle fixture is sized for a lag-only budget: refused at SITL's figures
    assert main(["check", str(COMPACT_12_PATH), "--no-fixes"]) == 2
    out = capsys.readouterr().out
    m = re.search(r"margin: none at the assumed figures \(L = 0\.124 s, σ = 0\.300 m → δ = "
                  r"[0-9.]+ m\): the slots validate only while δ ≤ ([0-9.]+) m", out)
    assert m, out
    mission = load_mission(COMPACT_12_PATH)
    assert refusal_note(mission, LinkMeasurement(0.1, 0.0, 0.29)).startswith(
        "check refuses this mission too at its assumed figures")
    # δ ≤ the printed bound validates (a fixed δ through safety_margin_m), 1 mm more does not
    delta_max = float(m.group(1))
    for delta, ok in ((delta_max, 0), (delta_max + 1e-3, 2)):
        text = COMPACT_12_PATH.read_text().replace("[mission]",
                                                   f"[mission]\nsafety_margin_m = {delta}")
        (tmp_path / "c.toml").write_text(text)
        assert main(["check", str(tmp_path / "c.toml"), "--no-fixes"]) == ok
        capsys.readouterr()
    # a mission that fixes L and σ: they are not measured, so no margin in them
    text = PX4_SITL_3.read_text().replace(
        "[mission]", "[mission]\nlatency_s = 0.1\nposition_accuracy_m = 0.2")
    (tmp_path / "f.toml").write_text(text)
    assert main(["check", str(tmp_path / "f.toml")]) == 0
    out = capsys.readouterr().out
    assert ("margin: valid up to L = 0.1 s fixed (latency_s), σ = 0.2 m fixed "
            "(position_accuracy_m)") in out


def test_a_refusal_inside_the_margin_blames_the_positions() -> None:
    mission = load_mission(PX4_SITL_3)
    margin = mission_margin(mission)
    note = margin_note(margin, mission, LinkMeasurement(0.1, 0.0, 0.29))
    assert note.endswith("what refuses is where the vehicles are, not the link"), note
    assert math.isfinite(margin.delta_max_m)


# ----------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.timeout(120)
async def test_run_refuses_past_the_margin_as_check_predicts(tmp_path: Path) -> None:
    """The shipped SITL mission on mock vehicles behind a 120 ms relay (both ways): `run`
    measures L past the margin `check` printed and refuses before arming; the note names L."""
    mission = load_mission(PX4_SITL_3)
    margin = mission_margin(mission)
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(3),
                          seed=5) as fleet:
        ports = fleet.ports
        relay_to = free_ports(3, avoid=ports)  # the relay's fleet side: not the vehicles' GCS
        async with UdpRelay([ports.vehicle_port(i) for i in range(3)],
                            [ports.gcs_port(i) for i in range(3)],
                            [relay_to.gcs_port(i) for i in range(3)], delay_s=0.12) as relay:
            result = await fly(mission, endpoints=relay.endpoints, sysids=[1, 2, 3],
                               out_dir=tmp_path)
        assert not any(v.armed for v in fleet.vehicles)
    assert result.exit_code == 2 and "nothing armed" in result.reason, result.reason
    m = result.summary["measured"]
    measured = LinkMeasurement(m["position_age_p95_s"], m["setpoint_delay_s"], m["accuracy_m"])
    assert measured.latency_s > margin.latency_shown_s
    note = refusal_note(mission, measured)
    assert note.startswith(f"measured L = {measured.latency_s:.3f} s > the margin L ≤ "
                           f"{margin.latency_shown_s:.3f} s that check printed"), note
    assert note in result.reason  # run's refusal says which measured figure went past
    print(f"\n120 ms relay: {result.reason}")
