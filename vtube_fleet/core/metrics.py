"""Safety metrics of a swarm run (the quantities of the paper's Fig. 11) and the run summary.

Per time step, from robot positions p (M, 2) and velocities (M, 2):

* the minimum distance between two robots, safe iff > 2 r_s (S_i ∩ S_j = ∅);
* the minimum robot–obstacle **centre** distance ‖p_i − p_o,k‖, safe iff > r_o,k + r_s
  (S_i ∩ O_k = ∅; paper note 7: the triangle sides of the partition are virtual walls,
  this is the figure that matters);
* the minimum distance to the MAIN tube's left and right legs, d_Th (dtl) and d_Tr (dtr),
  safe iff > r_s (S_i ∩ ∂T = ∅); on a route, to the legs of the segment each robot flies
  (``segment=`` of :meth:`SafetyMonitor.evaluate`; docs/route.md);
* the minimum and maximum speed, safe iff within [v_min, v_max] (vminvmax), with a 1e-9 m/s
  tolerance for rounding.

A step *violates* when any of these fails. Everything is vectorized over a leading time axis:
``pos`` may be (K, M, 2), with NaN rows for robots that are not (or no longer) in the tube, so a
caller can evaluate a whole chunk of steps in one call. Pair distances are taken over candidate
pairs (I, J) — the controller's neighbour list, or :func:`vtube_fleet.core.neighbours.pairs_within`
within ``pair_radius`` — never an O(M²) matrix: a minimum pair distance of ``inf`` means "no two
robots closer than the search radius".

:class:`SummaryAccumulator` folds per-step metrics and exit events into the ``summary.json``
dictionary. The simulator, the fleet (from telemetry) and ``review`` (from a recording) all use
this module, so the numbers mean the same everywhere.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from vtube_fleet.core.tube import Obstacle, Trapezoid

__all__ = [
    "CONDITIONS",
    "METRIC_KEYS",
    "SafetyLimits",
    "SafetyMonitor",
    "StepMetrics",
    "SummaryAccumulator",
    "Verdict",
    "ViolationLog",
    "finite_or_none",
    "percentile_or_none",
    "truth_keys",
    "verdict",
]

#: Names of the safety conditions, as used in ``violations_by_condition``.
CONDITIONS: tuple[str, ...] = ("pair", "obstacle", "left_leg", "right_leg", "speed")

#: Per-step metric names (also the summary keys of their extrema over the run).
METRIC_KEYS: tuple[str, ...] = (
    "min_pair_distance_m",
    "min_obstacle_center_distance_m",
    "min_obstacle_clearance_m",
    "min_left_leg_distance_m",
    "min_right_leg_distance_m",
    "min_speed_m_s",
    "max_speed_m_s",
)


@dataclass(frozen=True, eq=False)
class StepMetrics:
    """Metrics of K steps, each field an array of shape (K,).

    ``min_obstacle_clearance_m`` is min ‖p_i − p_o,k‖ − r_o,k (compare with r_s; equals the
    centre distance minus r_o when all radii are equal). Minima over an empty set are ``inf``
    (no robot, no obstacle, no pair within the search radius); speeds are NaN when no velocity
    was given. ``robots`` is the number of robots present at each step. The ``*_violation``
    flags follow :data:`CONDITIONS`; ``violation`` is their OR.
    """

    min_pair_distance_m: np.ndarray
    min_obstacle_center_distance_m: np.ndarray
    min_obstacle_clearance_m: np.ndarray
    min_left_leg_distance_m: np.ndarray
    min_right_leg_distance_m: np.ndarray
    min_speed_m_s: np.ndarray
    max_speed_m_s: np.ndarray
    robots: np.ndarray
    pair_violation: np.ndarray
    obstacle_violation: np.ndarray
    left_leg_violation: np.ndarray
    right_leg_violation: np.ndarray
    speed_violation: np.ndarray

    @property
    def violation(self) -> np.ndarray:
        """(K,) bool: the step breaks at least one condition."""
        return (
            self.pair_violation
            | self.obstacle_violation
            | self.left_leg_violation
            | self.right_leg_violation
            | self.speed_violation
        )

    def __len__(self) -> int:
        return int(self.robots.shape[0])

    def flags(self, condition: str) -> np.ndarray:
        """The (K,) flags of one condition of :data:`CONDITIONS`."""
        return getattr(self, f"{condition}_violation")

    @classmethod
    def concatenate(cls, parts: Sequence[StepMetrics]) -> StepMetrics:
        """Join batches along the time axis (an empty sequence gives K = 0)."""
        names = [f.name for f in fields(cls)]
        if not parts:
            empty = {n: np.zeros(0, dtype=bool if n.endswith("violation") else float)
                     for n in names}
            empty["robots"] = np.zeros(0, dtype=np.int64)
            return cls(**empty)
        return cls(**{n: np.concatenate([getattr(p, n) for p in parts]) for n in names})

    def as_dict(self) -> dict[str, np.ndarray]:
        """Field name → array, plus ``violation`` (handy for ``np.savez``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["violation"] = self.violation
        return out


@dataclass(frozen=True)
class SafetyLimits:
    """The paper's safety limits, in one place: two robots > 2 r_s apart (pair), a robot more
    than r_s from each main-tube leg (left_leg, right_leg), its centre more than r_o,k + r_s
    from obstacle k's centre (obstacle: clearance ‖p − p_o‖ − r_o > r_s), speeds in
    [v_min, v_max] (speed). Always the PHYSICAL r_s (not the flown r_s' of the safety budget).
    """

    r_s: float
    v_min: float
    v_max: float

    @classmethod
    def from_params(cls, params: Any) -> SafetyLimits:
        return cls(float(params.r_s), float(params.v_min), float(params.v_max))

    @property
    def pair_m(self) -> float:
        """2 r_s: the limit of the minimum pair distance."""
        return 2.0 * self.r_s

    @property
    def leg_m(self) -> float:
        """r_s: the limit of the distance to a leg."""
        return self.r_s

    def obstacle_center_m(self, r_o: float) -> float:
        """r_o + r_s: the limit of the distance to an obstacle's centre."""
        return float(r_o) + self.r_s

    def limit(self, metric_key: str, obstacle_radii: Sequence[float] = ()) -> float | None:
        """The limit of a :data:`METRIC_KEYS` entry (the tightest over the obstacles for the
        centre distance), None for keys without one."""
        if metric_key.startswith("min_pair_distance"):
            return self.pair_m
        if metric_key.startswith(("min_left_leg", "min_right_leg", "min_obstacle_clearance")):
            return self.leg_m
        if metric_key.startswith("min_obstacle_center"):
            return (self.obstacle_center_m(min(obstacle_radii)) if len(obstacle_radii)
                    else None)
        if metric_key.startswith("min_speed"):
            return self.v_min
        if metric_key.startswith("max_speed"):
            return self.v_max
        return None


@dataclass(frozen=True, eq=False)
class SafetyMonitor:
    """The fixed data the metrics need: the MAIN tube (a route: every segment, ``segments``),
    the obstacles and the limits.

    ``pair_radius`` is the neighbour search radius used when no candidate pairs are given
    (``from_params`` uses r_s + r_a, the controller's own neighbourhood, which is larger than
    2 r_s so every violating pair is found). Build with :meth:`from_params`.
    """

    tube: Trapezoid
    obstacle_centers: np.ndarray
    obstacle_radii: np.ndarray
    r_s: float
    v_min: float
    v_max: float
    pair_radius: float
    speed_tol: float = 1e-9
    #: a route's segments (empty: one tube): the leg distances are then to the segment each
    #: robot flies (``segment=`` of :meth:`evaluate` and :meth:`explain`)
    segments: tuple[Trapezoid, ...] = ()
    _geom: dict[str, Any] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        c = np.asarray(self.obstacle_centers, dtype=float).reshape(-1, 2)
        r = np.asarray(self.obstacle_radii, dtype=float).reshape(-1)
        if c.shape[0] != r.shape[0]:
            raise ValueError("obstacle_centers and obstacle_radii differ in length")
        object.__setattr__(self, "obstacle_centers", c)
        object.__setattr__(self, "obstacle_radii", r)
        t = self.tube
        # d_Th(x) = n_hᵀx − n_hᵀp_h1 = Re(x conj(n_h)) − n_hᵀp_h1 in complex form; same for d_Tr
        geom = {
            "nh": complex(t.n_h[0], -t.n_h[1]),
            "nr": complex(t.n_r[0], -t.n_r[1]),
            "off_h": float(t.n_h @ t.p_h1),
            "off_r": float(t.n_r @ t.p_r1),
            "oc": (c[:, 0] + 1j * c[:, 1])[:, None],  # (P, 1)
        }
        if self.segments:  # per segment: conj(n), nᵀp_1 of both legs, (S,)
            segs = tuple(self.segments)
            object.__setattr__(self, "segments", segs)
            geom["seg"] = tuple(np.array(v) for v in (
                [complex(t.n_h[0], -t.n_h[1]) for t in segs], [float(t.n_h @ t.p_h1)
                                                                for t in segs],
                [complex(t.n_r[0], -t.n_r[1]) for t in segs], [float(t.n_r @ t.p_r1)
                                                                for t in segs]))
        object.__setattr__(self, "_geom", geom)

    def _legs(self, segment: np.ndarray | None) -> tuple | None:
        """(conj n_h, n_hᵀp_h1, conj n_r, n_rᵀp_r1) of each robot's segment (shaped like
        ``segment``), or None: the one tube's."""
        if segment is None or len(self.segments) <= 1:
            return None
        s = np.asarray(segment, dtype=np.intp)
        return tuple(a.take(s) for a in self._geom["seg"])

    @property
    def limits(self) -> SafetyLimits:
        return SafetyLimits(self.r_s, self.v_min, self.v_max)

    @classmethod
    def from_params(
        cls, tube: Trapezoid, obstacles: Iterable[Obstacle], params: Any
    ) -> SafetyMonitor:
        """From the main tube, the obstacles and a ``ControllerParams`` (r_s, r_a, v_min, v_max)."""
        obstacles = tuple(obstacles)
        return cls(
            tube=tube,
            obstacle_centers=np.array([o.center for o in obstacles], dtype=float).reshape(-1, 2),
            obstacle_radii=np.array([o.radius for o in obstacles], dtype=float),
            r_s=float(params.r_s),
            v_min=float(params.v_min),
            v_max=float(params.v_max),
            pair_radius=float(params.r_s + params.r_a),
        )

    @classmethod
    def for_corridor(cls, corridor: Any, params: Any, flown: Any = None) -> SafetyMonitor:
        """The monitor of a route (:class:`~vtube_fleet.core.route.Corridor`): its obstacles,
        the leg distances to each robot's own segment; one segment: :meth:`for_run` of its
        tube."""
        mon = cls.for_run(corridor.segments[0], corridor.obstacles, params, flown)
        if corridor.S == 1:
            return mon
        return dataclasses.replace(mon, segments=tuple(corridor.segments))

    @classmethod
    def for_run(cls, tube: Trapezoid, obstacles: Iterable[Obstacle], params: Any,
                flown: Any = None) -> SafetyMonitor:
        """The monitor of a run that flies inflated radii ``flown`` (r_s', r_a'): the limits
        of the physical ``params``, pairs searched within r_s' + r_a' + 1 m so that the
        minimum pair distance is reported even when nobody came within r_s + r_a. The fleet
        and ``review`` of its recording use this."""
        mon = cls.from_params(tube, obstacles, params)
        if flown is None:
            return mon
        return dataclasses.replace(mon, pair_radius=float(flown.r_s + flown.r_a + 1.0))

    # ----- the metrics ------------------------------------------------------------------
    def evaluate(
        self,
        pos: np.ndarray,
        vel: np.ndarray | None = None,
        *,
        pairs: tuple[np.ndarray, np.ndarray] | None = None,
        all_present: bool = False,
        min_pair: np.ndarray | None = None,
        segment: np.ndarray | None = None,
    ) -> StepMetrics:
        """Metrics of one step (``pos`` (M, 2)) or of K steps (``pos`` (K, M, 2)).

        ``segment`` (a route's monitor): each robot's segment, (M,) for every step or (K, M)
        step by step; the leg distances are to that segment's legs.

        NaN rows in ``pos`` are absent robots. ``pairs`` = (I, J) candidate pairs valid for all
        K steps (e.g. a Verlet list); without it, pairs within :attr:`pair_radius` are searched
        step by step with :func:`vtube_fleet.core.neighbours.pairs_within`.

        ``all_present=True`` promises that ``pos`` has no NaN and enables an exact pruned
        evaluation for long chunks (the simulator's case): with D_i = max_k ‖p_i(k) − p_i(0)‖,
        each distance of robot i (to a leg line, an obstacle centre, another robot) stays
        within D_i of its value at the first step (within D_i + D_j for a pair), so only the
        robots whose lower bound can reach the smallest upper bound are evaluated at every step.
        The minima are the same as without pruning.

        ``min_pair`` (K,): the minimum pair distances of the steps over ``pairs``, when the
        caller has them already (the simulator's controller computes every candidate pair's
        distance each step, :class:`vtube_fleet.core.controller.CommandEvaluator`); they are used
        as given.
        """
        pos = np.asarray(pos, dtype=float)
        single = pos.ndim == 2
        if single:
            pos = pos[None]
            vel = None if vel is None else np.asarray(vel, dtype=float)[None]
        if pos.ndim != 3 or pos.shape[-1] != 2:
            raise ValueError(f"pos must be (M, 2) or (K, M, 2), got {pos.shape}")
        k, m = pos.shape[0], pos.shape[1]
        # 2-D points as complex numbers: every array below has the robots on its last,
        # contiguous axis, so each numpy call is one tight loop (a trailing axis of length 2
        # would make broadcasting and reductions an order of magnitude slower)
        z = _as_complex(pos)  # (K, M)
        if min_pair is not None:
            min_pair = np.array(min_pair, dtype=float).reshape(-1)  # (a copy: kept)
            if min_pair.shape != (k,):
                raise ValueError(f"min_pair must have shape ({k},), got {min_pair.shape}")
        legs = self._legs(segment)
        if legs is not None and legs[0].ndim == 2 and legs[0].shape != (k, m):
            raise ValueError(f"segment must have shape ({m},) or ({k}, {m})")
        if all_present and m and (pairs is not None or min_pair is not None) and (
                legs is None or legs[0].ndim == 1):
            return self._evaluate_pruned(z, None if vel is None else np.asarray(vel, float),
                                         pairs, min_pair, legs)
        present = ~np.isnan(z.real)
        robots = present.sum(axis=1)
        g = self._geom
        fmin = np.fmin.reduce

        # legs of the MAIN tube, (dtl)/(dtr): d = Re(z conj(n)) − nᵀp_1 (a route: each
        # robot's segment)
        if legs is None:
            left = fmin((z * g["nh"]).real, axis=1, initial=np.inf) - g["off_h"]
            right = fmin((z * g["nr"]).real, axis=1, initial=np.inf) - g["off_r"]
        else:
            nh, oh, nr, orr = legs
            left = fmin((z * nh).real - oh, axis=1, initial=np.inf)
            right = fmin((z * nr).real - orr, axis=1, initial=np.inf)

        # obstacle centres: (K, P, M)
        if self.obstacle_radii.size and m:
            dist = np.abs(z[:, None, :] - g["oc"])
            dmin = fmin(dist, axis=2, initial=np.inf)  # (K, P)
            min_center = fmin(dmin, axis=1, initial=np.inf)
            min_clear = fmin(dmin - self.obstacle_radii, axis=1, initial=np.inf)
        else:
            min_center = np.full(k, np.inf)
            min_clear = np.full(k, np.inf)

        # pairs (unless given by the caller)
        if min_pair is None and pairs is not None:
            i_idx, j_idx = np.asarray(pairs[0]), np.asarray(pairs[1])
            if i_idx.size:
                dpair = np.abs(z.take(i_idx, axis=1) - z.take(j_idx, axis=1))
                min_pair = fmin(dpair, axis=1, initial=np.inf)
            else:
                min_pair = np.full(k, np.inf)
        elif min_pair is None:
            min_pair = np.array([self._min_pair_search(pos[s], present[s]) for s in range(k)])

        # speeds
        if vel is not None:
            vel = np.asarray(vel, dtype=float)
            if vel.shape != pos.shape:
                raise ValueError(f"vel shape {vel.shape} differs from pos shape {pos.shape}")
            speed = np.abs(_as_complex(vel))
            speed[~present] = np.nan
            vmin = fmin(speed, axis=1, initial=np.inf)
            vmax = np.fmax.reduce(speed, axis=1, initial=-np.inf)
            empty = robots == 0
            vmin[empty] = np.nan
            vmax[empty] = np.nan
            speed_bad = self._speed_bad(vmin, vmax)
        else:
            vmin, vmax, speed_bad = self._no_speeds(k)

        return self._result(min_pair, min_center, min_clear, left, right, vmin, vmax,
                            robots.astype(np.int64), speed_bad)

    def _evaluate_pruned(
        self, z: np.ndarray, vel: np.ndarray | None, pairs: tuple[np.ndarray, np.ndarray] | None,
        min_pair: np.ndarray | None = None, legs: tuple | None = None,
    ) -> StepMetrics:
        """:meth:`evaluate` for NaN-free chunks, evaluating only candidates (see there).

        The few candidates are gathered from the chunk's columns and laid out (C, K), so that
        every minimum over them is a reduction along axis 0 (fast in numpy; along a short last
        axis it is not); the squared speeds of all robots likewise as their transpose (M, K).
        """
        k, m = z.shape
        g = self._geom
        z0 = z[0]
        # D_i, bounded from above by the box of robot i's positions (2 reductions instead of
        # |z − z0| of every step): a larger D_i only adds candidates, the minima are the same
        if k > 1:
            zf, z0f = z.view(np.float64), z0.view(np.float64)
            ext = np.maximum(np.maximum.reduce(zf, axis=0) - z0f,
                             z0f - np.minimum.reduce(zf, axis=0))
            disp = np.abs(ext.view(np.complex128)) * (1.0 + 1e-12)
        else:
            disp = np.zeros(m)
        minimum = np.minimum.reduce

        def rows(c: np.ndarray) -> np.ndarray:  # (C, K): the candidates' positions
            return np.ascontiguousarray(z.take(c, axis=1).T)

        def leg(n: complex, off: float) -> np.ndarray:
            d0 = (z0 * n).real
            cand = np.flatnonzero(d0 - disp <= (d0 + disp).min())
            return minimum((rows(cand) * n).real, axis=0) - off

        def legs_of(n: np.ndarray, off: np.ndarray) -> np.ndarray:  # each robot its own leg
            d0 = (z0 * n).real - off
            cand = np.flatnonzero(d0 - disp <= (d0 + disp).min())
            return minimum((rows(cand) * n.take(cand)[:, None]).real
                           - off.take(cand)[:, None], axis=0)

        if legs is None:
            left = leg(g["nh"], g["off_h"])
            right = leg(g["nr"], g["off_r"])
        else:
            left = legs_of(legs[0], legs[1])
            right = legs_of(legs[2], legs[3])

        radii = self.obstacle_radii
        if radii.size:
            oc = g["oc"]  # (P, 1)
            d0 = np.abs(z0 - oc)  # (P, M)
            lo = d0 - disp
            hi = d0 + disp
            r = radii[:, None]
            cand = (lo <= hi.min()) | (lo - r <= (hi - r).min())
            pi, mi = np.nonzero(cand)
            dd = np.abs(rows(mi) - oc.take(pi, axis=0))  # (C, K)
            min_center = minimum(dd, axis=0)
            min_clear = minimum(dd - r.take(pi, axis=0), axis=0)
        else:
            min_center = np.full(k, np.inf)
            min_clear = np.full(k, np.inf)

        if min_pair is None:  # (else given by the caller)
            i_idx, j_idx = np.asarray(pairs[0]), np.asarray(pairs[1])
            if i_idx.size:
                d0 = np.abs(z0.take(i_idx) - z0.take(j_idx))
                slack = disp.take(i_idx) + disp.take(j_idx)
                cand = np.flatnonzero(d0 - slack <= (d0 + slack).min())
                ci, cj = i_idx.take(cand), j_idx.take(cand)
                min_pair = minimum(np.abs(rows(ci) - rows(cj)), axis=0)
            else:
                min_pair = np.full(k, np.inf)

        if vel is not None:
            if vel.shape != (k, m, 2):
                raise ValueError(f"vel shape {vel.shape} differs from pos shape {(k, m, 2)}")
            zv = _as_complex(vel)  # (K, M): the minima over the robots, along the last axis
            # ‖v‖², reduced along the robots as the contiguous columns of its transpose
            sp2 = np.ascontiguousarray((zv * zv.conj()).real.T)
            vmin = np.sqrt(minimum(sp2, axis=0))
            vmax = np.sqrt(np.maximum.reduce(sp2, axis=0))
            speed_bad = self._speed_bad(vmin, vmax)
        else:
            vmin, vmax, speed_bad = self._no_speeds(k)
        return self._result(min_pair, min_center, min_clear, left, right, vmin, vmax,
                            np.full(k, m, dtype=np.int64), speed_bad)

    def explain(self, pos: np.ndarray, vel: np.ndarray | None = None,
                segment: np.ndarray | None = None) -> list[dict[str, Any]]:
        """What breaks the limits in ONE step (``pos`` (M, 2), NaN rows absent): one entry per
        broken condition, the worst offender: ``condition``, ``value`` (m or m/s), ``limit``
        and ``robots`` (indices into ``pos``). ``segment`` (M,): each robot's segment (a
        route). For reports; O(M²) in the pairs."""
        p = np.asarray(pos, dtype=float).reshape(-1, 2)
        ok = np.flatnonzero(np.isfinite(p[:, 0]) & np.isfinite(p[:, 1]))
        lim = self.limits
        out: list[dict[str, Any]] = []
        if ok.size > 1:
            q = p[ok]
            d = np.hypot(*(q[:, None, :] - q[None, :, :]).transpose(2, 0, 1))
            d[np.tril_indices(len(q))] = np.inf
            i, j = np.unravel_index(int(np.argmin(d)), d.shape)
            if d[i, j] <= lim.pair_m:
                out.append({"condition": "pair", "value": float(d[i, j]), "limit": lim.pair_m,
                            "robots": [int(ok[i]), int(ok[j])]})
        if ok.size:
            q = p[ok]
            t = self.tube
            legs = self._legs(None if segment is None else np.asarray(segment).reshape(-1)[ok])
            if legs is None:
                dists = (t.d_Th(q), t.d_Tr(q))
            else:
                zq = q[:, 0] + 1j * q[:, 1]
                dists = ((zq * legs[0]).real - legs[1], (zq * legs[2]).real - legs[3])
            for cond, dist in zip(("left_leg", "right_leg"), dists, strict=True):
                k = int(np.argmin(dist))
                if dist[k] <= lim.leg_m:
                    out.append({"condition": cond, "value": float(dist[k]), "limit": lim.leg_m,
                                "robots": [int(ok[k])]})
            for c, r in zip(self.obstacle_centers, self.obstacle_radii, strict=True):
                dc = np.hypot(*(q - c).T)
                k = int(np.argmin(dc))
                if dc[k] - r <= lim.leg_m:
                    out.append({"condition": "obstacle", "value": float(dc[k]),
                                "limit": lim.obstacle_center_m(r), "robots": [int(ok[k])],
                                "obstacle_center": [float(c[0]), float(c[1])]})
            if vel is not None:
                sp = np.hypot(*np.asarray(vel, dtype=float).reshape(-1, 2)[ok].T)
                for k in np.flatnonzero((sp < lim.v_min - self.speed_tol)
                                        | (sp > lim.v_max + self.speed_tol))[:1]:
                    out.append({"condition": "speed", "value": float(sp[k]),
                                "limit": lim.v_min if sp[k] < lim.v_min else lim.v_max,
                                "robots": [int(ok[k])]})
        return out

    def breaks(self, metric_key: str, values: np.ndarray) -> tuple[str, np.ndarray] | None:
        """(condition of :data:`CONDITIONS`, (K,) bool) for a per-step series of a
        :data:`METRIC_KEYS` entry (any stream suffix, or ``truth_`` prefix): the values that
        break the limit, by the rule of the violation flags (``min_speed`` below v_min,
        ``max_speed`` above v_max, within ``speed_tol``; distances at or below their limit).
        None for the obstacle-centre distance (its limit depends on the obstacle: the
        clearance carries the condition) and for keys without a limit."""
        base = metric_key.removeprefix("truth_").removesuffix("_truth").removesuffix("_center")
        v = np.asarray(values, dtype=float)
        lim = self.limits
        if base == "min_pair_distance_m":
            return "pair", v <= lim.pair_m
        if base == "min_obstacle_clearance_m":
            return "obstacle", v <= lim.leg_m
        if base == "min_left_leg_distance_m":
            return "left_leg", v <= lim.leg_m
        if base == "min_right_leg_distance_m":
            return "right_leg", v <= lim.leg_m
        if base == "min_speed_m_s":
            return "speed", v < self.v_min - self.speed_tol
        if base == "max_speed_m_s":
            return "speed", v > self.v_max + self.speed_tol
        return None

    def _speed_bad(self, vmin: np.ndarray, vmax: np.ndarray) -> np.ndarray:
        """Steps whose slowest or fastest robot leaves [v_min, v_max] (within the tolerance)."""
        return self.breaks("min_speed_m_s", vmin)[1] | self.breaks("max_speed_m_s", vmax)[1]

    @staticmethod
    def _no_speeds(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vmin, vmax, speed_bad) of ``k`` steps without velocities: unknown, never bad."""
        return np.full(k, np.nan), np.full(k, np.nan), np.zeros(k, dtype=bool)

    def _result(self, min_pair: np.ndarray, min_center: np.ndarray, min_clear: np.ndarray,
                left: np.ndarray, right: np.ndarray, vmin: np.ndarray, vmax: np.ndarray,
                robots: np.ndarray, speed_bad: np.ndarray) -> StepMetrics:
        def bad(key: str, v: np.ndarray) -> np.ndarray:
            return self.breaks(key, v)[1]  # type: ignore[index]

        return StepMetrics(
            min_pair_distance_m=min_pair,
            min_obstacle_center_distance_m=min_center,
            min_obstacle_clearance_m=min_clear,
            min_left_leg_distance_m=left,
            min_right_leg_distance_m=right,
            min_speed_m_s=vmin,
            max_speed_m_s=vmax,
            robots=robots,
            pair_violation=bad("min_pair_distance_m", min_pair),
            obstacle_violation=bad("min_obstacle_clearance_m", min_clear),
            left_leg_violation=bad("min_left_leg_distance_m", left),
            right_leg_violation=bad("min_right_leg_distance_m", right),
            speed_violation=speed_bad,
        )

    def _min_pair_search(self, p: np.ndarray, present: np.ndarray) -> float:
        from vtube_fleet.core.neighbours import pairs_within

        q = p[present]
        if q.shape[0] < 2:
            return math.inf
        i_idx, j_idx = pairs_within(q, self.pair_radius)
        if len(i_idx) == 0:
            return math.inf
        d = q[i_idx] - q[j_idx]
        return float(np.sqrt(np.einsum("pd,pd->p", d, d)).min())


def _as_complex(a: np.ndarray) -> np.ndarray:
    """(..., 2) float → (...) complex view (copy only if the last axis is not contiguous)."""
    if a.strides[-1] != a.itemsize:
        a = np.ascontiguousarray(a)
    return a.view(np.complex128)[..., 0]


def finite_or_none(x: float | None) -> float | None:
    """A summary number: ``x`` as a float, ``None`` (JSON null) when missing, NaN or inf."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def percentile_or_none(values: Iterable[float] | np.ndarray, q: float) -> float | None:
    """A summary percentile: the ``q``-th percentile of the finite ``values``, or ``None``."""
    a = np.asarray(values if isinstance(values, np.ndarray) else list(values), dtype=float)
    a = a[np.isfinite(a)]
    return float(np.percentile(a, q)) if a.size else None


class SummaryAccumulator:
    """Folds per-step :class:`StepMetrics` and exit events into the ``summary.json`` dict.

    Several metric *streams* can be fed, distinguished by a key suffix: the simulator feeds the
    unicycle's control points as ``""`` and its robot centres as ``"_center"`` (paper note
    10). Steps are counted on the ``""`` stream.

    Summary keys: ``robots``, ``exited``, ``last_exit_s``, ``median_exit_s``, the extrema of
    :data:`METRIC_KEYS` (``min_…`` are minima, ``max_speed_m_s`` a maximum, ``None`` when
    nothing was measured), ``violations`` (steps breaking any condition),
    ``violations_by_condition`` and ``first_violation_s``, each with the stream's suffix, and
    ``steps``; callers add their own (``dt_s``, ``wall_s`` ...) through :meth:`summary`.
    """

    def __init__(self, robots: int) -> None:
        self.robots = int(robots)
        self.exit_time_s = np.full(self.robots, np.nan)
        self.steps = 0
        self._streams: dict[str, dict[str, Any]] = {}

    def _stream(self, suffix: str) -> dict[str, Any]:
        st = self._streams.get(suffix)
        if st is None:
            st = {key: (-math.inf if key.startswith("max_") else math.inf) for key in METRIC_KEYS}
            st["violations"] = 0
            st["by_condition"] = dict.fromkeys(CONDITIONS, 0)
            st["first_violation_s"] = None
            self._streams[suffix] = st
        return st

    def add(self, t_s: np.ndarray | float, metrics: StepMetrics, suffix: str = "") -> None:
        """Add K steps of metrics taken at times ``t_s`` (K,)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if len(metrics) == 0:
            return
        st = self._stream(suffix)
        for key in METRIC_KEYS:
            vals = getattr(metrics, key)
            if key.startswith("max_"):
                st[key] = float(np.fmax(st[key], np.fmax.reduce(vals, initial=-np.inf)))
            else:
                st[key] = float(np.fmin(st[key], np.fmin.reduce(vals, initial=np.inf)))
        bad = metrics.violation
        n_bad = int(np.count_nonzero(bad))
        if n_bad:
            st["violations"] += n_bad
            for c in CONDITIONS:
                st["by_condition"][c] += int(np.count_nonzero(metrics.flags(c)))
            if st["first_violation_s"] is None:
                st["first_violation_s"] = float(t[np.argmax(bad)])
        if suffix == "":
            self.steps += len(metrics)

    def add_exits(self, t_s: float, robot_ids: Iterable[int] | np.ndarray) -> None:
        """Robots ``robot_ids`` (indices in config order) reached the finishing line at ``t_s``."""
        ids = np.asarray(list(robot_ids) if not isinstance(robot_ids, np.ndarray) else robot_ids,
                         dtype=np.int64)
        self.exit_time_s[ids] = float(t_s)

    @property
    def exited(self) -> int:
        return int(np.count_nonzero(~np.isnan(self.exit_time_s)))

    def summary(self, **extra: Any) -> dict[str, Any]:
        """The summary dict (JSON-ready); ``extra`` keys are added (and win on conflicts)."""
        done = self.exit_time_s[~np.isnan(self.exit_time_s)]
        out: dict[str, Any] = {
            "robots": self.robots,
            "exited": int(done.size),
            "last_exit_s": finite_or_none(done.max()) if done.size else None,
            "median_exit_s": finite_or_none(np.median(done)) if done.size else None,
        }
        for suffix in sorted(self._streams or {"": None}, key=lambda s: (s != "", s)):
            st = self._stream(suffix)
            for key in METRIC_KEYS:
                out[f"{key}{suffix}"] = finite_or_none(st[key])
            out[f"violations{suffix}"] = int(st["violations"])
            out[f"violations_by_condition{suffix}"] = dict(st["by_condition"])
            out[f"first_violation_s{suffix}"] = st["first_violation_s"]
        out["steps"] = self.steps
        out.update(extra)
        return out


@dataclass(frozen=True)
class Verdict:
    """Whether a run kept the limits (:func:`verdict`): ``safe``; ``violations`` (steps that
    broke a limit) per judged stream; ``first`` the first violation as recorded (time,
    condition, figure, limit, robots) or None; ``summary_line`` for people."""

    safe: bool
    violations: dict[str, int]
    first: dict[str, Any] | None

    @property
    def summary_line(self) -> str:
        if self.safe:
            return "safe: every limit kept"
        f = self.first or {}
        where = ""
        if f:
            who = ", ".join(str(r) for r in f.get("vehicles", f.get("robots", [])))
            nan = float("nan")
            where = (f"; first at t = {f.get('t_s', nan):.2f} s: {f.get('condition')} "
                     f"{f.get('value', nan):.3f} m (limit {f.get('limit', nan):.3f} m)"
                     + (f", vehicle(s) {who}" if who else "")
                     + (f" ({f['source']})" if f.get("source") else ""))
        counts = ", ".join(f"{n} step(s) by {k or 'telemetry'}" for k, n in
                           self.violations.items() if n)
        return f"UNSAFE: limits broken in {counts}{where}"


def verdict(summary: dict[str, Any], streams: Sequence[str] = ("",)) -> Verdict:
    """THE decision whether a run was safe, from its summary: any step of a judged stream
    (``""`` = the run's own telemetry in the tube, ``"_truth"`` = ground truth where the
    simulator provides it) that broke a limit makes it unsafe. Used by the fleet, the MQTT
    coordinator and agents, the simulator and ``review``."""
    def key(s: str) -> str:
        k = f"violations{s}"
        return "truth_violations" if s == "_truth" and k not in summary else k

    counts = {s: int(summary.get(key(s)) or 0) for s in streams if key(s) in summary}
    first = summary.get("first_violation")
    return Verdict(not any(counts.values()), counts, first if isinstance(first, dict) else None)


class ViolationLog:
    """The first violation of each judged stream, explained (:meth:`SafetyMonitor.explain`):
    ``first`` is the earliest over the streams (the summary's ``first_violation``: time,
    source, condition, value, limit, vehicle ids). :meth:`note` returns the entry the first
    time a stream breaks a limit (for the caller to announce), else None."""

    SOURCES = {"": "telemetry", "_truth": "ground truth", "_center": "robot centres"}

    def __init__(self, monitor: SafetyMonitor) -> None:
        self.monitor = monitor
        self.first: dict[str, Any] | None = None
        self._seen: set[str] = set()

    def note(self, t_s: float, suffix: str, metrics: StepMetrics, pos: np.ndarray,
             vel: np.ndarray | None, ids: Sequence[int],
             segment: np.ndarray | None = None) -> dict[str, Any] | None:
        if suffix in self._seen or not bool(np.asarray(metrics.violation).any()):
            return None
        what = self.monitor.explain(pos, vel, segment)
        if not what:
            return None
        self._seen.add(suffix)
        w = what[0]
        entry = {"t_s": round(float(t_s), 3), "source": self.SOURCES.get(suffix, suffix),
                 "condition": w["condition"], "value": round(w["value"], 4),
                 "limit": round(w["limit"], 4), "vehicles": [int(ids[r]) for r in w["robots"]]}
        if self.first is None:
            self.first = entry
        return entry


def truth_keys(summary: dict[str, Any]) -> dict[str, Any]:
    """A summary with the ground-truth stream's keys as ``truth_<key>``
    (``min_pair_distance_m_truth`` → ``truth_min_pair_distance_m``): how the fleet's summary
    names them, and ``review`` too."""
    out: dict[str, Any] = {}
    for k, v in summary.items():
        out["truth_" + k[: -len("_truth")] if k.endswith("_truth") else k] = v
    return out
