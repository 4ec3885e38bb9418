"""Defence in depth on the vehicle: PX4's own geofence from the route, and the audit of the PX4
parameters the mission relies on (``docs/fleet.md``, "The fence on the vehicle" and "The PX4
parameter audit").

* :func:`fence_items` turns :func:`vtube_fleet.core.fence.route_fence` (the tube frame: one
  inclusion polygon per segment of the route, PX4 allows their union; the exclusion circles)
  into PX4 fence items (WGS84); :func:`install_fence` sets GF_ACTION, uploads them, reads them
  back and compares, on one link.
* :func:`audit_rules` are the parameters checked with the mission's numbers;
  :func:`audit_fleet` reads them from every vehicle, returns the hard problems (refuse to arm),
  the warnings, and — with ``fix`` — sets them, returning the old values for
  :func:`restore_params`.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from vtube_fleet.config.mission import Mission
from vtube_fleet.core.fence import RouteFence
from vtube_fleet.core.text import compact_number
from vtube_fleet.errors import PROBLEMS_SHOWN
from vtube_fleet.link.base import (
    FenceItem,
    FenceRejected,
    LinkError,
    LinkTimeout,
    LinkUnsupported,
    VehicleLink,
)

T = TypeVar("T")

__all__ = [
    "AuditResult",
    "GF_ACTION_VALUES",
    "NO_FENCE_WARNING",
    "ParamRule",
    "ONBOARD_WINDOW",
    "audit_fleet",
    "audit_rules",
    "gather_bounded",
    "fence_geometry",
    "fence_items",
    "install_fence",
    "restore_params",
]

#: mission ``fence_action`` → PX4 GF_ACTION (geofence_params.yaml: 2 Hold, 3 Return, 5 Land)
GF_ACTION_VALUES: dict[str, int] = {"hold": 2, "rtl": 3, "land": 5}
#: what ``run --no-fence`` and ``agent --no-fence`` say (an info event: the user asked for it)
NO_FENCE_WARNING = ("--no-fence: no geofence uploaded; PX4 does not know the tube and a "
                    "vehicle that our process loses can leave it")
#: vehicles whose parameter / fence exchanges run at once (the rest wait for a slot): a
#: thousand vehicles answering PARAM_REQUEST_READ together would overrun the sockets' buffers
#: and the per-try timeouts of a busy process
ONBOARD_WINDOW = 64
#: an audit read that times out is repeated, up to this many reads in all
AUDIT_READ_ROUNDS = 3
CMD_POLYGON_INCLUSION = 5001
CMD_CIRCLE_EXCLUSION = 5004


def fence_geometry(mission: Mission) -> RouteFence:
    """The mission's fence in the tube frame (the route's outline, one polygon per segment):
    :meth:`Mission.fence_geometry <vtube_fleet.config.mission.Mission.fence_geometry>`."""
    return mission.fence_geometry()


def fence_items(mission: Mission, geom: RouteFence | None = None) -> list[FenceItem]:
    """PX4 fence items: one inclusion polygon (5001, param1 = its vertex count) per segment
    of the route, in order, then one exclusion circle (5004, param1 = radius) per obstacle,
    positions via the mission's tube frame."""
    geom = fence_geometry(mission) if geom is None else geom
    frame = mission.frame
    items = []
    for poly in geom.polygons:
        lat, lon, _ = frame.tube_to_geodetic(poly[:, 0], poly[:, 1], 0.0)
        n = len(poly)
        items += [FenceItem(CMD_POLYGON_INCLUSION, float(a), float(b), float(n))
                  for a, b in zip(np.atleast_1d(lat), np.atleast_1d(lon), strict=True)]
    if geom.circle_radii.size:
        clat, clon, _ = frame.tube_to_geodetic(geom.circle_centers[:, 0],
                                               geom.circle_centers[:, 1], 0.0)
        items += [FenceItem(CMD_CIRCLE_EXCLUSION, float(a), float(b), float(r))
                  for a, b, r in zip(np.atleast_1d(clat), np.atleast_1d(clon),
                                     geom.circle_radii, strict=True)]
    return items


def _same_item(a: FenceItem, b: FenceItem) -> bool:
    return (a.command == b.command and round(a.lat_deg * 1e7) == round(b.lat_deg * 1e7)
            and round(a.lon_deg * 1e7) == round(b.lon_deg * 1e7)
            and math.isclose(a.param1, b.param1, rel_tol=1e-6, abs_tol=1e-4))


async def gather_bounded(coros: Sequence[Awaitable[T]], limit: int | None = None
                         ) -> list[T | BaseException]:
    """``asyncio.gather(*coros, return_exceptions=True)`` with at most ``limit`` (default
    :data:`ONBOARD_WINDOW`) running at once; results in order."""
    window = asyncio.Semaphore(ONBOARD_WINDOW if limit is None else limit)

    async def one(coro: Awaitable[T]) -> T:
        async with window:
            return await coro

    return await asyncio.gather(*(one(c) for c in coros), return_exceptions=True)


async def install_fence(link: VehicleLink, items: list[FenceItem], gf_action: int) -> None:
    """GF_ACTION, upload, download and compare: :class:`FenceRejected` naming the first
    difference; :class:`LinkUnsupported` from backends without fences."""
    got = await link.set_param("GF_ACTION", float(gf_action))
    if round(got) != gf_action:
        raise FenceRejected(f"{link.name}: GF_ACTION = {got:g} after setting {gf_action}",
                            result="PARAM")
    await link.upload_fence(items)
    back = await link.download_fence()
    if len(back) != len(items):
        raise FenceRejected(f"{link.name}: fence read back has {len(back)} items, uploaded "
                            f"{len(items)}", result="MISMATCH")
    for k, (a, b) in enumerate(zip(items, back, strict=True)):
        if not _same_item(a, b):
            raise FenceRejected(f"{link.name}: fence item {k} read back as {b}, uploaded {a}",
                                result="MISMATCH")


# -- the parameter audit ------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamRule:
    """One PX4 parameter the mission relies on: ``problem(value)`` is None when fine, else the
    message; ``fix`` the value ``--fix-params`` sets; ``hard`` problems refuse to arm."""

    name: str
    hard: bool
    problem: Callable[[float], str | None]
    fix: float


def _n(x: float) -> str:
    return compact_number(float(x), 2)


_OBL_NAMES = {0: "Position mode (without RC PX4 descends where it is: captures)",
              1: "Altitude mode (descends without RC)", 2: "Stabilized (descends without RC)",
              3: "Return (climbs to RTL_RETURN_ALT and flies home across the others' paths)",
              4: "Land", 5: "Hold", 6: "Terminate", 7: "Disarm"}
_DLL_NAMES = {0: "disabled", 1: "Hold", 2: "Return (climbs and flies home across the tube)",
              3: "Land", 5: "Terminate", 6: "Disarm"}


#: a jerk-limited start from rest (PX4's S-curve, jerk j, no acceleration cap) reaches
#: 1 − 1/e of a speed step V after (2 − √(2/e)) √(V / j): within t63 when j ≥ this × V / t63²
JERK_T63_FACTOR = (2.0 - math.sqrt(2.0 / math.e)) ** 2
#: PX4's largest MPC_JERK_AUTO (multicopter_autonomous_params.yaml): ``--fix-params`` sets no more
JERK_AUTO_MAX = 80.0


def _up(x: float, step: float) -> float:
    """``x`` rounded up to a multiple of ``step`` = 1 / n (what ``--fix-params`` sets)."""
    n = round(1.0 / step)
    return math.ceil(x * n - 1e-9) / n


def _at_least(need: float, why: Callable[[float], str]) -> Callable[[float], str | None]:
    """A rule "the parameter must be at least ``need``": None when it is, else ``why(x)``."""
    return lambda x: None if x >= need else why(x)


def audit_rules(mission: Mission) -> list[ParamRule]:
    """The parameters checked against ``mission`` (docs/fleet.md lists why)."""
    sc, cfg = mission.scenario, mission.config
    v_max = float(sc.controller.v_max)
    d = float(cfg.disturbance_residual_m_s) if cfg.compensate_estimate else 0.0
    t63 = max(float(cfg.tracking_t63_s), 1e-3)
    acc_need = v_max / t63
    jerk_need = JERK_T63_FACTOR * v_max / t63 ** 2
    # PX4 judges GF_MAX_VER_DIST on its estimate of the height above home (the slots are on
    # the ground, origin_alt_m): the take-off ends within altitude_tolerance_m of altitude_m
    ceiling_need = float(cfg.altitude_m) + float(cfg.altitude_tolerance_m)
    climb, hold_v = float(cfg.climb_speed_m_s), float(cfg.max_vertical_speed_m_s)
    up_need = max(climb, hold_v)
    up_what = ("climb_speed_m_s" if climb >= hold_v else "max_vertical_speed_m_s")

    vel = _at_least(v_max, lambda x: (
        f"MPC_XY_VEL_MAX = {_n(x)} m/s < v_max = {_n(v_max)} m/s (PX4 would clip the "
        f"controller's speeds)"))
    acc = _at_least(acc_need, lambda x: (
        f"MPC_ACC_HOR = {_n(x)} m/s² < v_max / t63 = {_n(acc_need)} m/s²: PX4 reaches "
        f"a commanded speed more slowly than the tracking_t63_s = {_n(t63)} s the safety "
        f"budget assumes"))

    def loss(x: float) -> str | None:
        if x <= 1.0:
            return None
        return (f"COM_OF_LOSS_T = {_n(x)} s > 1 s: when our setpoints stop, PX4 flies the last "
                f"one for up to {_n(x * v_max)} m (at v_max) before its failsafe")

    def obl(x: float) -> str | None:
        if round(x) in (4, 5):
            return None
        return (f"COM_OBL_RC_ACT = {round(x)}, {_OBL_NAMES.get(round(x), 'unknown')}: on "
                f"offboard loss a vehicle should hold (5) or land (4) where it is")

    def dll(x: float) -> str | None:
        if round(x) == 3:
            return None
        return (f"NAV_DLL_ACT = {round(x)} ({_DLL_NAMES.get(round(x), 'unknown')}): a vehicle "
                f"whose ground station is gone for COM_DL_LOSS_T should land (3), not hover "
                f"until its battery fails")

    def ceiling(x: float) -> str | None:
        if x <= 0.0 or x >= ceiling_need:  # 0 = disabled (PX4 geofence_params.yaml)
            return None
        return (f"GF_MAX_VER_DIST = {_n(x)} m < altitude_m + altitude_tolerance_m = "
                f"{_n(ceiling_need)} m: PX4's own fence ceiling (height above home) would "
                f"breach during the climb and take the vehicle out of offboard (GF_ACTION); "
                f"lower altitude_m or raise GF_MAX_VER_DIST")

    def z_up(x: float) -> str | None:
        if x >= up_need:
            return None
        head = f"MPC_Z_VEL_MAX_UP = {_n(x)} m/s < {up_what} = {_n(up_need)} m/s: PX4 clips"
        if x >= climb:
            return (f"{head} the altitude-hold climbs (slower height corrections; the "
                    f"horizontal flight is not affected)")
        slow, plan = cfg.altitude_m / max(x, 1e-3), cfg.altitude_m / climb
        late = (f", longer than takeoff_timeout_s = {_n(cfg.takeoff_timeout_s)} s: the "
                f"take-off will time out" if slow > cfg.takeoff_timeout_s else "")
        return (f"{head} the climb (take-off {_n(slow)} s instead of {_n(plan)} s{late}); "
                f"the horizontal flight is not affected")

    z_dn = _at_least(hold_v, lambda x: (
        f"MPC_Z_VEL_MAX_DN = {_n(x)} m/s < max_vertical_speed_m_s = {_n(hold_v)} m/s: "
        f"PX4 clips the altitude-hold descents (slower height corrections; the "
        f"horizontal flight is not affected)"))
    jerk = _at_least(jerk_need, lambda x: (
        f"MPC_JERK_AUTO = {_n(x)} m/s³ < {_n(JERK_T63_FACTOR)} v_max / t63² = "
        f"{_n(jerk_need)} m/s³: a jerk-limited start reaches 63 % of a v_max step "
        f"later than the tracking_t63_s = {_n(t63)} s the safety budget assumes"))

    vel_fix = _up(v_max + d, 0.1)
    return [
        ParamRule("MPC_XY_VEL_MAX", True, vel, vel_fix),
        ParamRule("GF_MAX_VER_DIST", True, ceiling, _up(ceiling_need, 1.0)),
        ParamRule("MPC_ACC_HOR", False, acc, _up(acc_need, 0.1)),
        ParamRule("MPC_JERK_AUTO", False, jerk, min(_up(jerk_need, 0.1), JERK_AUTO_MAX)),
        ParamRule("MPC_Z_VEL_MAX_UP", False, z_up, _up(up_need, 0.1)),
        ParamRule("MPC_Z_VEL_MAX_DN", False, z_dn, _up(hold_v, 0.1)),
        ParamRule("COM_OF_LOSS_T", False, loss, 1.0),
        ParamRule("COM_OBL_RC_ACT", False, obl, 5.0),
        ParamRule("NAV_DLL_ACT", False, dll, 3.0),
    ]


@dataclass
class AuditResult:
    """What :func:`audit_fleet` found: ``problems`` (refuse to arm), ``warnings``,
    ``values[i][name]`` as read, ``changed[i][name]`` = the old value of what was set."""

    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    values: list[dict[str, float]] = field(default_factory=list)
    changed: list[dict[str, float]] = field(default_factory=list)
    unsupported: bool = False


async def _read_param(link: VehicleLink, name: str) -> float:
    """``link.read_param`` repeated :data:`AUDIT_READ_ROUNDS` times while it times out (a busy
    vehicle or link, as with hundreds of vehicles on one computer)."""
    for k in range(AUDIT_READ_ROUNDS):
        try:
            return await link.read_param(name)
        except LinkTimeout as exc:
            if k == AUDIT_READ_ROUNDS - 1:
                raise LinkTimeout(f"{exc}; read {AUDIT_READ_ROUNDS} times") from None
    raise AssertionError("unreachable")  # pragma: no cover


async def _audit_one(link: VehicleLink, rules: Sequence[ParamRule], fix: bool,
                     changed: dict[str, float]) -> tuple[dict[str, float], list[str], list[str]]:
    """(values, problems, warnings) of one vehicle; warnings without the vehicle's name
    (:func:`audit_fleet` says which vehicles share each)."""
    values: dict[str, float] = {}
    problems: list[str] = []
    warnings: list[str] = []
    for rule in rules:
        try:
            x = await _read_param(link, rule.name)
        except LinkUnsupported:
            raise
        except LinkError as exc:
            if rule.hard:
                problems.append(f"{link.name}: {rule.name} cannot be read ({exc}); not checked")
            else:
                warnings.append(f"{rule.name} cannot be read ({exc}); not checked")
            continue
        values[rule.name] = x
        why = rule.problem(x)
        if why is None:
            continue
        if fix:
            await link.set_param(rule.name, rule.fix)
            changed[rule.name] = x
            warnings.append(f"{why}; --fix-params set {rule.name} = "
                            f"{_n(rule.fix)} (restored to {_n(x)} on exit)")
        elif rule.hard:
            problems.append(f"{link.name}: {why}")
        else:
            warnings.append(why)
    return values, problems, warnings


async def audit_fleet(links: Sequence[VehicleLink], mission: Mission, *, fix: bool = False
                      ) -> AuditResult:
    """Read :func:`audit_rules` from every link (concurrently) and judge them; with ``fix``
    set what is off (the old values are in ``changed``, also when a later step fails)."""
    rules = audit_rules(mission)
    res = AuditResult(changed=[{} for _ in links])
    outs = await gather_bounded([_audit_one(link, rules, fix, res.changed[i])
                                 for i, link in enumerate(links)])
    shared: dict[str, list[str]] = {}  # one warning per fact, naming the vehicles it holds for
    for link, out in zip(links, outs, strict=True):
        if isinstance(out, asyncio.CancelledError):
            raise out
        if isinstance(out, LinkUnsupported):
            res.unsupported = True
            res.values.append({})
            continue
        if isinstance(out, BaseException):
            res.problems.append(f"{link.name}: parameter audit failed: {out}")
            res.values.append({})
            continue
        values, problems, warnings = out
        res.values.append(values)
        res.problems += problems
        for w in warnings:
            shared.setdefault(w, []).append(link.name)
    for w, names in shared.items():
        if len(names) == len(links) > 1:
            who = f"all {len(names)} vehicles"
        elif len(names) > PROBLEMS_SHOWN:  # each one's values: the summary's px4_params
            who = (f"{len(names)} of {len(links)} vehicles ("
                   + ", ".join(names[:PROBLEMS_SHOWN]) + ", …)")
        else:
            who = ", ".join(names)
        res.warnings.append(f"{who}: {w}")
    return res


async def restore_params(links: Sequence[VehicleLink], changed: Sequence[dict[str, float]]
                         ) -> list[str]:
    """Set every recorded old value back; returns one line per failure (never raises)."""

    async def one(link: VehicleLink, old: dict[str, float]) -> list[str]:
        fails = []
        for name, value in old.items():
            try:
                await link.set_param(name, value)
            except Exception as exc:  # noqa: BLE001 - restore as much as possible, report
                fails.append(f"{link.name}: cannot restore {name} = {_n(value)}: {exc}")
        return fails

    outs = await asyncio.gather(*(one(link, old) for link, old in zip(links, changed,
                                                                     strict=True) if old),
                                return_exceptions=True)
    lines: list[str] = []
    for out in outs:
        lines += [str(out)] if isinstance(out, BaseException) else out
    return lines
