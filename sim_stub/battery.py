"""The mock vehicle's battery: PX4 SITL's simulated battery, per-vehicle drain, a low-battery fault.

By default the charge follows PX4 SITL's battery simulator (PX4 source,
``src/modules/simulation/battery_simulator``; capture 1a, ``offboard_flight_i0``): while the
vehicle is armed it falls by 100 % every ``SIM_BAT_DRAIN`` = 60 s (the capture: 100 → 57 % in
27 s armed, 1.6 %/s), never below ``SIM_BAT_MIN_PCT`` = 50 %; disarmed, the battery is full
again (the capture: back to 96 % within 2 s of disarming, through PX4's filter). The voltage
goes linearly from PX4's empty to its charged cell voltage (``BAT1_V_EMPTY`` 3.6 V,
``BAT1_V_CHARGED`` 4.05 V) times ``BAT1_N_CELLS`` = 4 (the capture's 16.2 V when full).

Per vehicle (:class:`~sim_stub.faults.Faults`): ``battery_pct`` is the charge of the full
battery (what it starts with and returns to when disarmed: a half-charged pack is
``battery_pct=50``), ``drain_pct_per_min`` the drain while armed, ``battery_floor_pct`` the
level the drain stops at; the ``battery_low`` fault sets the charge (and the full battery) to
``battery_low_pct`` at ``battery_low_at_s`` after the vehicle's start, and it stays there: a
depleted or failing pack. :meth:`Battery.drop_to` does the same on demand. The charge is
integrated lazily, when a message reports it (SYS_STATUS at 5 Hz), so a thousand idle vehicles
cost nothing. Not modelled: PX4's own low-battery failsafe (``COM_LOW_BAT_ACT``), current and
consumed capacity (PX4 SITL reports none either).
"""

from __future__ import annotations

import math

from .faults import Faults

__all__ = ["Battery", "CELLS", "V_CHARGED", "V_EMPTY"]

#: PX4's defaults: BAT1_N_CELLS, BAT1_V_CHARGED, BAT1_V_EMPTY (V per cell).
CELLS = 4
V_CHARGED = 4.05
V_EMPTY = 3.6
#: MAV_BATTERY_CHARGE_STATE by remaining charge: OK, LOW below PX4's BAT_LOW_THR (15 %),
#: CRITICAL below BAT_CRIT_THR (7 %), EMERGENCY below BAT_EMERGEN_THR (5 %).
_CHARGE_STATES = ((15.0, 1), (7.0, 2), (5.0, 3))


class Battery:
    """One vehicle's battery (module docstring); ``faults`` configures it."""

    __slots__ = ("faults", "full_pct", "level_pct", "_t", "_low_done")

    def __init__(self, faults: Faults) -> None:
        self.faults = faults
        self.full_pct = float(faults.battery_pct)
        self.level_pct = self.full_pct
        self._t: float | None = None
        self._low_done = faults.battery_low_pct is None

    def update(self, now: float, uptime_s: float, armed: bool) -> float:
        """The charge (%) at ``now`` (``uptime_s`` after the vehicle's start), integrated since
        the last call with the vehicle ``armed`` or not."""
        f = self.faults
        if not self._low_done and uptime_s >= f.battery_low_at_s:
            self._low_done = True
            self.drop_to(float(f.battery_low_pct))  # type: ignore[arg-type]
        dt = 0.0 if self._t is None else max(0.0, now - self._t)
        self._t = now
        if not armed:
            self.level_pct = self.full_pct  # PX4 SITL: full again whenever disarmed
        elif self.level_pct > f.battery_floor_pct:
            self.level_pct = max(f.battery_floor_pct,
                                 self.level_pct - f.drain_pct_per_min * dt / 60.0)
        return self.level_pct

    def drop_to(self, pct: float) -> None:
        """From now on the battery holds at most ``pct`` % (also after disarming)."""
        if not 0.0 <= pct <= 100.0 or math.isnan(pct):
            raise ValueError(f"battery level must be in [0, 100] %, got {pct}")
        self.full_pct = min(self.full_pct, pct)
        self.level_pct = min(self.level_pct, pct)

    @property
    def remaining_pct(self) -> int:
        """The charge as MAVLink's ``battery_remaining`` (whole percent, 0..100)."""
        return max(0, min(100, int(round(self.level_pct))))

    @property
    def voltage_mv(self) -> int:
        """Pack voltage (mV): linear between PX4's empty and charged cell voltages."""
        frac = max(0.0, min(1.0, self.level_pct / 100.0))
        return int(round(1000.0 * CELLS * (V_EMPTY + frac * (V_CHARGED - V_EMPTY))))

    @property
    def charge_state(self) -> int:
        """MAV_BATTERY_CHARGE_STATE (1 OK, 2 LOW, 3 CRITICAL, 4 EMERGENCY)."""
        state = 1
        for below, code in _CHARGE_STATES:
            if self.level_pct < below:
                state = code + 1
        return state
