"""Neighbour pairs within a radius, without O(M²) memory.

* :func:`pairs_within` — all pairs (i < j) with ‖p_i − p_j‖ ≤ radius (a KD-tree; brute force
  for a handful of robots). Rows with a NaN coordinate (robots that exited) are ignored.
* :class:`VerletPairs` — a Verlet-style cached candidate list for the simulator: the KD-tree
  runs only when some robot has moved more than skin/2 since the last build (or the set of NaN
  rows changed), so that every pair within ``radius`` is always among the candidates.
  :meth:`VerletPairs.candidates` returns that superset (enough for the controller: V_m,ij is
  exactly 0 beyond r_s + r_a); :meth:`VerletPairs.pairs` filters it to exactly the pairs within
  ``radius``.

Returned index arrays are read-only int64 arrays, sorted by (i, j).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["VerletPairs", "pairs_within"]

_BRUTE_MAX = 48  # below this many robots a triangular brute force beats building a KD-tree


def _readonly(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.setflags(write=False)
    return arrays


def _as_points(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"positions must have shape (M, 2), got {p.shape}")
    return p


def pairs_within(p: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (I[n], J[n]) with I < J and ‖p_I − p_J‖ ≤ radius, sorted; NaN rows ignored.

    Memory is O(M + number of pairs) (scipy ``cKDTree.query_pairs(output_type="ndarray")``).
    """
    p = _as_points(p)
    if not radius >= 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    if p.flags.c_contiguous and p.shape[0]:  # a complex is finite iff both parts are
        finite = np.isfinite(p.view(np.complex128)[:, 0])
    else:
        finite = np.isfinite(p).all(axis=1)
    idx = None if not finite.shape[0] or finite[finite.argmin()] else np.flatnonzero(finite)
    q = p if idx is None else p[idx]
    m = q.shape[0]
    if m < _BRUTE_MAX:
        I, J = np.triu_indices(m, 1)
        d = q[I] - q[J]
        keep = np.hypot(d[:, 0], d[:, 1]) <= radius
        I, J = I[keep], J[keep]
    else:
        ij = cKDTree(q).query_pairs(radius, output_type="ndarray")
        # sorted by (i, j): the pairs are distinct, so sorting i·m + j sorts them
        key = ij[:, 0] * m
        key += ij[:, 1]
        key.sort()
        I, J = np.divmod(key, m)
    if idx is not None:
        I, J = idx[I], idx[J]
    return _readonly(np.ascontiguousarray(I, dtype=np.int64),
                     np.ascontiguousarray(J, dtype=np.int64))


class VerletPairs:
    """Cached neighbour candidates (a Verlet list) for positions that move a little per step.

    ``radius``: the interaction radius (r_s + r_a for the controller); ``skin`` > 0: extra
    margin. The candidate list holds every pair within ``radius + skin`` at the last build; it
    is rebuilt when the largest displacement since then exceeds ``skin/2`` (two robots can then
    have closed at most ``skin``), when the number of robots changes or the set of NaN rows
    changes. ``builds`` counts the rebuilds; ``last_move`` is the largest displacement since
    the build seen by the last :meth:`candidates` call (0 right after a build).
    """

    def __init__(self, radius: float, skin: float) -> None:
        if not radius > 0 or not skin > 0:
            raise ValueError(f"VerletPairs needs radius > 0 and skin > 0, got {radius}, {skin}")
        self.radius = float(radius)
        self.skin = float(skin)
        self._half = np.array(skin / 2.0)
        self._z0: np.ndarray | None = None
        self._nan0: np.ndarray | None = None
        self._I = self._J = np.zeros(0, np.int64)
        self.builds = 0
        self.last_move = 0.0

    def _build(self, p: np.ndarray, z: np.ndarray) -> None:
        self._I, self._J = pairs_within(p, self.radius + self.skin)
        self._z0 = z.copy()
        self._nan0 = np.isnan(z)
        self.builds += 1
        self.last_move = 0.0

    def _needs_build(self, z: np.ndarray) -> bool:
        z0 = self._z0
        if z0 is None or z0.shape != z.shape:
            return True
        dmax = np.abs(z - z0).max() if z.shape[0] else 0.0
        if dmax <= self._half:
            self.last_move = float(dmax)
            return False
        if not np.isnan(dmax):
            return True
        # NaN rows present (exited robots): same set as at the build and small moves elsewhere
        nan = np.isnan(z)
        if not np.array_equal(nan, self._nan0):
            return True
        dmax = np.fmax.reduce(np.abs(z - z0))
        self.last_move = float(dmax)
        return bool(dmax > self._half)

    def candidates(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A superset of the pairs within ``radius`` (read-only arrays, reused between builds)."""
        if not (type(p) is np.ndarray and p.dtype == np.float64 and p.ndim == 2
                and p.shape[1] == 2 and p.flags.c_contiguous):
            p = np.ascontiguousarray(_as_points(p))
        z = p.view(np.complex128).reshape(p.shape[0])
        z0 = self._z0
        if z0 is not None and z0.shape == z.shape and z.shape[0]:
            d = np.abs(z - z0)
            dmax = d[d.argmax()]
            if dmax <= self._half:  # common: 4 cheap numpy calls (argmax: first NaN)
                self.last_move = float(dmax)
                return self._I, self._J
        if self._needs_build(z):
            self._build(p, z)
        return self._I, self._J

    def pairs(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exactly the pairs within ``radius`` (I < J), like :func:`pairs_within`."""
        I, J = self.candidates(p)
        p = np.ascontiguousarray(p, dtype=float)
        z = p.view(np.complex128).ravel()
        keep = np.abs(z.take(J) - z.take(I)) <= self.radius
        return _readonly(I[keep], J[keep])
