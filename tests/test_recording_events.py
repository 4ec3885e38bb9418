"""The recorder's pure derivations (vtube_fleet.recording.events): the decimation merge rule,
phase changes told once, exits from phases, from disappearing rows and from the owner."""

from __future__ import annotations

import math

import numpy as np

from vtube_fleet.recording.events import ChangeDetector, announced_phase, merge_metric


def test_merge_keeps_the_extremes_by_key() -> None:
    assert merge_metric("min_pair_distance_m", 1.0, 0.5) == 0.5
    assert merge_metric("max_speed_m_s", 1.0, 0.5) == 1.0
    assert merge_metric("tick_duration_s", 0.01, 0.02) == 0.02
    assert merge_metric("link_latency_s", 0.03, 0.02) == 0.03
    assert merge_metric("battery_v", 12.0, 11.0) == 11.0  # no rule: the newer value
    assert merge_metric("min_x", math.nan, 2.0) == 2.0
    assert merge_metric("min_x", 2.0, math.nan) == 2.0


def test_phase_changes_are_told_once_and_exits_come_from_the_exited_phase() -> None:
    d = ChangeDetector()
    ids = np.array([1, 2])
    pos = np.zeros((2, 2))
    ch, ex = d.update(ids, pos, ["in_tube", "in_tube"])
    assert ch is not None and ch.texts == ["vehicle 1: in_tube", "vehicle 2: in_tube"]
    assert ex is None
    assert d.update(ids, pos, ["in_tube", "in_tube"]) == (None, None)  # nothing changed
    d.announced(2, "in_tube → exited (crossed the finishing line)")  # the owner told it
    ch, ex = d.update(ids, pos, ["lost", "exited"])
    assert ch is not None and ch.ids == [1] and ch.levels == ["WARN"]  # 2's change not repeated
    assert ch.texts == ["vehicle 1: in_tube → lost"]
    assert ex is not None and ex.ids == [2] and not ex.untold  # its exit was told
    assert d.explicit_exits([2]) is None  # already reported: never twice


def test_exits_without_phases_are_rows_that_disappear() -> None:
    d = ChangeDetector()
    ids = np.array([0, 1, 2])
    pos = np.zeros((3, 2))
    assert d.update(ids, pos, None) == (None, None)
    pos[1] = np.nan
    _, ex = d.update(ids, pos, None)
    assert ex is not None and ex.ids == [1] and ex.untold
    _, ex = d.update(np.array([0]), np.zeros((1, 2)), None)  # row 2 gone from the ids
    assert ex is not None and ex.ids == [2]
    quiet = ChangeDetector(detect_exits=False)  # the owner decides exits
    quiet.update(ids, np.zeros((3, 2)), None)
    assert quiet.update(ids, np.full((3, 2), np.nan), None) == (None, None)
    ex = quiet.explicit_exits([0, 1])
    assert ex is not None and ex.ids == [0, 1]


def test_announced_phase_reads_only_a_phase_change() -> None:
    assert announced_phase("in_tube → exited (why)") == "exited"
    assert announced_phase("- → takeoff") == "takeoff"
    assert announced_phase("link lost → nowhere") is None
    assert announced_phase("held, then landed") is None
