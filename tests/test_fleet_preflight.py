"""Preflight: the inflated scenario against the vehicles' actual positions (Assumption 1 …),
reported per vehicle with its position and the numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.fleet.mission import load_mission
from vtube_fleet.fleet.supervisor import PreflightError, Supervisor, preflight_report
from vtube_fleet.link.mavlink import MavlinkLink

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mission():
    return load_mission(ROOT / "configs" / "mock_fleet.toml")


def names(n: int) -> list[str]:
    return [f"vehicle {i} (udpin://127.0.0.1:{14540 + i})" for i in range(n)]


def flown(mission, latency_s: float = 0.02):
    b = SafetyBudget.compute(mission.scenario.controller, period_s=0.05, latency_s=latency_s,
                             dead_time_s=0.3, t63_s=1.0)
    return b.inflate(mission.scenario.controller)


def test_slots_pass(mission) -> None:
    part, problems = preflight_report(mission, flown(mission), mission.slots, names(12))
    assert problems == [] and part is not None


def test_overlap_and_outside_are_named(mission) -> None:
    pos = mission.slots.copy()
    pos[3] = pos[2] + [0.0, 1.5]  # 1.5 m from vehicle 2 < 2 r_s' ≈ 1.98 m
    pos[7] = [3.0, 4.5]  # 0.5 m from the left leg < r_s'
    params = flown(mission)
    _, problems = preflight_report(mission, params, pos, names(12))
    text = "\n".join(problems)
    assert "vehicle 2 (udpin://127.0.0.1:14542) and vehicle 3 (udpin://127.0.0.1:14543) " \
           "overlap: distance 1.5 m" in text
    assert "vehicle 7 (udpin://127.0.0.1:14547) at (3.0, 4.5)" in text
    assert "distance to the left leg 0.58 m" in text
    assert f"r_s' = {params.r_s:.3f} m" in text
    assert "robot " not in text


def test_position_moved_into_obstacle(mission) -> None:
    pos = mission.slots.copy()
    pos[5] = [12.0, 1.0]
    _, problems = preflight_report(mission, flown(mission), pos, names(12), where="at 3 m")
    assert any("vehicle 5 (udpin://127.0.0.1:14545) at (12.0, 1.0) overlaps obstacle #1" in p
               and "(at 3 m," in p for p in problems)


def test_budget_that_makes_the_mission_infeasible(mission) -> None:
    # a huge latency → δ so large that the slots overlap and the side passages are too narrow
    _, problems = preflight_report(mission, flown(mission, latency_s=2.0), mission.slots,
                                   names(12))
    assert any("overlap" in p for p in problems)
    assert any("Assumption3'" in p or "Partition" in p for p in problems)


def test_infeasible_budget_refused_before_connecting(tmp_path: Path, mission) -> None:
    text = (ROOT / "configs" / "mock_fleet.toml").read_text().replace(
        "lost_after_s = 1.0", "lost_after_s = 1.0\nsafety_margin_m = 5.0")
    p = tmp_path / "m.toml"
    p.write_text(text)
    m = load_mission(p)
    links = [MavlinkLink(f"udpin://127.0.0.1:{20000 + i}") for i in range(m.count)]
    with pytest.raises(PreflightError, match=r"δ = 5.000 m .* cannot be partitioned"):
        Supervisor(m, links)


def test_too_many_links(mission) -> None:
    links = [MavlinkLink(f"udpin://127.0.0.1:{20000 + i}") for i in range(13)]
    with pytest.raises(PreflightError.__mro__[1], match="13 endpoints but the mission has only "
                                                        "12 slots"):
        Supervisor(mission, links)
    sup = Supervisor(mission, links[:4])
    assert len(sup.pilots) == 4 and sup.mission.count == 4
    np.testing.assert_allclose(sup.mission.slots, mission.slots[:4])
