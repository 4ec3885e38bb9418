"""The controller's parameters: ONE defaults table, ONE domain check (paper's symbols).

:class:`ControllerParams` is validated once, when it is built (by the scenario parser, the
safety budget's inflation, a test); nothing checks r_s & co. again after that.
:func:`parameter_problems` is the check itself, also used to report a scenario's
"Parameters" condition by name. Constraint1 (v ± v'_max within [v_min, v_max]) is a condition
of the paper, not of the domain: :mod:`vtube_fleet.core.validation` reports it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from vtube_fleet.core.text import compact_number as _num
from vtube_fleet.errors import UserError

__all__ = [
    "CONTROLLER_DEFAULTS",
    "CONTROLLER_REQUIRED",
    "ControllerParams",
    "ParameterError",
    "parameter_problems",
]

#: Defaults of the optional parameters: the paper's values (Section III-D, V-A), ε_0 = 0.01 m
#: (paper note 5) and the Appendix C potential-term gains k4, ε_o.
CONTROLLER_DEFAULTS: Mapping[str, float] = {
    "k2": 1.0,
    "k3": 1.0,
    "k_t": 1.5,
    "eps_m": 1e-6,
    "eps_t": 1e-6,
    "eps_s": 1e-6,
    "eps_0": 0.01,
    "k4": 1.0,
    "eps_o": 1e-6,
}
#: Parameters without a default (besides the robots' r_s, r_a, v_min, v_max).
CONTROLLER_REQUIRED: tuple[str, ...] = ("v", "v_max_prime")


class ParameterError(UserError):
    """A controller parameter is out of its domain (names the parameter and the value)."""


def parameter_problems(values: Mapping[str, Any]) -> list[str]:
    """Every way ``values`` (name → number) leave the parameters' domain, one message each
    naming the parameter and the value: finite numbers; r_a > r_s > 0; v_max > v_min ≥ 0;
    v, v'_max, k2, k3, k4, ε_0 > 0; k_t ≥ 1; ε_m, ε_t, ε_o in [1e-12, 1]; ε_s in
    [1e-12, 0.1]. Missing names are not checked."""
    out: list[str] = []
    v: dict[str, float] = {}
    for name, val in values.items():
        if isinstance(val, bool) or not isinstance(val, int | float):
            out.append(f"{name} must be a number, got {val!r}")
        elif not math.isfinite(val):
            out.append(f"{name} = {val} is not finite")
        else:
            v[name] = float(val)

    def has(*names: str) -> bool:
        return all(n in v for n in names)

    if has("r_s") and not v["r_s"] > 0:
        out.append(f"r_s = {_num(v['r_s'])} must be > 0")
    if has("r_s", "r_a") and not v["r_a"] > v["r_s"]:
        out.append(f"r_a = {_num(v['r_a'])} must be > r_s = {_num(v['r_s'])}")
    if has("v_min") and not v["v_min"] >= 0:
        out.append(f"v_min = {_num(v['v_min'])} must be ≥ 0")
    if has("v_min", "v_max") and not v["v_max"] > v["v_min"]:
        out.append(f"v_max = {_num(v['v_max'])} must be > v_min = {_num(v['v_min'])}")
    for name in ("v", "v_max_prime", "k2", "k3", "k4", "eps_0"):
        if has(name) and not v[name] > 0:
            out.append(f"{name} = {_num(v[name])} must be > 0")
    if has("k_t") and not v["k_t"] >= 1:
        out.append(f"k_t = {_num(v['k_t'])} must be ≥ 1")
    for name in ("eps_m", "eps_t", "eps_o"):
        if has(name) and not 1e-12 <= v[name] <= 1.0:
            out.append(f"{name} = {_num(v[name])} must be in [1e-12, 1]")
    if has("eps_s") and not 1e-12 <= v["eps_s"] <= 0.1:
        out.append(f"eps_s = {_num(v['eps_s'])} must be in [1e-12, 0.1]")
    return out


@dataclass(frozen=True)
class ControllerParams:
    """Parameters of (ModifiedVectorField) / (Oldcontroller) / Appendix C, paper's symbols.

    r_s, r_a: safety and avoidance radii (m) — the physical ones in a scenario, the flown r_s',
    r_a' in a fleet's flight plan (``SafetyBudget.inflate``); v_min, v_max: speed bounds; v:
    forward speed of u1''; v_max_prime: v'_max, the norm bound of the repulsive part; k2, k3,
    k4: barrier gains; k_t ≥ 1: width factor of the L/R areas; eps_m, eps_t, eps_o, eps_s:
    barrier ε's; eps_0: finishing tolerance (TraCondition). The domain is checked at
    construction (:func:`parameter_problems`, :class:`ParameterError`).
    """

    r_s: float
    r_a: float
    v_min: float
    v_max: float
    v: float
    v_max_prime: float
    k2: float = CONTROLLER_DEFAULTS["k2"]
    k3: float = CONTROLLER_DEFAULTS["k3"]
    k_t: float = CONTROLLER_DEFAULTS["k_t"]
    eps_m: float = CONTROLLER_DEFAULTS["eps_m"]
    eps_t: float = CONTROLLER_DEFAULTS["eps_t"]
    eps_s: float = CONTROLLER_DEFAULTS["eps_s"]
    eps_0: float = CONTROLLER_DEFAULTS["eps_0"]
    k4: float = CONTROLLER_DEFAULTS["k4"]
    eps_o: float = CONTROLLER_DEFAULTS["eps_o"]

    def __post_init__(self) -> None:
        values = asdict(self)
        problems = parameter_problems(values)
        if problems:
            raise ParameterError("controller parameters: " + "; ".join(problems))
        for name, val in values.items():
            object.__setattr__(self, name, float(val))
