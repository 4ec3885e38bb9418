"""Judge a mock flight from the mock's GROUND TRUTH, never from the controller's own view.

:class:`TruthLog` is a tick hook for :class:`~vtube_fleet.fleet.supervisor.Supervisor`: every
control tick it reads every mock vehicle's true state (``MockVehicle.position_ned`` about its
own origin) and converts it to the tube frame with the mission's frame. :func:`true_clearance`
then measures what the paper's limits are about, while a vehicle is airborne (more than 0.5 m
up) and inside the tube's length: pair distance > 2 r_s, distance to each leg > r_s, distance to
each obstacle's centre > r_o + r_s.

On a route the leg distances are those of the TRUE position to the legs of the segment the
vehicle flies (each tick's ``segment`` of the supervisor's table: which segment's controller,
and so which trapezoid's guarantee, applies to it — a mode of the controller, not its position
estimate): the paper's per-segment condition, not a lenient "some segment's legs". Only the
route's ends bound the judged stretch — behind the first segment's start base and past the last
one's finishing line (Assumption 2: exited) a vehicle is not judged, as for one tube —; in
between every airborne vehicle is judged against its segment's legs wherever it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Phases during which a vehicle counts for the true clearance (it may be in the air).
AIRBORNE = ("takeoff", "in_tube", "exited", "holding", "landing", "lost")


@dataclass
class TruthLog:
    fleet: object  # sim_stub.MockFleet
    mission: object  # vtube_fleet Mission
    t_s: list[float] = field(default_factory=list)
    xy: list[np.ndarray] = field(default_factory=list)  # (M, 2) true tube-frame positions
    up: list[np.ndarray] = field(default_factory=list)  # (M,) true height above the origin
    phases: list[tuple[str, ...]] = field(default_factory=list)
    segment: list[np.ndarray] = field(default_factory=list)  # (M,) the segment each flies
    supervisor: object = None

    def __call__(self, tick: int, sup: object) -> None:
        if self.supervisor is None:
            self.supervisor = sup
        vs = self.fleet.vehicles[: len(sup.pilots)]  # type: ignore[attr-defined]
        ned = np.array([v.position_ned for v in vs])
        org = np.array([v.origin for v in vs])
        x, y, up = self.mission.frame.local_ned_to_tube(  # type: ignore[attr-defined]
            ned[:, 0], ned[:, 1], ned[:, 2], org[:, 0], org[:, 1], org[:, 2])
        self.t_s.append(sup.t_s())  # type: ignore[attr-defined]
        self.xy.append(np.stack((np.atleast_1d(x), np.atleast_1d(y)), axis=1))
        self.up.append(np.atleast_1d(up))
        self.phases.append(tuple(p.phase.value for p in sup.pilots))  # type: ignore[attr-defined]
        self.segment.append(sup.table.segment.copy())  # type: ignore[attr-defined]


def true_clearance(log: TruthLog, lost: tuple[int, ...] = ()) -> dict[str, float]:
    """The worst true clearances of the flight (see the module docstring): ``pair`` (m),
    ``left_leg``/``right_leg`` (m, to the legs of each vehicle's segment), ``obstacle``
    (centre distance − r_o, m) and how many ticks counted. Vehicles in ``lost`` count as
    obstacles only while they still fly."""
    sc = log.mission.scenario  # type: ignore[attr-defined]
    corridor = sc.corridor
    segs = corridor.segments
    worst = {"pair": np.inf, "left_leg": np.inf, "right_leg": np.inf, "obstacle": np.inf,
             "ticks": 0}
    for xy, up, ph, seg in zip(log.xy, log.up, log.phases, log.segment, strict=True):
        air = np.isin(np.array(ph), AIRBORNE) & (up > 0.5)
        if not air.any():
            continue
        worst["ticks"] += 1
        q = xy[air]
        if len(q) > 1:
            d = np.hypot(*(q[:, None, :] - q[None, :, :]).transpose(2, 0, 1))
            worst["pair"] = min(worst["pair"], float(d[np.triu_indices(len(q), 1)].min()))
        # each vehicle judged against its own segment (never assigned yet: where it starts)
        s_air = np.where(seg[air] >= 0, seg[air], corridor.start_segment_of(q))
        for s, tube in enumerate(segs):
            mine = s_air == s
            if not mine.any():
                continue
            p = q[mine]
            xi = tube.xi(p)
            inside = np.ones(len(p), bool)
            if s == 0:
                inside &= xi >= 0.0  # not behind the route's start base
            if s == len(segs) - 1:
                inside &= xi <= tube.length  # not past its finishing line (exited)
            if inside.any():
                worst["left_leg"] = min(worst["left_leg"], float(tube.d_Th(p[inside]).min()))
                worst["right_leg"] = min(worst["right_leg"], float(tube.d_Tr(p[inside]).min()))
        for ob in sc.obstacles:
            worst["obstacle"] = min(worst["obstacle"],
                                    float((np.hypot(*(q - ob.center).T) - ob.radius).min()))
    return worst


def assert_true_clearance(log: TruthLog) -> dict[str, float]:
    """Assert the paper's limits on the truth; return the figures."""
    r_s = log.mission.scenario.robots.r_s  # type: ignore[attr-defined]
    w = true_clearance(log)
    assert w["ticks"] > 0, "no airborne tick recorded"
    assert w["pair"] > 2 * r_s, f"TRUE pair distance {w['pair']:.3f} m <= 2 r_s = {2 * r_s}"
    assert w["left_leg"] > r_s, f"TRUE left-leg distance {w['left_leg']:.3f} m <= r_s"
    assert w["right_leg"] > r_s, f"TRUE right-leg distance {w['right_leg']:.3f} m <= r_s"
    assert w["obstacle"] > r_s, f"TRUE obstacle clearance {w['obstacle']:.3f} m <= r_s"
    return w
