"""Per-vehicle fault injection for the mock (link and vehicle faults), and its battery.

All faults are off by default; the battery is PX4 SITL's simulated one (:mod:`sim_stub.battery`).
Randomness (packet loss, GPS noise) comes from a per-vehicle
``random.Random``/``numpy`` generator seeded from the fleet seed, so a run is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import SimStubError

__all__ = ["Faults", "parse_fault_spec"]

DIE_HOWS = ("silent", "freeze")
#: ``Faults.mode_fault``: what the vehicle does with a DO_SET_MODE to any mode but OFFBOARD
MODE_FAULTS = ("", "drop", "deny")


@dataclass(frozen=True)
class Faults:
    """Faults of one vehicle.

    ``loss_pct``: each datagram, in both directions, is dropped with this probability (percent);
    PX4's sequence numbers still advance, as on a real lossy link.
    ``latency_s``: extra one-way delay added to every datagram in both directions (round trip
    grows by twice this); granularity is the scheduler tick (10 ms).
    ``gps_noise_m``: standard deviation of a Gauss-Markov position error (time constant 2 s) added
    consistently to LOCAL_POSITION_NED, ODOMETRY, GLOBAL_POSITION_INT and GPS_RAW_INT.
    ``die_at_s``: seconds after the vehicle's start at which it dies. ``die_how="silent"``: the link
    goes dead (nothing sent, everything received is dropped) while the autopilot keeps running its
    own logic (so in offboard it fails safe and lands). ``die_how="freeze"``: the vehicle keeps
    streaming telemetry but stops reacting: it holds its current position (hovering if airborne),
    ignores commands and setpoints (no COMMAND_ACK) and its state no longer changes.
    ``push_north_m_s``/``push_east_m_s`` from ``push_at_s`` for ``push_for_s`` seconds (after
    the vehicle's start): the vehicle is carried along at that velocity whatever it is told (a
    gust its controller cannot hold against); its estimate moves with it, so nothing on the link
    says why. :meth:`MockVehicle.push` does the same on demand.
    ``mode_fault``: a DO_SET_MODE to any mode but OFFBOARD (Hold, Position …) is ``"drop"``-ped
    (no COMMAND_ACK: the link retries, then gives up) or ``"deny"``-ed (COMMAND_ACK DENIED);
    NAV_LAND and everything else still work (the vehicle that would not hold, seen on real PX4
    SITL when its acks were lost).
    ``slow_gain`` from ``slow_at_s`` (after the vehicle's start) on: the vehicle follows only
    that share of every horizontal velocity it is commanded, whatever mode commands it (a heavy
    payload, a weak motor: PX4's response slower than it was when the mission started).

    The battery (:mod:`sim_stub.battery`; defaults: PX4 SITL's): ``battery_pct`` the charge of
    the full pack (at start, and again whenever disarmed), ``drain_pct_per_min`` the drain while
    armed, ``battery_floor_pct`` where the drain stops. The ``battery_low`` fault:
    ``battery_low_pct`` is the charge from ``battery_low_at_s`` after the vehicle's start on
    (and it stays there, also after disarming); :meth:`MockVehicle.set_battery` on demand.
    """

    loss_pct: float = 0.0
    latency_s: float = 0.0
    gps_noise_m: float = 0.0
    die_at_s: float | None = None
    die_how: str = "silent"
    push_north_m_s: float = 0.0
    push_east_m_s: float = 0.0
    push_at_s: float | None = None
    push_for_s: float = 1.0
    mode_fault: str = ""
    slow_gain: float = 1.0
    slow_at_s: float | None = None
    battery_pct: float = 100.0
    drain_pct_per_min: float = 100.0  # PX4 SITL: SIM_BAT_DRAIN = 60 s for 100 %
    battery_floor_pct: float = 50.0  # PX4 SITL: SIM_BAT_MIN_PCT
    battery_low_pct: float | None = None
    battery_low_at_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss_pct <= 100.0:
            raise SimStubError(f"fault loss_pct must be in [0, 100] %, got {self.loss_pct}")
        if not 0.0 <= self.latency_s <= 10.0:
            raise SimStubError(f"fault latency_s must be in [0, 10] s, got {self.latency_s}")
        if self.gps_noise_m < 0.0:
            raise SimStubError(f"fault gps_noise_m must be >= 0 m, got {self.gps_noise_m}")
        if self.die_at_s is not None and self.die_at_s < 0.0:
            raise SimStubError(f"fault die_at_s must be >= 0 s, got {self.die_at_s}")
        if self.mode_fault not in MODE_FAULTS:
            raise SimStubError(f"fault mode_fault must be one of {MODE_FAULTS[1:]}, got "
                               f"{self.mode_fault!r}")
        if self.die_how not in DIE_HOWS:
            raise SimStubError(f"fault die_how must be one of {DIE_HOWS}, got {self.die_how!r}")
        for name in ("push_north_m_s", "push_east_m_s"):
            v = getattr(self, name)
            if not -20.0 <= v <= 20.0:
                raise SimStubError(f"fault {name} must be in [-20, 20] m/s, got {v}")
        if self.push_at_s is not None and not self.push_at_s >= 0.0:
            raise SimStubError(f"fault push_at_s must be >= 0 s, got {self.push_at_s}")
        if not 0.0 < self.push_for_s <= 3600.0:
            raise SimStubError(f"fault push_for_s must be in (0, 3600] s, got {self.push_for_s}")
        if not 0.0 < self.slow_gain <= 1.0:
            raise SimStubError(f"fault slow_gain must be in (0, 1], got {self.slow_gain}")
        if self.slow_at_s is not None and not self.slow_at_s >= 0.0:
            raise SimStubError(f"fault slow_at_s must be >= 0 s, got {self.slow_at_s}")
        for name in ("battery_pct", "battery_floor_pct"):
            v = getattr(self, name)
            if not 0.0 <= v <= 100.0:
                raise SimStubError(f"fault {name} must be in [0, 100] %, got {v}")
        if self.battery_low_pct is not None and not 0.0 <= self.battery_low_pct <= 100.0:
            raise SimStubError(f"fault battery_low_pct must be in [0, 100] %, got "
                               f"{self.battery_low_pct}")
        if not 0.0 <= self.drain_pct_per_min <= 1000.0:
            raise SimStubError(f"fault drain_pct_per_min must be in [0, 1000] %/min, got "
                               f"{self.drain_pct_per_min}")
        if not self.battery_low_at_s >= 0.0:
            raise SimStubError(f"fault battery_low_at_s must be >= 0 s, got "
                               f"{self.battery_low_at_s}")

    @property
    def affects_link(self) -> bool:
        """True if datagrams must go through the lossy/delayed path."""
        return self.loss_pct > 0.0 or self.latency_s > 0.0


_KEYS = {
    "loss": ("loss_pct", float),
    "loss_pct": ("loss_pct", float),
    "latency": ("latency_s", float),
    "latency_s": ("latency_s", float),
    "gps_noise": ("gps_noise_m", float),
    "gps_noise_m": ("gps_noise_m", float),
    "die_at": ("die_at_s", float),
    "die_at_s": ("die_at_s", float),
    "die_how": ("die_how", str),
    "push_north": ("push_north_m_s", float),
    "push_east": ("push_east_m_s", float),
    "push_at": ("push_at_s", float),
    "push_for": ("push_for_s", float),
    "mode_fault": ("mode_fault", str),
    "slow": ("slow_gain", float),
    "slow_at": ("slow_at_s", float),
    "battery": ("battery_pct", float),
    "drain": ("drain_pct_per_min", float),
    "battery_floor": ("battery_floor_pct", float),
    "battery_low": ("battery_low_pct", float),
    "battery_low_at": ("battery_low_at_s", float),
}
#: the keys a fault spec's error lists (the long field names are accepted too)
_SHOWN = sorted(k for k, (name, _) in _KEYS.items() if k != name or k in ("die_how", "mode_fault"))


def parse_fault_spec(spec: str) -> tuple[int | None, Faults]:
    """Parse a CLI fault spec ``[I:]key=value,...`` into ``(vehicle index or None, Faults)``.

    Example: ``"2:loss=5,latency=0.05,die_at=30,die_how=freeze"``; without ``I:`` it applies to
    every vehicle. Keys: loss (percent), latency (s), gps_noise (m), die_at (s), die_how,
    push_north / push_east (m/s), push_at (s), push_for (s), mode_fault (drop / deny),
    slow (the share of the commanded velocity followed) and slow_at (s), battery (% of the
    full pack), drain (%/min while armed), battery_floor (%), battery_low (%) and
    battery_low_at (s).
    """
    index: int | None = None
    body = spec.strip()
    head, sep, rest = body.partition(":")
    if sep and "=" not in head:
        try:
            index = int(head)
        except ValueError:
            raise SimStubError(
                f"fault spec {spec!r}: vehicle index {head!r} is not an integer"
            ) from None
        if index < 0:
            raise SimStubError(f"fault spec {spec!r}: vehicle index must be >= 0, got {index}")
        body = rest
    kwargs: dict[str, object] = {}
    for item in filter(None, (p.strip() for p in body.split(","))):
        key, eq, value = item.partition("=")
        if not eq or key.strip() not in _KEYS:
            raise SimStubError(
                f"fault spec {spec!r}: expected key=value with key in {_SHOWN}, got {item!r}"
            )
        field, conv = _KEYS[key.strip()]
        try:
            kwargs[field] = conv(value.strip())
        except ValueError:
            raise SimStubError(f"fault spec {spec!r}: {key}={value!r} is not a number") from None
    return index, Faults(**kwargs)  # type: ignore[arg-type]
