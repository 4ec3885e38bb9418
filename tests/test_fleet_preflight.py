"""Preflight: the inflated scenario against the vehicles' actual positions (Assumption 1 …),
reported per vehicle with its position and the numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fleet_ports import free_ports
from missions import COMPACT_12, compact_12, write_mission

from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.preflight import PreflightError, preflight_report
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.link.mavlink import MavlinkLink


@pytest.fixture(scope="module")
def mission():
    return compact_12()  # sized for the lag-only budget these unit tests compute


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
    # the flown radius is r_s' in every clause; r_s stays the physical one
    assert f"overlap: distance 1.5 m ≤ 2 r_s' = {2 * params.r_s:.2f} m" in text
    assert f"< r_s' = {params.r_s:.3f} m" in text
    assert f"the physical r_s = {mission.scenario.robots.r_s:g} m + δ" in text
    assert "2 r_s =" not in text and "< r_s =" not in text


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
    text = COMPACT_12.replace("lost_after_s = 1.0", "lost_after_s = 1.0\nsafety_margin_m = 5.0")
    m = write_mission(tmp_path, text)
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


async def test_the_measured_accuracy_refuses_a_tight_mission_before_arming(tmp_path) -> None:
    """Mock vehicles with PX4 SITL's estimate (they report σ = 0.29 m): the full budget
    δ = (v'_max + D)·delay + 2σ makes the 2.5 m slots of COMPACT_12 overlap; nothing arms and
    the error names the accuracy, r_s' and the slots with their distance and the need."""
    m = write_mission(tmp_path, COMPACT_12).with_vehicles(3)
    async with mock_fleet(m, boot_time_scale=0.3, port_scheme=free_ports(3), seed=7) as fleet:
        result = await fly(m, endpoints=fleet.endpoints, sysids=[1, 2, 3], out_dir=tmp_path)
        assert not any(v.armed for v in fleet.vehicles)
    assert result.exit_code == 2 and result.outcome == "failed"
    r = result.reason
    assert "nothing armed" in r and "σ = 0.29 m" in r and "r_s' = " in r
    assert "slot 0 (" in r and "and slot 1 (" in r and "overlap: distance 2.5 m" in r
    print(f"\n{r}")


async def test_a_port_in_use_is_named_at_once_not_as_a_timeout(tmp_path) -> None:
    """An endpoint whose port another program holds (a ground station, another run): the
    run fails at once ("could not connect", not "did not connect within connect_timeout_s")
    and names the port and the cause."""
    import socket

    m = write_mission(tmp_path, COMPACT_12).with_vehicles(1)
    port = free_ports(1).gcs_base
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
        held.bind(("127.0.0.1", port))
        result = await fly(m, endpoints=[f"udpin://127.0.0.1:{port}"], sysids=[1],
                           out_dir=tmp_path)
    assert result.exit_code == 2 and result.outcome == "failed", result.reason
    assert result.reason.startswith("1 of 1 vehicles could not connect: "), result.reason
    assert f"cannot bind udpin://127.0.0.1:{port}: Address already in use" in result.reason
    texts = [e["text"] for e in result.summary["events"]]
    assert any(t.endswith(": no vehicle is airborne") for t in texts), texts
    assert not any("holds, then lands" in t for t in texts), texts


async def test_connect_window_and_one_deadline_name_every_vehicle(tmp_path, monkeypatch) -> None:
    """Links connect at most CONNECT_WINDOW at a time, all within connect_timeout_s: silent
    endpoints end the run with one error naming each (waited for, or never reached)."""
    import vtube_fleet.fleet.preflight as preflight_module

    monkeypatch.setattr(preflight_module, "CONNECT_WINDOW", 1)
    text = "\n".join(line for line in COMPACT_12.splitlines()
                     if not line.startswith("connect_timeout_s"))
    m = write_mission(tmp_path, text + "\nconnect_timeout_s = 0.5\n").with_vehicles(3)
    ports = free_ports(3)
    endpoints = [f"udpin://127.0.0.1:{ports.gcs_base + i}" for i in range(3)]
    result = await fly(m, endpoints=endpoints, sysids=[1, 2, 3], out_dir=tmp_path)
    assert result.exit_code == 2 and result.outcome == "failed"
    r = result.reason
    assert "3 of 3 vehicles did not connect within connect_timeout_s = 0.5 s" in r
    assert "no HEARTBEAT within" in r
    assert r.count("not tried: connect_timeout_s = 0.5 s ran out while connecting the "
                   "others (at most 1 at a time)") == 2


async def test_a_long_list_of_vehicle_problems_is_cut_in_the_error_kept_in_the_events(
        tmp_path, caplog) -> None:
    """12 silent endpoints: the one-line error shows PROBLEMS_SHOWN of the 12 and counts the
    rest; the summary's events keep every vehicle's problem (at 1,000 vehicles such a list was
    146 kB on one line), and the terminal is not flooded with one warning per vehicle."""
    import json
    import logging

    caplog.set_level(logging.DEBUG)

    from vtube_fleet.errors import PROBLEMS_SHOWN

    text = "\n".join(line for line in COMPACT_12.splitlines()
                     if not line.startswith("connect_timeout_s"))
    m = write_mission(tmp_path, text + "\nconnect_timeout_s = 0.5\n")
    ports = free_ports(12)
    endpoints = [f"udpin://127.0.0.1:{ports.gcs_base + i}" for i in range(12)]
    result = await fly(m, endpoints=endpoints, sysids=list(range(1, 13)), out_dir=tmp_path)
    assert result.exit_code == 2 and result.outcome == "failed"
    r = result.reason
    assert "12 of 12 vehicles did not connect within connect_timeout_s = 0.5 s" in r
    assert r.count("no HEARTBEAT within") == PROBLEMS_SHOWN == 10
    assert r.endswith("; … and 2 more (every one is in the summary's events)"), r
    events = json.loads((tmp_path / "summary.json").read_text())["events"]
    told = [e["text"] for e in events if e["level"] == "error" and "no HEARTBEAT" in e["text"]
            and "did not connect" not in e["text"]]  # not the final error itself
    assert len(told) == 12
    assert all(any(ep in t for t in told) for ep in endpoints)
    per_vehicle = [rec for rec in caplog.records if "no HEARTBEAT within" in rec.getMessage()
                   and "did not connect" not in rec.getMessage()]
    assert len(per_vehicle) == 12  # every one logged, so the test sees the logger ...
    assert all(rec.levelno == logging.DEBUG for rec in per_vehicle)  # ... below the terminal


def test_join_problems_counts_what_it_leaves_out() -> None:
    from vtube_fleet.errors import join_problems

    assert join_problems(["a", "b"]) == "a; b"
    assert join_problems(list("abcd"), shown=2) == "a; b; … and 2 more (every one is in the " \
                                                   "summary's events)"
    assert join_problems(list("abc"), shown=3, rest="x") == "a; b; c"
