"""Distributed swarm controller within (sub) trapezoid virtual tubes (Sections III-D, IV-B).

One function, :func:`velocity_command`, serves the simulator (all M robots at once) and the
fleet agents (``rows=``: one robot from itself and its neighbours). Three laws:

* ``kind="new"`` — (ModifiedVectorField) with the switching logic (ObstacleController):
  v_c = u1'' + sat(u2 + u3' + u4', v'_max). With Constraint1, v_min ≤ ‖v_c‖ ≤ v_max always
  (paper note 9).
* ``kind="old"`` — (Oldcontroller): v_c = sat(u1'' + u2 + u3' + u4', v_max).
* ``kind="apf"`` — Appendix C: v_c = u1'' + sat(u2 + u3' + u4' + u5, v'_max) with the potential
  obstacle term u5 = Σ_k −∂V_o,ik/∂p_i, V_o,ik = V_n(k4, ‖p_i − p_o,k‖, r_o,k + r_s,
  r_o,k + r_a, ε_o, ε_s); meant for the main tube without partition.

Terms (robot i in its own sub-tube k_i, partition §4):

* u1'' — smooth line approaching term (paper note 4):
  u1'' = v·normalize(n_c + σ_h [n_cᵀn_h < 0](t_h − n_c) + σ_r [n_cᵀn_r < 0](t_r − n_c)),
  σ_h = σ(d_Th(p_i), r_a, k_t r_a), σ_r likewise.
* u2 = Σ_j b_ij (p_i − p_j), b_ij = −(∂V_m,ij/∂‖p_ij‖)/‖p_ij‖ with (Vmij)
  V_m,ij = V_n(k2, ‖p_i − p_j‖, 2r_s, r_s + r_a, ε_m, ε_s) over ALL neighbours, whatever their
  sub-tube (paper note 6).
* u3' = −(∂V'_th/∂d_Th) P_t n_h, u4' = −(∂V'_tr/∂d_Tr) P_t n_r with (Vtli1)/(Vtri1)
  V'_th = V_n(k3, d_Th(p_i), r_s, r_a, ε_t, ε_s) and P_t = I − n_c n_cᵀ (paper note 1: the
  printed n_c n_cᵀ contradicts Remark 4).

Implementation: 2-D vectors are complex numbers (``p.view(complex128)``), so vector algebra is
one numpy call; all robot–robot and robot–leg barrier derivatives of a step are evaluated in ONE
fused :class:`~vtube_fleet.core.barrier.BarrierBank` call, together with the σ's of u1''; the sums
over neighbours, legs and σ's are one ``np.bincount``. Per-sub-tube constants are precomputed
once per (TubeArrays, ControllerParams) and gathered with one ``take`` per step. In a loop of
small moves (:meth:`CommandEvaluator.step` with ``move``, the simulator) only the elements
that can be non-zero are evaluated: legs/σ's within max(r_a, k_t r_a) + :data:`ACTIVE_SKIN`,
pairs within r_s + r_a + 2 :data:`ACTIVE_SKIN`, chosen again when the points may have moved
ACTIVE_SKIN; the others are exactly 0 and the sums keep their order, so the commands are
bitwise those of the full evaluation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np

from vtube_fleet.core.barrier import X_MIN, BarrierBank, dV_n_dx
from vtube_fleet.core.neighbours import pairs_within
from vtube_fleet.core.params import ControllerParams
from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = [
    "ACTIVE_SKIN",
    "CommandEvaluator",
    "TubeArrays",
    "reuse_heap",
    "u1pp",
    "u2",
    "u3p_u4p",
    "u5",
    "velocity_command",
]

Kind = Literal["new", "old", "apf"]

# Minima in the hot paths are x[x.argmin()]: the same value as np.minimum.reduce, NaN included
# (argmin returns the first NaN), in a third of the time of a ufunc reduction on a few hundred
# elements.


def _c(v: np.ndarray) -> np.ndarray:
    """(..., 2) float → (...,) complex."""
    v = np.asarray(v, dtype=float)
    return v[..., 0] + 1j * v[..., 1]


@dataclass(frozen=True, eq=False)
class TubeArrays:
    """Geometry of K (sub) tubes stacked for vectorized evaluation (rows follow the order of
    the tubes given to :meth:`from_tubes`, i.e. the sub-tube index k of each robot).

    n_c, n_h, n_r, t_h, t_r, p_h1, p_r1: (K, 2); has_L, has_R: (K,) bool (L/R areas exist,
    n_cᵀn_h < 0 / n_cᵀn_r < 0).
    """

    n_c: np.ndarray
    n_h: np.ndarray
    n_r: np.ndarray
    t_h: np.ndarray
    t_r: np.ndarray
    p_h1: np.ndarray
    p_r1: np.ndarray
    has_L: np.ndarray
    has_R: np.ndarray
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        K = None
        for f in fields(self):
            if f.name == "_cache":
                continue
            is_flag = f.name in ("has_L", "has_R")
            a = np.array(getattr(self, f.name), dtype=bool if is_flag else float)
            K = a.shape[0] if K is None else K
            want = (K,) if is_flag else (K, 2)
            if a.shape != want or K == 0:
                raise ValueError(f"TubeArrays.{f.name}: expected shape {want} with K >= 1, "
                                 f"got {a.shape}")
            if not is_flag and not np.all(np.isfinite(a)):
                raise ValueError(f"TubeArrays.{f.name} must be finite")
            a.setflags(write=False)
            object.__setattr__(self, f.name, a)

    @classmethod
    def from_tubes(cls, tubes: Sequence[Trapezoid]) -> TubeArrays:
        tubes = list(tubes)
        if not tubes:
            raise ValueError("TubeArrays.from_tubes needs at least one tube")
        st = lambda attr: np.stack([getattr(t, attr) for t in tubes])  # noqa: E731
        return cls(n_c=st("n_c"), n_h=st("n_h"), n_r=st("n_r"), t_h=st("t_h"), t_r=st("t_r"),
                   p_h1=st("p_h1"), p_r1=st("p_r1"),
                   has_L=np.array([t.has_L for t in tubes]),
                   has_R=np.array([t.has_R for t in tubes]))

    def __len__(self) -> int:
        return self.n_c.shape[0]

    def d_Th(self, p: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(dtl) d_Th of each point in its own tube k: n_h,kᵀ(p − p_h1,k), shape (M,)."""
        p = np.asarray(p, dtype=float)
        return np.einsum("ij,ij->i", p - self.p_h1[k], self.n_h[k])

    def d_Tr(self, p: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(dtr) d_Tr of each point in its own tube k: n_r,kᵀ(p − p_r1,k), shape (M,)."""
        p = np.asarray(p, dtype=float)
        return np.einsum("ij,ij->i", p - self.p_r1[k], self.n_r[k])

    def _prepared(self, params: ControllerParams) -> _Prepared:
        last = self._cache.get("last")
        if last is not None and last.params is params:
            return last
        prep = self._cache.get(params)
        if prep is None:
            if len(self._cache) > 8:  # bounded: params objects are few in practice
                self._cache.clear()
            prep = _Prepared(self, params)
            self._cache[params] = prep
        self._cache["last"] = prep
        return prep


class _Layout:
    """Constants for evaluating n robots out of M (memoized per M, or per rows for agents).

    Fused element layout of one step (floats): X = [d_Th of the n robots | d_Tr | d_Th | d_Tr |
    ‖p_i − p_j‖ of the P pairs]: the first two blocks feed (Vtli1)/(Vtri1), the next two the
    σ's of u1'', the last (Vmij). Complex weights W = [legs (2n) | σ (2n) | pairs, i side (P) |
    pairs, j side (P) | n_c (n)] are summed by ONE ``np.bincount`` into float slots giving the
    complex array B = [q_0 … q_{n−1} | u_rep,0 … u_rep,n−1] (q = n_c + σ_h A_h + σ_r A_r: the
    direction of u1''; u_rep = u2 + u3' + u4'); with ``rows`` the slots cover all M robots and
    the rows are taken afterwards.
    """

    __slots__ = ("n", "M", "bank", "slot_ls", "q_slot", "cv", "mv", "pairs", "spare")

    def __init__(self, prep: _Prepared, slots: np.ndarray, M: int, n_pairs: int) -> None:
        p = prep.params
        n = slots.shape[0]
        self.n, self.M = n, M
        cap = max(2 * n_pairs, 4 * n, 64)
        legs, sig, pair = prep.blocks(2 * n, cap)
        self.bank = BarrierBank.concatenate_prefixes([(legs, 2 * n), (sig, 2 * n), (pair, cap)])
        re_im = np.array([0, 1])
        q_slot = (2 * slots[:, None] + re_im).ravel()  # float slots of q_r
        u_slot = q_slot + 2 * M  # float slots of u_rep,r
        self.slot_ls = np.concatenate([u_slot, u_slot, q_slot, q_slot])
        self.q_slot = q_slot
        # final step on [q | u_rep]: × cv/max(|.|, mv) gives [v q/‖q‖ | sat(u_rep, v'_max)]
        self.cv = np.repeat([p.v, p.v_max_prime], n)
        self.mv = np.repeat([1e-300, p.v_max_prime], n)
        self.pairs: tuple | None = None
        self.spare: _Scratch | None = None  # scratch arrays of a finished call, for the next

    def scratch(self, n: int, P: int) -> _Scratch:
        """Scratch arrays for (n, P): the spare ones if they fit and nobody holds them."""
        w, self.spare = self.spare, None
        return w if w is not None and w.n == n and w.P == P else _Scratch(n, P)

    def pair_arrays(self, I: np.ndarray, J: np.ndarray, cache: bool) -> tuple:
        """(IJ = [I, J], float slots of all W elements) for pairs (I, J); memoized on array
        identity when ``cache`` (read-only arrays)."""
        pa = self.pairs
        if cache and pa is not None and pa[0] is I and pa[1] is J:
            return pa[2], pa[3]
        re_im = np.array([0, 1]) + 2 * self.M
        ia = (2 * I[:, None] + re_im).ravel()
        ib = (2 * J[:, None] + re_im).ravel()
        IJ = np.concatenate([I, J])
        slots = np.concatenate([self.slot_ls, ia, ib, self.q_slot])
        if cache:
            self.pairs = (I, J, IJ, slots)
        return IJ, slots


class _Prepared:
    """Per-(TubeArrays, ControllerParams) constants, gathered per robot with one ``take``."""

    def __init__(self, tubes: TubeArrays, params: ControllerParams) -> None:
        self.params = params
        self.K = len(tubes)
        n_c, n_h, n_r = _c(tubes.n_c), _c(tubes.n_h), _c(tubes.n_r)
        t_h, t_r = _c(tubes.t_h), _c(tubes.t_r)
        c_h = np.einsum("ij,ij->i", tubes.n_h, tubes.p_h1)
        c_r = np.einsum("ij,ij->i", tubes.n_r, tubes.p_r1)
        # P_t = I − n_c n_cᵀ (paper note 1); E = −P_t n: u3' = (∂V'_th/∂d_Th)·E_h
        pt = lambda n: n - n_c * (n_c.real * n.real + n_c.imag * n.imag)  # noqa: E731
        # rows, one column per sub-tube:
        #   0-1 conj(n_h), conj(n_r): Re(conj(n)·z) = nᵀp; 2-3 n_hᵀp_h1, n_rᵀp_r1 → (dtl)/(dtr)
        #   4-5 E_h, E_r; 6-7 A = [area exists](t − n_c), so that u1'' ∝ q = n_c + σ_h A_h
        #   + σ_r A_r (paper note 4); 8 n_c
        self.table = np.ascontiguousarray(np.stack([
            np.conj(n_h), np.conj(n_r), c_h + 0j, c_r + 0j, -pt(n_h), -pt(n_r),
            np.where(tubes.has_L, t_h - n_c, 0), np.where(tubes.has_R, t_r - n_c, 0), n_c]))
        self.r_pair = params.r_s + params.r_a  # V_m,ij ≡ 0 beyond (Vmij)
        self._layouts: dict = {}
        self._blocks: tuple[BarrierBank, BarrierBank, BarrierBank] | None = None
        self.active_banks: dict = {}  # (leg capacity, pair capacity) → bank (_Active)

    def blocks(self, n_legs: int, n_pairs: int) -> tuple[BarrierBank, BarrierBank, BarrierBank]:
        """The three kinds of barrier elements, as banks of at least n_legs, n_legs and
        n_pairs elements (grown by doubling; layouts take prefixes)."""
        b = self._blocks
        if b is None or len(b[0]) < n_legs or len(b[2]) < n_pairs:
            m = max(n_legs, 64 if b is None else 2 * len(b[0]))
            c = max(n_pairs, 64 if b is None else 2 * len(b[2]))
            p = self.params
            full = np.full
            b = self._blocks = (
                # (Vtli1)/(Vtri1): V_n(k3, d_T, r_s, r_a, ε_t, ε_s)
                BarrierBank(full(m, p.k3), p.r_s, p.r_a, p.eps_t, p.eps_s),
                # σ(d_T, r_a, k_t r_a) of u1'' (k = 0: σ only); k_t = 1 → a hair-thin band
                BarrierBank(full(m, 0.0), p.r_a, max(p.k_t, 1 + 1e-9) * p.r_a, 1.0, p.eps_s),
                # (Vmij): V_n(k2, ‖p_ij‖, 2 r_s, r_s + r_a, ε_m, ε_s)
                BarrierBank(full(c, p.k2), 2 * p.r_s, p.r_s + p.r_a, p.eps_m, p.eps_s),
            )
        return b

    def layout(self, M: int, n_pairs: int, rows: np.ndarray | None = None) -> _Layout:
        """The layout for all M robots (rows=None) or for ``rows``; memoized (bounded)."""
        key = M if rows is None else (M, rows.tobytes())
        lay = self._layouts.get(key)
        n = M if rows is None else rows.shape[0]
        if lay is None or len(lay.bank) < 4 * n + n_pairs:
            lay = _Layout(self, np.arange(M) if rows is None else rows, M, n_pairs)
            if len(self._layouts) > 64:
                self._layouts.clear()
            self._layouts[key] = lay
        return lay


class _Gathered:
    """Per-robot sub-tube constants of one ``k`` (columns of :attr:`_Prepared.table`, one
    take): G01 the conj(n_h), conj(n_r) (2, n); G23 n_hᵀp_h1, n_rᵀp_r1 (2, n); GA E_h, E_r,
    A_h, A_r (4n,); n_c (n,); G8 rows 0–7 as (4, 2n), one column per leg/σ element.
    ``buf``: a (9, n) complex array to gather into (a scratch's, see :meth:`_Scratch.gbuf`)
    instead of a new one: a fresh multi-megabyte array on every call makes the allocator unmap
    and re-fault memory (10,000 robots: 2.1 instead of 1.3 ms per call)."""

    __slots__ = ("k", "writeable", "G", "G01", "G23", "GA", "n_c", "G8")

    def __init__(self, prep: _Prepared, k: np.ndarray, buf: np.ndarray | None = None,
                 G: np.ndarray | None = None) -> None:
        n = k.shape[0]
        if G is None:
            _check_k(prep, k)
            # k is checked, so mode="clip" (with "raise", take buffers its output)
            G = prep.table.take(k, 1, buf, "clip")
        self.G = G
        self.G01, self.G23, self.GA, self.n_c = G[0:2], G[2:4].real, G[4:8].reshape(4 * n), G[8]
        # the four per-element rows of the leg/σ elements (side·n + robot): conj(n), nᵀp_1, E, A
        self.G8 = G[:8].reshape(4, 2 * n)
        self.k = k
        self.writeable = k.flags.writeable  # (then it may change in place: gather every time)

    def replaced(self, prep: _Prepared, k: np.ndarray, ch: list[int]) -> _Gathered:
        """The constants of ``k``, which equals this one's k but in the columns ``ch`` (a
        few)."""
        G = self.G.copy()
        table, K = prep.table, prep.K
        for c in ch:
            kc = int(k[c])
            if not 0 <= kc < K:
                raise ValueError(f"k must be in [0, {K}) (sub-tube indices), got {kc}")
            G[:, c] = table[:, kc]
        return _Gathered(prep, k, G=G)


def _check_k(prep: _Prepared, k: np.ndarray) -> None:
    if k.shape[0] and (k[k.argmin()] < 0 or k[k.argmax()] >= prep.K):  # (no reduction)
        bad = k.min() if k.min() < 0 else k.max()
        raise ValueError(f"k must be in [0, {prep.K}) (sub-tube indices), got {bad}")


def reuse_heap(nbytes: int) -> None:
    """Allocate and free ``nbytes`` once, so that the C allocator keeps temporaries of up to
    that size on its heap instead of mapping and unmapping (and page-faulting) them on every
    call: glibc raises its mmap threshold (dynamically, up to 32 MB) to the size of a freed
    mapped block (mallopt(3)). Long-lived scratch arrays allocated before any such free keep
    the threshold at 128 KB otherwise: 550 page faults per step at 10,000 robots. Harmless
    elsewhere."""
    if nbytes > 1 << 17:
        np.empty(min(nbytes, 32 << 20), np.uint8)


class _Scratch:
    """Work arrays for n evaluated robots and P pairs, with the views :func:`_core` uses.

    X (4n + P): distances (the :class:`_Layout` element order); W (5n + 2P, complex): the
    weights, its last n elements n_c; NB (2n, complex, imaginary parts 0): the final scale
    factors (a complex × complex product costs less than complex × float, which numpy casts
    through a buffer).
    """

    __slots__ = ("n", "P", "X", "X4", "xp", "W", "Wf", "Wl", "Wi", "Wj", "Wnc", "NB", "NBr",
                 "nb", "track", "pmin", "_g", "ncg")

    def __init__(self, n: int, P: int, track: bool = False) -> None:
        self.n, self.P = n, P
        n4 = 4 * n
        self.X = np.empty(n4 + P)
        self.X4 = self.X[:n4].reshape(2, 2, n)
        self.xp = self.X[n4:]
        self.W = np.empty(5 * n + 2 * P, np.complex128)
        self.Wf = self.W.view(np.float64)
        self.Wl = self.W[:n4]
        self.Wi = self.W[n4: n4 + P]
        self.Wj = self.W[n4 + P: n4 + 2 * P]
        self.Wnc = self.W[n4 + 2 * P:]
        self.NB = np.zeros(2 * n, np.complex128)
        self.NBr = self.NB.real
        self.nb = np.empty(2 * n)  # |B| (CommandEvaluator.step's inlined _finish)
        # track: keep min ‖p_i − p_j‖ over the pairs (before the barriers clamp it) in pmin
        self.track, self.pmin = track, math.inf
        self._g: np.ndarray | None = None
        self.ncg: _Gathered | None = None  # (CommandEvaluator: whose n_c is in Wnc)
        reuse_heap(64 * (5 * n + 2 * P))  # > every temporary of a call (the largest: 32 P)

    def gbuf(self) -> np.ndarray:
        """The (9, n) array for a :class:`_Gathered` of these n robots (made on first use)."""
        if self._g is None:
            self._g = np.empty((9, self.n), np.complex128)
        return self._g


def _core(z: np.ndarray, zr: np.ndarray, g: _Gathered, bank: BarrierBank, IJ: np.ndarray,
          slots: np.ndarray, w: _Scratch, M: int) -> np.ndarray:
    """The equations shared by every entry point: B (4M floats, viewed as 2M complex) =
    [q of the M robots | u2 + u3' + u4' of the M robots] (slots of robots not evaluated stay
    0). ``zr``: the n evaluated robots; ``IJ`` = [I, J]; ``w``: scratch arrays whose n_c
    block (``w.Wnc``) holds ``g.n_c``. 18 numpy calls for any M.
    """
    P = w.P
    n4 = w.Wl.shape[0]
    # --- distances: d_Th, d_Tr (dtl)/(dtr) of each robot in its own sub-tube, written to the
    # legs and σ blocks; ‖p_i − p_j‖ of the pairs ---------------------------------------
    np.subtract((g.G01 * zr).real, g.G23, out=w.X4)
    zz = z.take(IJ)
    dz = zz[P:]
    dz -= zz[:P]  # p_j − p_i
    np.abs(dz, out=w.xp)
    if w.track:
        w.pmin = float(w.xp[w.xp.argmin()]) if P else math.inf
    # --- all barrier derivatives and σ's in one call (clamps X ≥ X_MIN if needed) -------
    y = bank.evaluate(w.X)
    # --- weights, summed per robot by one bincount -------------------------------------
    np.multiply(y[:n4], g.GA, out=w.Wl)  # u3', u4'; σ·A
    # u2: b_ij (p_i − p_j) = (∂V_m/∂‖p_ij‖/‖p_ij‖)(p_j − p_i) for i, the opposite for j
    yp = y[n4:]
    yp /= w.xp
    np.multiply(dz, yp, out=w.Wi)
    np.negative(w.Wi.view(np.float64), out=w.Wj.view(np.float64))  # (complex negative: slow)
    # + n_c (the last block of W) → q = n_c + σ_h A_h + σ_r A_r
    return np.bincount(slots, w.Wf, 4 * M).view(np.complex128)


def _evaluate(p, k, tubes: TubeArrays, params: ControllerParams, pairs, rows
              ) -> tuple[np.ndarray, _Layout, _Scratch]:
    """Checks and converts the arguments, then :func:`_core`.

    Returns B (2n,) complex = [q of the n robots | u2 + u3' + u4' of the n robots] (q: the
    unnormalized direction of u1''), the layout and the scratch arrays used.
    """
    prep = tubes._prepared(params)
    # --- arguments (cheap checks first; conversions only when needed) --------------------
    if type(p) is not np.ndarray or p.dtype != np.float64 or not p.flags.c_contiguous:
        p = np.ascontiguousarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"p must have shape (M, 2), got {p.shape}")
    M = p.shape[0]
    z = p.view(np.complex128).reshape(M)
    if type(k) is not np.ndarray or k.dtype != np.intp:
        k = np.asarray(k)
        if k.dtype.kind not in "iu" and k.size:
            raise ValueError(f"k must be integer sub-tube indices, got dtype {k.dtype}")
        k = k.astype(np.intp)
    if rows is not None:
        rows = np.asarray(rows, dtype=np.intp).reshape(-1)
        if rows.size and (rows.min() < 0 or rows.max() >= M):
            raise ValueError(f"rows must index the {M} robots, got {rows}")
        if np.unique(rows).size != rows.size:
            raise ValueError(f"rows must not repeat a robot, got {rows}")
    if pairs is None:
        if rows is None:
            pairs = pairs_within(p, prep.r_pair)
        else:  # an agent: every (row, other) pair is a candidate; pairs inside rows once
            I = np.repeat(rows, M)
            J = np.tile(np.arange(M), rows.shape[0])
            inrows = np.zeros(M, bool)
            inrows[rows] = True
            keep = (I != J) & ~(inrows[J] & (J < I))
            pairs = (I[keep], J[keep])
    I, J = _check_pairs(pairs)
    cache = not (I.flags.writeable or J.flags.writeable)
    if rows is None:
        if k.shape != (M,):
            raise ValueError(f"k must have shape ({M},), got {k.shape}")
        zr = z
    else:
        if k.shape == (M,):
            k = k.take(rows)
        elif k.shape != rows.shape:
            raise ValueError(f"k must have shape ({M},) or ({rows.shape[0]},), got {k.shape}")
        inrows = np.zeros(M, bool)
        inrows[rows] = True
        keep = inrows[I] | inrows[J]
        I, J = I[keep], J[keep]
        zr = z.take(rows)
        cache = False
    if not cache:
        _check_pair_range(I, J, M)
    n, P = zr.shape[0], I.shape[0]
    lay = prep.layout(M, P, rows)
    w = lay.scratch(n, P)
    if n == 0:
        return np.zeros(0, np.complex128), lay, w
    g = _Gathered(prep, k, w.gbuf())
    IJ, slots = lay.pair_arrays(I, J, cache)
    w.Wnc[:] = g.n_c
    B = _core(z, zr, g, lay.bank, IJ, slots, w, M)
    if rows is not None:
        B = B.reshape(2, M).take(rows, axis=1).reshape(2 * n)
    return B, lay, w


def _check_pairs(pairs) -> tuple[np.ndarray, np.ndarray]:
    I, J = pairs
    if type(I) is not np.ndarray or type(J) is not np.ndarray or I.dtype.kind not in "iu" \
            or J.dtype.kind not in "iu" or I.ndim != 1 or I.shape != J.shape:
        I, J = np.asarray(I), np.asarray(J)
        if I.size == 0 and J.size == 0:
            I = J = np.zeros(0, np.intp)
        elif I.ndim != 1 or I.shape != J.shape or I.dtype.kind not in "iu" \
                or J.dtype.kind not in "iu":
            raise ValueError("pairs must be two 1-D integer arrays (I, J) of equal length")
    return I, J


def _check_pair_range(I: np.ndarray, J: np.ndarray, M: int) -> None:
    if I.size and (I[I.argmin()] < 0 or J[J.argmax()] >= M or I[I.argmax()] >= M
                   or J[J.argmin()] < 0):
        raise ValueError(f"pairs must index the {M} robots")


def _finish(B: np.ndarray, lay: _Layout, kind: str, params: ControllerParams, p, rows,
            obstacles: Sequence[Obstacle], out: np.ndarray | None = None,
            w: _Scratch | None = None) -> np.ndarray:
    """v_c from B = [q | u_rep] (2n,) complex (overwritten) for the law ``kind``; written to
    ``out`` ((n,) complex) if given; ``w``: scratch arrays for these n robots; ``p``: the (M, 2)
    positions (used by "apf" only). Returns v_c as (n,) complex."""
    n = B.shape[0] >> 1
    q = B[:n]
    if kind == "new":
        # [v q/‖q‖ | sat(u_rep, v'_max)] in one go, then u1'' + sat(...) (ModifiedVectorField)
        if w is None:
            w = _Scratch(n, 0)
        nb = np.abs(B)
        np.maximum(nb, lay.mv, out=nb)
        np.divide(lay.cv, nb, out=w.NBr)
        B *= w.NB
        return np.add(q, B[n:], out=out)
    u = B[n:]
    if kind == "apf":  # Appendix C: u_rep += u5, then as "new"
        if not obstacles:
            raise ValueError("kind='apf' needs obstacles")
        pr = np.asarray(p, dtype=np.float64)
        if rows is not None:
            pr = pr[np.asarray(rows, dtype=np.intp).reshape(-1)]
        u += u5(pr, obstacles, params).view(np.complex128).reshape(n)
        B *= lay.cv / np.maximum(np.abs(B), lay.mv)
        return np.add(q, u, out=out)
    # (Oldcontroller): sat(u1'' + u2 + u3' + u4', v_max)
    u += q * (params.v / np.maximum(np.abs(q), 1e-300))
    return np.multiply(u, params.v_max / np.maximum(np.abs(u), params.v_max), out=out)


def velocity_command(p: np.ndarray, k: np.ndarray, tubes: TubeArrays,
                     params: ControllerParams, *, pairs=None, kind: Kind = "new",
                     obstacles: Sequence[Obstacle] = (), rows=None) -> np.ndarray:
    """Velocity commands v_c of the robots (ModifiedVectorField)/(ObstacleController).

    p: (M, 2) positions (control points) of ALL robots (the swarm p); k: (M,) int index of
    each robot's own sub-tube in ``tubes`` (with ``rows``, k may also be (len(rows),));
    pairs: (I, J) int arrays of neighbour candidates (any superset of the pairs closer than
    r_s + r_a; farther pairs contribute exactly 0), excluding NaN rows. None → computed with
    :func:`vtube_fleet.core.neighbours.pairs_within`. Read-only arrays (as
    :class:`~vtube_fleet.core.neighbours.VerletPairs` returns) let derived index arrays be reused.
    kind: "new" (ModifiedVectorField), "old" (Oldcontroller), "apf" (Appendix C, with
    ``obstacles``; meant for the main tube without partition). rows: compute only these
    robots' commands (an agent: its own row).

    Returns a new (M, 2) or (len(rows), 2) float array. For finite positions (|p| < 1e100 m)
    the result is finite; for "new" v_min ≤ ‖v_c‖ ≤ v_max whenever Constraint1 holds and the
    sub-tubes satisfy Constraint3 (then u1'' never degenerates). NaN rows give NaN rows and do
    not affect the others provided ``pairs`` excludes them. Calls share only memoized
    constants (per ``tubes`` and ``params``), and scratch arrays only one at a time (a call
    takes them and puts them back when done), so concurrent calls are safe. The first call for a new
    robot count builds a layout (~0.1–1 ms). A simulator loop calling this every step should
    use :class:`CommandEvaluator` (same equations and results, state kept between calls).
    """
    if kind != "new" and kind != "old" and kind != "apf":
        raise ValueError(f"kind must be 'new', 'old' or 'apf', got {kind!r}")
    B, lay, w = _evaluate(p, k, tubes, params, pairs, rows)
    v = _finish(B, lay, kind, params, p, rows, obstacles, None, w)
    lay.spare = w  # (the result never refers to w's arrays)
    return v.view(np.float64).reshape(-1, 2)


#: Margin (m) of the element subset of :meth:`CommandEvaluator.step` with ``move``: a leg
#: element is kept if its distance is below max(r_a, k_t r_a) + ACTIVE_SKIN, a pair if below
#: r_s + r_a + 2 ACTIVE_SKIN; the subset is chosen again once the points may have moved that far.
ACTIVE_SKIN = 0.1

_FAR = 1e9  # distance of the padding leg elements (m): beyond every barrier, exactly 0
_ZPAD = np.zeros(16, np.intp)  # the padding leg elements' indices (robot 0's; weights 0)
_ZPAD.setflags(write=False)
#: the padding column of (conj(n), nᵀp_1, E, A): distance _FAR (as Re(0·z) − (−_FAR)), weights 0
_PAD = np.array([[0.0], [-_FAR], [0.0], [0.0]], np.complex128)


# the ufuncs of the hot path as module globals (one lookup instead of two per call)
_mul, _sub, _add, _div, _abs, _neg = (np.multiply, np.subtract, np.add, np.divide, np.abs,
                                      np.negative)
#: np.bincount without the __array_function__ dispatch (a third of the call on ~1,000 weights)
_bincount = getattr(np.bincount, "_implementation", np.bincount)
#: the clip ufunc (min(max(x, lo), hi) in one call, NaN propagated as by np.maximum/minimum;
#: np.clip itself is a Python wrapper around it); None: np.maximum, then np.minimum
_clip = getattr(getattr(getattr(np, "_core", None), "umath", None), "clip", None)
if not isinstance(_clip, np.ufunc):  # pragma: no cover - another numpy
    _clip = None


def _band_floor(E1: float, D1: float) -> float:
    """A distance x0 with ĝ(x) = x·E1 − D1 ≥ 1 (rounded as numpy rounds it, two operations)
    for every x ≥ x0: the band formula of :class:`BarrierBank` then holds (E1 > 0, so ĝ is
    monotone in x, also after rounding)."""
    x = (1.0 + D1) / E1
    while not x * E1 - D1 >= 1.0:
        x = math.nextafter(x, math.inf)
    return x


def _finite(x: np.ndarray) -> bool:
    """All of the non-empty ``x`` finite (argmin/argmax return the first NaN)."""
    return bool(-math.inf < x[x.argmin()] and x[x.argmax()] < math.inf)


class _Active:
    """The elements of :func:`_core` that can be non-zero, for a loop of small moves.

    :meth:`refresh` chooses them at the current points: the candidate pairs closer than
    ``r_pair + 2 skin`` and the leg/σ elements closer than ``cut + skin`` (cut =
    max(r_a, k_t r_a)). Every element left out is then exactly 0 (a = 0 in the band formula of
    :class:`BarrierBank`) while the points have moved less than ``skin`` in total (:attr:`slack`
    counts down), and ``np.bincount`` sums the kept ones in the same order as the full layout
    (a sum that starts at +0 is unchanged by ±0 terms), so B is bitwise the same. The leg block
    is padded to a multiple of 16 (padding at distance ``_FAR``, weights 0) so that a few banks
    serve every subset.

    Whether some element needs the general formula
    (ĝ < 1, :class:`BarrierBank`) is known without looking at ĝ while the smallest pair
    distance is at least :attr:`pair_ok` and no leg distance can have come below
    :attr:`leg_ok` since the legs were chosen (:attr:`leg_floor` of the slack).
    """

    __slots__ = ("g", "pa", "slack", "P", "Lc", "n", "M", "idx", "G01a", "G23a", "GAa",
                 "slots", "bank", "X", "X2", "xp", "W", "Wf", "tmpc", "Gd", "LA", "G2",
                 "pmin", "track", "r_pair", "IJ", "cut", "prep", "sel", "TA", "q_slot",
                 "tmpr", "zz", "dz", "zL", "Y", "Yc", "Yp", "gb", "ab", "nm", "bound", "pos",
                 "free", "fs3", "pair_ok", "leg_ok", "U", "V", "T", "leg_floor", "mv", "cv",
                 "nb", "NB", "z2")

    def __init__(self, prep: _Prepared, M: int, track: bool) -> None:
        legs, sig, pair = prep.blocks(16, 16)
        self.cut = max(float(legs.d2[0]), float(sig.d2[0]))
        # (legs and pairs: one E1, D1 per kind; σ elements have ĝ ≡ 2)
        self.pair_ok = _band_floor(float(pair._E1[0]), float(pair._D1[0]))
        self.leg_ok = _band_floor(float(legs._E1[0]), float(legs._D1[0])) + 1e-9
        self.leg_floor = math.inf
        self.prep, self.n, self.M, self.track = prep, M, M, track
        self.r_pair, self.pmin, self.slack = prep.r_pair, math.inf, -math.inf
        self.g = self.pa = None
        self.Lc, self.P, self.X = 0, -1, np.empty(0)
        # the float slots of _Layout: q of robot r at 2r, 2r + 1; u_rep at 2M + 2r, 2M + 2r + 1;
        # fs3[0, e], fs3[1, e]: those of leg/σ element e = side·M + r (u_rep and q of r)
        q_slot = (2 * np.arange(M)[:, None] + np.array([0, 1])).ravel()
        self.q_slot = q_slot
        self.fs3 = np.concatenate([q_slot + 2 * M, q_slot + 2 * M, q_slot, q_slot]).reshape(
            2, 2 * M, 2)
        # _finish of (ModifiedVectorField), as _Layout's: × cv/max(|.|, mv), then the halves
        p = prep.params
        self.cv = np.repeat([p.v, p.v_max_prime], M)
        self.mv = np.repeat([1e-300, p.v_max_prime], M)
        self.nb = np.empty(2 * M)
        self.NB = np.zeros(2 * M, np.complex128)
        self.z2 = np.empty(2 * M, np.complex128)

    def refresh(self, g: _Gathered, pa: tuple, z: np.ndarray) -> bool:
        """Choose the elements at the points ``z`` for the sub-tubes of ``g`` and the pairs of
        ``pa`` (the evaluator's pair entry); False if a distance is not finite (then the caller
        evaluates everything). New sub-tubes only (same pairs, slack left): the pairs are kept
        and the leg elements are chosen with the slack that is left.

        The kept pairs are padded with further candidates up to a multiple of 32 (or all of
        them): those are farther than r_pair + 2 skin, their terms exactly 0 as the pairs
        left out; with the leg block's multiple of 16, the work arrays of one subset then
        serve the next and are filled in place."""
        M = self.M
        og = self.g
        if (pa is self.pa and self.slack > 0.0 and og is not None and not g.writeable
                and not og.writeable and og.k.shape == g.k.shape):
            # new sub-tubes of a few robots (the tracker's common case): their elements only
            ch = (g.k != og.k).nonzero()[0]
            if ch.shape[0] <= 4 and self._legs_update(g, z, ch.tolist()):
                return True
        # (dtl)/(dtr) of every robot, as _core, as 1-D calls: [conj(n_h) | conj(n_r)]·[z | z]
        z2 = np.concatenate((z, z), out=self.z2)
        G = g.G
        d = np.subtract(np.multiply(G[0:2].reshape(2 * M), z2, out=z2).real,
                        G[2:4].real.reshape(2 * M))
        # (every d finite: every point is, so are the pair distances)
        dmin = d[d.argmin()] if M else 0.0
        if not (-math.inf < dmin and d[d.argmax()] < math.inf):
            return False
        if pa is self.pa and self.slack > 0.0:
            self._legs(g, d, float(dmin), self.cut + self.slack, False)
            return True
        skin = ACTIVE_SKIN
        IJ = pa[4]
        P0 = IJ.shape[0] >> 1
        if pa is not self.pa:
            # the float slots of every candidate's weights (as _Layout.pair_arrays: u_rep of
            # I, then of J, real and imaginary part)
            TA = self.TA = np.empty((2 * P0, 2), np.intp)
            np.multiply(IJ, 2, out=TA[:, 0])
            TA[:, 0] += 2 * M
            np.add(TA[:, 0], 1, out=TA[:, 1])
        zz = z.take(IJ)
        dp = np.abs(zz[P0:] - zz[:P0])
        self.pa, self.IJ, self.slack = pa, IJ, skin
        near = dp < self.r_pair + 2.0 * skin
        sel = near.nonzero()[0]
        P = sel.shape[0]
        Pc = min(P0, -(-P // 32) * 32)
        if Pc > P:  # (pads: the first farther candidates)
            sel = np.concatenate([sel, np.logical_not(near, out=near).nonzero()[0][: Pc - P]])
        self.sel = sel
        self._legs(g, d, float(dmin), self.cut + skin, True)
        return True

    def _legs(self, g: _Gathered, d: np.ndarray, dmin: float, thr: float, new_pairs: bool
              ) -> None:
        """The leg/σ elements closer than ``thr`` (``d``: their distances, side·n + robot,
        ``dmin`` the smallest), padded to Lc (elements of robot 0 with distance ``_FAR`` and
        weights 0); with ``new_pairs``, also the pairs :attr:`sel` of the candidates."""
        n = self.n
        e = (d < thr).nonzero()[0]  # side·n + robot
        L = e.shape[0]
        Lc = max(16, -(-L // 16) * 16)
        el = e.tolist()
        self.pos = {e: j for j, e in enumerate(el)}  # element → its column (_legs_update)
        self.free = list(range(Lc - 1, L - 1, -1))  # the pads' columns
        ep = np.concatenate([e, _ZPAD[: Lc - L]])  # (< 16 pads)
        sel = self.sel
        P = sel.shape[0]
        fresh = self.Lc != Lc or self.P != P  # else the work arrays of the last subset
        if fresh:
            self._alloc(Lc, P)
        if fresh or new_pairs:  # [I | J] of the kept pairs, their weights' float slots
            IJ, TA, idx = self.IJ, self.TA, self.idx
            IJ.reshape(2, IJ.shape[0] >> 1).take(sel, 1, idx[: 2 * P].reshape(2, P), "clip")
            TA.reshape(2, TA.shape[0] >> 1, 2).take(
                sel, 1, self.slots[4 * Lc: 4 * Lc + 4 * P].reshape(2, P, 2), "clip")
        # conj(n), nᵀp_1, E, A of the kept elements, (4, Lc)
        la = g.G8.take(ep, 1, self.LA, "clip")
        if L < Lc:
            la[:, L:] = _PAD
        # both leg rows (the barrier and the σ element of one leg distance) as one block of
        # 2 Lc: conj(n) and nᵀp_1 twice, the points gathered twice (1-D calls, no broadcast)
        np.concatenate([la[:2], la[:2]], axis=1, out=self.G2)
        self.GAa[:] = la[2:].reshape(2 * Lc)
        idx = self.idx
        np.remainder(ep, n, out=idx[2 * P: 2 * P + Lc])
        idx[2 * P + Lc:] = idx[2 * P: 2 * P + Lc]
        # ĝ ≥ 1 for every leg element while the points moved less than this below the slack
        self.leg_floor = self.slack - (dmin - self.leg_ok)
        # legs | σ slots of the kept elements (the pads': robot 0's, with ±0 weights: harmless)
        self.fs3.take(ep, 1, self.slots[: 4 * Lc].reshape(2, Lc, 2), "clip")
        if fresh or g is not self.g:
            self.W[2 * Lc + 2 * P:] = g.n_c
        self.g = g

    def _alloc(self, Lc: int, P: int) -> None:
        """The work arrays of a subset of 2 Lc leg/σ elements and P pairs (and the bank)."""
        n, M = self.n, self.M
        nx = 2 * Lc + P
        _, _, pair = self.prep.blocks(Lc, P)
        key = (Lc, len(pair))
        banks = self.prep.active_banks
        bank = banks.get(key)
        if bank is None:
            if len(banks) > 32:
                banks.clear()
            legs, sig, pair = self.prep.blocks(Lc, P)
            bank = banks[key] = BarrierBank.concatenate_prefixes(
                [(legs, Lc), (sig, Lc), (pair, len(pair))])
        self.bank = bank
        self.Lc, self.P = Lc, P
        self.idx = np.empty(2 * P + 2 * Lc, np.intp)  # [I | J | leg robots × 2]
        self.slots = np.empty(4 * Lc + 4 * P + 2 * M, np.intp)  # [legs, σ | pairs | n_c]
        self.slots[4 * Lc + 4 * P:] = self.q_slot
        self.LA = np.empty((4, Lc), np.complex128)
        self.G2 = np.empty((2, 2 * Lc), np.complex128)
        self.G01a, self.G23a = self.G2[0], self.G2[1].real
        # the band formula's first steps on two elements per element (one call each):
        # V = [x | D1], U = [d2 | x·E1] → U − V = [d2 − x | ĝ] in T (and T[:nx]·(1/w) → a)
        sl = bank.prefix(nx)
        self.V, self.U, self.T = np.empty(2 * nx), np.empty(2 * nx), np.empty(2 * nx)
        self.V[nx:] = sl[3]
        self.U[:nx] = sl[0]
        self.X = self.V[:nx]
        self.X2 = self.X[: 2 * Lc]
        self.xp = self.X[2 * Lc:]
        self.W = np.empty(2 * Lc + 2 * P + n, np.complex128)
        self.Wf = Wf = self.W.view(np.float64)
        self.tmpc = np.empty(2 * Lc, np.complex128)
        self.tmpr = self.tmpc.real
        self.zz = np.empty(2 * P + 2 * Lc, np.complex128)  # [p_I | p_J | leg points × 2]
        self.zL = self.zz[2 * P:]
        # the second factors of the weights: [E_h, E_r of the legs, A of the σ's (GAa) |
        # p_j − p_i of the pairs (dz)], one product with Yc for all
        self.Gd = np.empty(nx, np.complex128)
        self.GAa, self.dz = self.Gd[: 2 * Lc], self.Gd[2 * Lc:]
        # the bank's values (legs, σ | pairs) as the real parts of complex numbers with
        # imaginary parts 0: the weights are then complex × complex products (what numpy
        # computes for complex × float, after casting the float through a buffer)
        self.Yc = np.zeros(nx, np.complex128)
        self.Y = self.Yc.real
        self.Yp = self.Y[2 * Lc:]
        self.gb, self.ab, self.nm = self.T[nx:], np.empty(nx), np.empty(nx)
        self.bound = (self.idx, self.zz, self.zz[P: 2 * P], self.zz[:P], self.dz, self.xp,
                      self.G01a, self.zL, self.tmpc, self.tmpr, self.G23a, self.X2, self.X,
                      self.Y, self.Yc, self.Gd, self.W[: nx], self.Yp,
                      Wf[4 * Lc: 4 * Lc + 2 * P], Wf[4 * Lc + 2 * P: 4 * Lc + 4 * P],
                      self.slots, Wf, 4 * M, self.gb, self.ab, self.nm, self.U, self.V,
                      self.T, self.U[nx:], self.T[:nx], sl[1], sl[2], sl[4], sl[5], sl[6],
                      bank._zero, bank._one, self.nb, self.mv, self.cv, self.NB.real, self.NB,
                      M, P, self.track, self.r_pair, self.pair_ok)

    def _legs_update(self, g: _Gathered, z: np.ndarray, ch: list[int]) -> bool:
        """The robots ``ch`` changed sub-tube (``g``: the new ones; pairs and slack as
        before): their leg/σ elements become pads (distance ``_FAR``: values and weights
        exactly 0) and those closer than the threshold of :meth:`_legs` are written into free
        columns, with Python scalars (a few microseconds instead of a new subset). The other
        robots keep their elements (chosen with more slack: a superset). A robot's two terms
        per slot may then be summed in the other order, which gives the same bits (x + y =
        y + x; the sums start at +0). False (nothing changed) if a distance is not finite or
        the columns do not suffice: the caller chooses the subset anew."""
        n, Lc, P = self.n, self.Lc, self.P
        thr = self.cut + self.slack + 1e-9  # (a hair more: the scalars may round otherwise)
        pos, free = self.pos, self.free
        G = g.G
        adds = []
        gone = 0
        ncs = []
        for r in ch:
            zr = complex(z[r])
            col = G[:, r].tolist()  # rows of _Prepared.table: h and r side, n_c last
            ncs.append(col[8])
            for side, e in ((0, r), (1, n + r)):
                gone += e in pos
                c01, c23, cE, cA = col[side], col[2 + side], col[4 + side], col[6 + side]
                d = (c01 * zr).real - c23.real
                if not -math.inf < d < math.inf:
                    return False
                if d < thr:
                    adds.append((e, r, c01, c23.real, cE, cA, d))
        if len(adds) > len(free) + gone:
            return False
        for a in adds:
            self.leg_floor = max(self.leg_floor, self.slack - (a[6] - self.leg_ok))
        G01a, G23a, GAa, idx, slots = self.G01a, self.G23a, self.GAa, self.idx, self.slots
        for r in ch:
            for e in (r, n + r):
                j = pos.pop(e, None)
                if j is not None:
                    G01a[j] = G01a[Lc + j] = 0.0
                    G23a[j] = G23a[Lc + j] = -_FAR
                    free.append(j)
        o, su = 2 * P, 2 * self.M  # (float slots of r: q at 2r, 2r + 1, u_rep at su + 2r, …)
        for e, r, c01, c23, cE, cA, _ in adds:
            j = free.pop()
            pos[e] = j
            G01a[j] = G01a[Lc + j] = c01
            G23a[j] = G23a[Lc + j] = c23
            GAa[j] = cE
            GAa[Lc + j] = cA
            idx[o + j] = idx[o + Lc + j] = r
            slots[2 * j] = su + 2 * r  # (as fs3[0, e], fs3[1, e])
            slots[2 * j + 1] = su + 2 * r + 1
            slots[2 * Lc + 2 * j] = 2 * r
            slots[2 * Lc + 2 * j + 1] = 2 * r + 1
        W = self.W
        for r, nc in zip(ch, ncs, strict=True):
            W[2 * Lc + 2 * P + r] = nc
        self.g = g
        return True

    def core(self, z: np.ndarray, out: np.ndarray | None = None, new: bool = False
             ) -> np.ndarray:
        """:func:`_core` on the subset (the same operations per element, the band formula of
        :meth:`BarrierBank.evaluate` inlined, into buffers kept between calls); sets
        :attr:`pmin`. ``new``: also :func:`_finish` of (ModifiedVectorField), inlined (the
        same operations), returning v_c (written to ``out`` if given)."""
        (idx, zz, zJ, zI, dz, xp, G01a, zL, tmpc, tmpr, G23a, X2, X, Y, Yc, Gd, Wd, Yp, Wif,
         Wjf, slots, Wf, M4, gb, ab, nm, U, V, T, Ug, Ta, Bw, E1, Q0, R1, R2, zero, one, fnb,
         fmv, fcv, fNBr, fNB, M, P, track, r_pair, pair_ok) = self.bound
        # (outputs passed by position: numpy then parses no keywords, ~10 % of a small call)
        mul, sub = _mul, _sub
        z.take(idx, None, zz, "clip")  # [p_I | p_J | leg points] (valid indices)
        sub(zJ, zI, dz)  # p_j − p_i
        _abs(dz, xp)
        pm = float(xp[xp.argmin()]) if P else math.inf
        slack = self.slack
        if track:
            pt = pm
            # a pair left out is farther than r_pair + 2·slack; else take all candidates
            if not pt < r_pair + 2.0 * slack and self.IJ.shape[0]:
                Pa = self.IJ.shape[0] >> 1
                za = z.take(self.IJ)
                da = za[Pa:]
                da -= za[:Pa]
                da = np.abs(da)
                pt = float(da[da.argmin()])
            self.pmin = pt
        mul(G01a, zL, tmpc)
        sub(tmpr, G23a, X2)  # (dtl)/(dtr): Re(conj(n)·z) − nᵀp_1
        # BarrierBank.evaluate(X, Y), its common path inlined (the same operations)
        mul(X, E1, Ug)
        sub(U, V, T)  # [d2 − x | ĝ = x·E1 − D1]
        if (pm >= pair_ok and slack > self.leg_floor) or gb[gb.argmin()] >= 1.0:
            mul(Ta, Bw, ab)
            if _clip is not None:  # (a = −0 cannot occur: d2 − x ≠ −0)
                _clip(ab, zero, one, ab)
            else:  # pragma: no cover
                np.maximum(ab, zero, out=ab)
                np.minimum(ab, one, out=ab)
            mul(ab, R2, nm)
            _add(nm, R1, nm)
            mul(nm, ab, nm)
            _add(nm, Q0, nm)
            mul(nm, ab, nm)
            mul(gb, gb, gb)
            _div(nm, gb, Y)
        else:  # some element below d1·x2 (or NaN): the general formula
            self.bank.evaluate(X, Y)
        _div(Yp, xp, Yp)
        # u3', u4'; σ·A; u2: (p_j − p_i)·y/‖p_ij‖ for i (y·(p_j − p_i): the same products, as
        # y has imaginary part 0), the negation for j
        mul(Yc, Gd, Wd)
        _neg(Wif, Wjf)  # on the floats: numpy's complex negative is slow
        B = _bincount(slots, Wf, M4).view(np.complex128)
        if not new:
            return B
        # [v q/‖q‖ | sat(u_rep, v'_max)], then u1'' + sat(...) (ModifiedVectorField)
        nb = _abs(B, fnb)
        np.maximum(nb, fmv, out=nb)
        _div(fcv, nb, fNBr)
        mul(B, fNB, B)
        return _add(B[:M], B[M:], out)


class CommandEvaluator:
    """:func:`velocity_command` for all robots of a simulator, called every step.

    ``evaluator(p, k, pairs, out=None)`` returns exactly (bitwise) what
    ``velocity_command(p, k, tubes, params, pairs=pairs, kind=kind, obstacles=obstacles)``
    returns, through the same code (:func:`_core`, :func:`_finish`), but keeps between calls:
    the per-robot sub-tube constants while ``k`` is the same read-only array (as
    :meth:`~vtube_fleet.core.partition.SubTubeTracker.update` returns), the pair index arrays and
    scratch buffers while ``pairs`` are the same read-only arrays (as
    :class:`~vtube_fleet.core.neighbours.VerletPairs` returns); ``k`` and ``pairs`` are validated
    when they change, not at every call (read-only arrays must not be made writeable and
    changed in between). ``p``: (M, 2) float64 C-contiguous; ``out``: an
    optional (M, 2) float64 C-contiguous array receiving the result (else a new array).
    26 numpy calls per step in the common case (law "new"), whatever M. Not thread-safe (scratch
    buffers); one evaluator per loop.

    ``track_min_pair=True``: after each call, :attr:`min_pair_distance` is the smallest
    ‖p_i − p_j‖ over ``pairs`` (inf without pairs), computed exactly as the metrics do
    (:mod:`vtube_fleet.core.metrics`), so the simulator need not compute it again.
    """

    min_pair_distance: float = math.inf

    def __init__(self, tubes: TubeArrays, params: ControllerParams, kind: Kind = "new",
                 obstacles: Sequence[Obstacle] = (), track_min_pair: bool = False) -> None:
        if kind != "new" and kind != "old" and kind != "apf":
            raise ValueError(f"kind must be 'new', 'old' or 'apf', got {kind!r}")
        if kind == "apf" and not obstacles:
            raise ValueError("kind='apf' needs obstacles")
        self.tubes, self.params, self.kind = tubes, params, kind
        self.obstacles = tuple(obstacles)
        self.track_min_pair = bool(track_min_pair)
        self._prep = tubes._prepared(params)
        self._g: _Gathered | None = None
        self._pairs: tuple | None = None  # (I, J, M, lay, IJ, slots, [scratch], writeable)
        self._act: _Active | None = None  # the non-zero elements (step(move=...))
        self._same: tuple | None = None  # (k, I, J, M) of g and the pair entry, if read-only
        self._fast: tuple | None = None  # what step's short path needs (set by the long one)

    def __call__(self, p: np.ndarray, k: np.ndarray, pairs: tuple[np.ndarray, np.ndarray],
                 out: np.ndarray | None = None) -> np.ndarray:
        if not (type(p) is np.ndarray and p.dtype == np.float64 and p.ndim == 2
                and p.shape[1] == 2 and p.flags.c_contiguous):
            raise ValueError("p must be a C-contiguous float64 array of shape (M, 2)")
        M = p.shape[0]
        if out is not None:
            if out.shape != (M, 2) or out.dtype != np.float64 or not out.flags.c_contiguous:
                raise ValueError(f"out must be a C-contiguous float64 array of shape ({M}, 2)")
            out = out.view(np.complex128).reshape(M)
        v = self.step(p.view(np.complex128).reshape(M), k, pairs, out)
        return v.view(np.float64).reshape(M, 2)

    def step(self, z: np.ndarray, k: np.ndarray, pairs: tuple[np.ndarray, np.ndarray],
             out: np.ndarray | None = None, move: float | None = None) -> np.ndarray:
        """:meth:`__call__` on complex numbers (the simulator's state): ``z`` (M,) complex128
        C-contiguous positions x + iy, ``out`` an optional (M,) complex128 array receiving
        the commands; returns the (M,) complex commands. ``z`` is not checked.

        ``move``: an upper bound of how far any point moved since the previous call (the
        simulator's v_bound·dt). With it, the elements that are exactly 0 (legs and σ's
        beyond max(r_a, k_t r_a), pairs beyond r_s + r_a) are skipped while no point can have
        moved :data:`ACTIVE_SKIN` since the subset was chosen (:class:`_Active`); the result is
        bitwise the same (a sum that starts at +0 is unchanged by adding ±0)."""
        fs = self._fast
        if (fs is not None and move is not None and fs[1] is pairs[0] and fs[2] is pairs[1]
                and fs[3] == z.shape[0]):
            # the common call of a simulator loop: the read-only k and pairs of the last call,
            # law "new", the element subset still valid: core and _finish, nothing else
            act = fs[4]
            slack = act.slack - (move * (1.0 + 1e-9) + 1e-9)
            if slack > 0.0:  # (else the general path below counts the move down itself)
                if fs[0] is k:
                    act.slack = slack
                    v = act.core(z, out, True)
                    if fs[5]:
                        self.min_pair_distance = act.pmin
                    return v
                v = self._new_k(z, k, out, act, slack)
                if v is not None:
                    return v
        self._fast = None
        M = z.shape[0]
        f = self._same
        if f is not None and f[0] is k and f[1] is pairs[0] and f[2] is pairs[1] and f[3] == M:
            g, pa = self._g, self._pairs  # the read-only k and pairs of the last call
        else:
            g = self._g
            pa = self._pairs
            if g is None or g.k is not k or g.writeable:
                if type(k) is not np.ndarray or k.dtype != np.intp or k.shape != (M,):
                    raise ValueError(f"k must be an intp array of shape ({M},)")
                g = self._g = _Gathered(self._prep, k)
            I, J = pairs
            if pa is None or pa[0] is not I or pa[1] is not J or pa[2] != M or pa[7]:
                pa = self._pairs = self._new_pairs(I, J, M, g)
            if M == 0:
                self.min_pair_distance = math.inf
                return np.zeros(0, np.complex128)
            self._same = None if g.writeable or pa[7] else (k, I, J, M)
        lay, track = pa[3], self.track_min_pair
        if move is not None:  # the elements that can be non-zero only (_Active)
            act = self._act
            if act is None or act.M != M:
                act = self._act = _Active(self._prep, M, track)
            act.slack -= move * (1.0 + 1e-9) + 1e-9
            if (act.slack > 0.0 and act.g is g and act.pa is pa) or act.refresh(g, pa, z):
                if self.kind == "new":  # _finish inlined (the same operations)
                    v = act.core(z, out, True)
                    if track:
                        self.min_pair_distance = act.pmin
                    if self._same is not None:  # the next call may take the short path
                        self._fast = (k, pairs[0], pairs[1], M, act, track)
                    return v
                B = act.core(z)
                if track:
                    self.min_pair_distance = act.pmin
                p = z.view(np.float64).reshape(M, 2) if self.kind == "apf" else None
                return _finish(B, lay, self.kind, self.params, p, None, self.obstacles, out,
                               self._work(pa))
        self._act = None  # (how far the points move until the next call is unknown)
        w = self._work(pa)
        if pa[5] is None:
            pa = self._pairs = (*pa[:5], lay.pair_arrays(pa[0], pa[1], cache=False)[1], *pa[6:])
        if w.ncg is not g:  # (the n_c block of the weights, as _core expects)
            w.Wnc[:] = g.n_c
            w.ncg = g
        B = _core(z, z, g, lay.bank, pa[4], pa[5], w, M)
        if w.track:
            self.min_pair_distance = w.pmin
        p = z.view(np.float64).reshape(M, 2) if self.kind == "apf" else None
        return _finish(B, lay, self.kind, self.params, p, None, self.obstacles, out, w)

    def _new_k(self, z: np.ndarray, k: np.ndarray, out: np.ndarray | None, act: _Active,
               slack: float) -> np.ndarray | None:
        """:meth:`step`'s short path for a read-only ``k`` that differs from the last call's
        in a few robots (the sub-tube tracker's changes), the pairs and the element subset as
        before: those robots' constants are gathered and their leg/σ elements patched
        (:meth:`_Active._legs_update`), then the subset is evaluated as on the short path.
        None (nothing changed but the slack) when that does not apply."""
        og, M = self._g, z.shape[0]
        if (type(k) is not np.ndarray or k.dtype != np.intp or k.shape != (M,)
                or k.flags.writeable or og is None or og.writeable or act.g is not og):
            return None
        ch = (k != og.k).nonzero()[0]
        if not 0 < ch.shape[0] <= 4:
            return None
        ch = ch.tolist()
        g = og.replaced(self._prep, k, ch)
        act.slack = slack
        if not act._legs_update(g, z, ch):
            return None
        self._g = g
        fs = self._fast
        self._fast = (k, *fs[1:])
        self._same = (k, fs[1], fs[2], M)
        v = act.core(z, out, True)
        if fs[5]:
            self.min_pair_distance = act.pmin
        return v

    def _new_pairs(self, I, J, M: int, g: _Gathered) -> tuple:
        I, J = _check_pairs((I, J))
        _check_pair_range(I, J, M)
        P = I.shape[0]
        lay = self._prep.layout(M, P)
        # (the float slots of the full layout, entry 5, are made by the first call that
        # evaluates all elements, the scratch arrays, entry 6, by the first that needs them
        # (_work); the element subset of the law "new" needs neither)
        return (I, J, M, lay, np.concatenate([I, J]), None, [None],
                I.flags.writeable or J.flags.writeable)

    def _work(self, pa: tuple) -> _Scratch:
        """The scratch arrays of the pair entry ``pa`` (made on first use; their n_c block is
        filled before a full evaluation)."""
        w = pa[6][0]
        if w is None:
            w = pa[6][0] = _Scratch(pa[2], pa[0].shape[0], self.track_min_pair)
        return w


# ----------------------------------------------------------------------------------------------
# individual terms (for tests and plots); they share the implementation above
# ----------------------------------------------------------------------------------------------
def u1pp(p, k, tubes: TubeArrays, params: ControllerParams) -> np.ndarray:
    """u1'' of every robot (paper note 4), (M, 2)."""
    p = np.asarray(p, dtype=float)
    empty = np.zeros(0, np.intp)
    B, _, _ = _evaluate(p, k, tubes, params, (empty, empty), None)
    q = B[: B.shape[0] // 2]
    return (q * (params.v / np.maximum(np.abs(q), 1e-300))).view(np.float64).reshape(-1, 2)


def u2(p, params: ControllerParams, pairs=None) -> np.ndarray:
    """Robot avoidance term u2 = Σ_j b_ij (p_i − p_j) (Vmij), (M, 2). Tube-independent
    (evaluated in a 2e6 m square tube, so positions must lie within ±1e6 m)."""
    p = np.asarray(p, dtype=float)
    M = p.shape[0]
    dummy = _dummy_tube()
    k = np.zeros(M, np.intp)
    B, _, _ = _evaluate(p, k, dummy, params, pairs, None)  # legs 1e6 m away: u3' = u4' = 0
    return B[B.shape[0] // 2:].view(np.float64).reshape(-1, 2)


def u3p_u4p(p, k, tubes: TubeArrays, params: ControllerParams) -> np.ndarray:
    """Leg avoidance terms u3' + u4' (Vtli1)/(Vtri1) with P_t = I − n_c n_cᵀ, (M, 2)."""
    p = np.asarray(p, dtype=float)
    empty = np.zeros(0, np.intp)
    B, _, _ = _evaluate(p, k, tubes, params, (empty, empty), None)
    return B[B.shape[0] // 2:].view(np.float64).reshape(-1, 2)


def u5(p, obstacles: Sequence[Obstacle], params: ControllerParams) -> np.ndarray:
    """Potential obstacle term of Appendix C: Σ_k −∂V_o,ik/∂p_i, (M, 2)."""
    p = np.asarray(p, dtype=float)
    out = np.zeros_like(p)
    for ob in obstacles:
        d = p - ob.center
        dist = np.hypot(d[:, 0], d[:, 1])
        dc = np.maximum(dist, X_MIN)
        dV = dV_n_dx(params.k4, dc, ob.radius + params.r_s, ob.radius + params.r_a,
                     params.eps_o, params.eps_s)
        out -= (dV / dc)[:, None] * d
    return out


def _dummy_tube() -> TubeArrays:
    """A huge rectangle: zero leg terms, u1'' = v e_y; used to isolate u2."""
    return TubeArrays.from_tubes([Trapezoid([-1e6, -1e6], [-1e6, 1e6], [1e6, -1e6],
                                            [1e6, 1e6])])
