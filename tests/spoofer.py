"""A naive MAVLink spoofer for the tests (issue 33): unsigned fake telemetry for vehicles, sent
with pymavlink from its own UDP socket into the controller's ports.

Per target (the controller's port of one vehicle, its system id, where to claim it is), every
period: a LOCAL_POSITION_NED and an ATTITUDE; once a second a HEARTBEAT that says armed, in
OFFBOARD (what PX4 says in the tube). ``time_boot_ms`` is the spoofer's own clock from 0 unless
the target gives one (an attacker who sniffs the vehicle's clock). It runs in a thread of its
own, as another process on the network would, at ``rate_hz`` (50 Hz: the attack of issue 33),
for ``duration_s`` (then it falls silent; :attr:`done` is set).

    with Spoofer([SpoofTarget(("127.0.0.1", 14541), 2, lambda t: (20.0, 0.5, -5.0, 3, 0, 0))]):
        ...
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mav

__all__ = ["SpoofTarget", "Spoofer"]

#: PX4 armed in OFFBOARD (captures: base_mode 0x91 | custom 0x80 … as PX4 sends it in flight)
_BASE_MODE_ARMED_OFFBOARD = 157
_CUSTOM_MODE_OFFBOARD = 393216


@dataclass
class SpoofTarget:
    """``port``: where the controller listens for this vehicle; ``ned(t)``: the claimed
    (north, east, down, vn, ve, vd) at ``t`` s after the spoofer started; ``time_boot_ms()``:
    the claimed time (None: the spoofer's own clock from 0)."""

    port: tuple[str, int]
    sysid: int
    ned: Callable[[float], tuple[float, float, float, float, float, float]]
    time_boot_ms: Callable[[], int] | None = None


class Spoofer:
    """Sends the fakes of ``targets`` from one UDP socket (its own address) until stopped."""

    def __init__(self, targets: list[SpoofTarget], rate_hz: float = 50.0,
                 duration_s: float = float("inf"),
                 source: tuple[str, int] = ("127.0.0.1", 0)) -> None:
        self.targets = targets
        self.period_s = 1.0 / rate_hz
        self.duration_s = duration_s
        self.done = threading.Event()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(source)
        self.address = self.sock.getsockname()
        self._mavs = [mav.MAVLink(None, srcSystem=t.sysid, srcComponent=1) for t in targets]
        self.sent = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="spoofer", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.sock.close()

    def __enter__(self) -> Spoofer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _send(self, target: SpoofTarget, m: mav.MAVLink, msg: object) -> None:
        try:
            self.sock.sendto(msg.pack(m), target.port)  # type: ignore[attr-defined]
            self.sent += 1
        except OSError:  # nobody listens (yet): as on a real network, sent anyway
            pass

    def _run(self) -> None:
        t0 = time.monotonic()
        next_hb = t0
        while not self._stop.is_set():
            now = time.monotonic()
            t = now - t0
            if t > self.duration_s:
                break
            hb = now >= next_hb
            if hb:
                next_hb += 1.0
            for target, m in zip(self.targets, self._mavs, strict=True):
                tb = (int(t * 1000) if target.time_boot_ms is None
                      else target.time_boot_ms()) & 0xFFFFFFFF
                n, e, d, vn, ve, vd = target.ned(t)
                if hb:
                    self._send(target, m, m.heartbeat_encode(
                        mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4,
                        _BASE_MODE_ARMED_OFFBOARD, _CUSTOM_MODE_OFFBOARD,
                        mav.MAV_STATE_ACTIVE, 3))
                self._send(target, m, m.local_position_ned_encode(tb, n, e, d, vn, ve, vd))
                self._send(target, m, m.attitude_encode(tb, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            self._stop.wait(self.period_s)
        self.done.set()

    @property
    def started(self) -> bool:
        return self._thread is not None
