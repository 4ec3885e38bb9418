"""Neighbour pairs: pairs_within against brute force (up to 10,000 robots) and the Verlet list."""

import tracemalloc

import numpy as np
import pytest

from vtube_fleet.core.neighbours import VerletPairs, pairs_within


def _brute(p: np.ndarray, radius: float) -> set[tuple[int, int]]:
    """All pairs i < j within radius, by blocks of rows (no M×M array)."""
    out: set[tuple[int, int]] = set()
    ok = np.isfinite(p).all(axis=1)
    M = p.shape[0]
    for a in range(0, M, 256):
        blk = p[a:a + 256]
        d = np.hypot(blk[:, None, 0] - p[None, :, 0], blk[:, None, 1] - p[None, :, 1])
        i, j = np.nonzero(d <= radius)
        i = i + a
        keep = (i < j) & ok[i] & ok[j]
        out.update(zip(i[keep].tolist(), j[keep].tolist(), strict=True))
    return out


def _as_set(I, J) -> set[tuple[int, int]]:
    return set(zip(I.tolist(), J.tolist(), strict=True))


@pytest.mark.parametrize("M", [0, 1, 2, 7, 47, 48, 300])
def test_pairs_within_matches_brute_force(M):
    rng = np.random.default_rng(M)
    p = rng.uniform(0, 6, (M, 2))
    if M > 5:
        p[3] = p[4]  # two robots at the same place
        p[5] = np.nan  # an exited robot
    I, J = pairs_within(p, 0.75)
    assert _as_set(I, J) == _brute(p, 0.75)
    assert len(_as_set(I, J)) == len(I)  # no duplicates
    assert np.all(I < J)
    assert I.dtype == np.int64 and J.dtype == np.int64
    assert not I.flags.writeable and not J.flags.writeable
    order = np.lexsort((J, I))
    assert np.array_equal(order, np.arange(len(I)))


def test_pairs_within_includes_the_radius_itself():
    p = np.array([[0.0, 0.0], [0.75, 0.0], [0.0, 0.7500001]])
    assert _as_set(*pairs_within(p, 0.75)) == {(0, 1)}
    p = np.tile(p, (20, 1)) + np.repeat(np.arange(20) * 10.0, 3)[:, None]  # KD-tree path
    assert len(pairs_within(p, 0.75)[0]) == 20


def test_pairs_within_10000_robots_in_a_long_tube_without_quadratic_memory():
    rng = np.random.default_rng(7)
    M = 10_000
    p = np.column_stack([rng.uniform(0, 2000, M), rng.uniform(-3, 3, M)])
    p[::997] = np.nan
    tracemalloc.start()
    try:
        I, J = pairs_within(p, 0.75)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6  # an M×M float array alone would be 800 MB
    assert len(I) > 1000
    assert _as_set(I, J) == _brute(p, 0.75)


def test_pairs_within_rejects_bad_input():
    with pytest.raises(ValueError):
        pairs_within(np.zeros((3, 3)), 1.0)
    with pytest.raises(ValueError):
        pairs_within(np.zeros((3, 2)), -1.0)


def test_verlet_candidates_always_cover_the_pairs_and_rebuild_rarely():
    rng = np.random.default_rng(3)
    M, radius, skin = 150, 0.75, 0.3
    p = rng.uniform(0, 10, (M, 2))
    vel = rng.normal(size=(M, 2))
    vl = VerletPairs(radius, skin)
    steps = 400
    for _ in range(steps):
        Ic, Jc = vl.candidates(p)
        exact = _brute(p, radius)
        assert exact <= _as_set(Ic, Jc)
        Ie, Je = vl.pairs(p)
        assert _as_set(Ie, Je) == exact
        assert np.all(Ie < Je)
        p = p + 0.002 * vel  # ≤ ~1 cm per step
    assert 2 <= vl.builds < steps / 10


def test_verlet_returns_the_same_arrays_between_builds():
    p = np.random.default_rng(0).uniform(0, 5, (60, 2))
    vl = VerletPairs(0.75, 0.4)
    a = vl.candidates(p)
    b = vl.candidates(p + 0.1)
    assert a[0] is b[0] and a[1] is b[1] and vl.builds == 1
    c = vl.candidates(p + 0.25)  # moved more than skin/2
    assert c[0] is not a[0] and vl.builds == 2


def test_verlet_rebuilds_when_robots_exit_or_the_count_changes():
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 4, (80, 2))
    vl = VerletPairs(0.75, 0.3)
    vl.candidates(p)
    q = p.copy()
    q[10] = np.nan  # robot 10 exits
    I, J = vl.candidates(q)
    assert vl.builds == 2
    assert 10 not in I and 10 not in J
    assert _as_set(I, J) >= _brute(q, 0.75)
    vl.candidates(q)  # same NaN set, no movement: no rebuild
    assert vl.builds == 2
    q[:, 0] += 0.1  # small move with NaN rows present: still no rebuild
    vl.candidates(q)
    assert vl.builds == 2
    q[20] += 0.2  # a finite robot moved more than skin/2
    vl.candidates(q)
    assert vl.builds == 3
    vl.candidates(q[:50])  # robots removed (compacted arrays)
    assert vl.builds == 4
    with pytest.raises(ValueError):
        VerletPairs(0.0, 0.1)
