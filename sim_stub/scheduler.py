"""One periodic tick for all mock vehicles of an event loop.

Per tick (default 100 Hz, absolute schedule so it does not drift):

1. the PX4 logic (:meth:`MockVehicle.control`) of half of the vehicles (each vehicle runs at
   50 Hz, alternating halves to spread the load),
2. one vectorized step of the estimator errors (:class:`~sim_stub.estimator.EstimatorErrors`) and
   of the dynamics for all vehicles (:class:`~sim_stub.dynamics.QuadState`): PX4's velocity loop
   drives the *estimated* velocity to the command, so the true vehicle follows ``u − e_v``; then
   the estimate (``p + e_p``, ``v + e_v``) is exported as Python lists for the message
   builders, every other row set (truth, attitude, GNSS, IMU, ...) on its first use in the tick,
3. every telemetry message that is due, from a timing wheel of (due time, vehicle, stream)
   entries: a stream at rate r is sent at ``t_start + k/r`` exactly (no drift), several times in
   one tick if the loop fell behind (bounded by ``max_lag_s``), never more often,
4. datagrams held back by a latency fault.

There is no task per vehicle or per stream; a process serving 200 vehicles runs one callback per
tick. The scheduler drives a vehicle only through its public interface: ``control(now)``,
``send_stream(stream, payload)`` and ``flush_delayed(now)``. It also watches the vehicles'
sockets (:meth:`Scheduler.add_reader`): one epoll for all of them, one event-loop reader, so a
burst of setpoints to many vehicles costs one loop wake-up, not one loop callback per datagram.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import select
import socket
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .dynamics import GRAVITY, DynamicsParams, QuadState
from .estimator import EstimatorErrors

if TYPE_CHECKING:  # pragma: no cover
    from .vehicle import MockVehicle, StreamState

__all__ = ["TICK_HZ_MAX", "TICK_HZ_MIN", "Scheduler"]

#: The scheduler ticks the mock supports (Hz): the dynamics step at the tick, the PX4 logic at
#: half of it, so 20 Hz keeps that at 10 Hz; above 1 kHz a tick is shorter than a wake-up.
TICK_HZ_MIN = 20.0
TICK_HZ_MAX = 1000.0

log = logging.getLogger("sim_stub")

_WHEEL_SIZE = 1024  # buckets; the wheel spans 10.24 s at 100 Hz (longer intervals lap)


class Scheduler:
    """Drives ``capacity`` vehicle slots with one ``loop.call_at`` chain."""

    def __init__(
        self,
        capacity: int,
        *,
        tick_hz: float = 100.0,
        clock: Callable[[], float] | None = None,
        dynamics: DynamicsParams | None = None,
        max_lag_s: float = 0.25,
        seed: int = 0,
        stream: int = 0,
    ) -> None:
        """``seed``/``stream``: the estimate errors' generator (stream 0 = seed alone; the
        processes of a :class:`~sim_stub.processes.ProcessFleet` use their first instance, so
        their vehicles' errors are independent; shared draws stay common to all)."""
        if capacity < 1:
            raise ValueError(f"scheduler capacity must be >= 1, got {capacity}")
        if not TICK_HZ_MIN <= tick_hz <= TICK_HZ_MAX:
            raise ValueError(f"tick_hz must be in [{TICK_HZ_MIN:g}, {TICK_HZ_MAX:g}], got "
                             f"{tick_hz}")
        self.capacity = capacity
        self.tick_hz = float(tick_hz)
        self.dt = 1.0 / self.tick_hz
        self._clock = clock
        self.max_lag_s = max_lag_s
        self.dyn = QuadState(capacity, dynamics, nominal_dt=self.dt)
        self.est = EstimatorErrors(capacity, seed, stream=stream)
        n = capacity
        self.u = np.zeros((n, 3))
        self.airborne = np.zeros(n, dtype=bool)
        self.frozen = np.zeros(n, dtype=bool)
        self.yaw_sp = np.full(n, np.nan)
        self.yaw_rate_sp = np.zeros(n)
        self.noise = np.zeros((n, 3))
        self.push = np.zeros((n, 3))  # fault: carried along at this NED velocity (m/s)
        self.xy_gain = np.ones(n)  # fault: the share of the horizontal command followed
        self._slow_on = False
        self.noise_sigma = np.zeros(n)
        self._noise_on = False  # noise_sigma.any(): a GPS noise fault somewhere
        self._noise_rng = np.random.default_rng(0)
        self.vehicles: list[MockVehicle | None] = [None] * n
        self._buckets: list[list[list]] = [[] for _ in range(_WHEEL_SIZE)]
        self._mask = _WHEEL_SIZE - 1
        self._t0 = 0.0
        self._k_done = -1
        self._ticks = 0
        self._last = 0.0
        self._handle: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.delayed: set[MockVehicle] = set()
        self.late_ticks = 0  # grid ticks missed (the loop was busy or the process starved)
        self.errors = 0  # exceptions caught in the tick (logged, the first 5 with traceback)
        self.skipped_msgs = 0  # messages dropped because the loop fell > max_lag_s behind
        self.reader_errors = 0  # exceptions caught in a socket reader (logged, the first 5)
        # the vehicles' sockets: one epoll, itself one reader of the event loop (add_reader)
        self._readers: dict[int, Callable[[], None]] = {}
        self._epoll: select.epoll | None = None
        self._epoll_loop: asyncio.AbstractEventLoop | None = None
        self._export()

    # --- time -----------------------------------------------------------------------------
    def now(self) -> float:
        if self._clock is not None:
            return self._clock()
        loop = self._loop or asyncio.get_running_loop()
        return loop.time()

    # --- vehicles -------------------------------------------------------------------------
    def attach(self, vehicle: MockVehicle) -> int:
        for slot, v in enumerate(self.vehicles):
            if v is None:
                self.vehicles[slot] = vehicle
                return slot
        raise ValueError(f"scheduler is full ({self.capacity} vehicles)")

    def detach(self, vehicle: MockVehicle) -> None:
        for slot, v in enumerate(self.vehicles):
            if v is vehicle:
                self.vehicles[slot] = None
                self.u[slot] = 0.0
                self.airborne[slot] = False
                self.frozen[slot] = False
                self.push[slot] = 0.0
                self.xy_gain[slot] = 1.0
                self.est.release(slot)

    def slow(self, slot: int, gain: float) -> None:
        """From now on the vehicle in ``slot`` follows ``gain`` of its horizontal command
        (:class:`~sim_stub.faults.Faults` ``slow_*``)."""
        self.xy_gain[slot] = gain
        self._slow_on = bool((self.xy_gain != 1.0).any())

    # --- sockets ---------------------------------------------------------------------------
    def add_reader(self, sock: socket.socket, on_readable: Callable[[], None]) -> None:
        """Call ``on_readable()`` whenever ``sock`` has data (in the running event loop).

        On Linux all sockets of the scheduler share one epoll, which is a single reader of the
        loop: a wake-up serves every socket that is ready, without a loop callback each (the
        loop's per-datagram cost of ``create_datagram_endpoint``); elsewhere plain
        ``loop.add_reader``."""
        loop = asyncio.get_running_loop()
        if not hasattr(select, "epoll"):  # pragma: no cover - not Linux
            loop.add_reader(sock.fileno(), on_readable)
            return
        if self._epoll is None or self._epoll_loop is not loop:
            self._close_epoll()
            self._epoll = select.epoll()
            self._epoll_loop = loop
            loop.add_reader(self._epoll.fileno(), self._poll_readers)
        self._epoll.register(sock.fileno(), select.EPOLLIN)
        self._readers[sock.fileno()] = on_readable

    def remove_reader(self, sock: socket.socket) -> None:
        """Undo :meth:`add_reader` (before the socket is closed)."""
        fd = sock.fileno()
        if self._epoll is None:
            if not hasattr(select, "epoll"):  # pragma: no cover - not Linux
                with contextlib.suppress(Exception):
                    asyncio.get_running_loop().remove_reader(fd)
            return
        if self._readers.pop(fd, None) is not None:
            with contextlib.suppress(OSError, ValueError):
                self._epoll.unregister(fd)
        if not self._readers:
            self._close_epoll()

    def _close_epoll(self) -> None:
        ep, loop = self._epoll, self._epoll_loop
        self._epoll = self._epoll_loop = None
        self._readers.clear()
        if ep is not None:
            if loop is not None and not loop.is_closed():
                with contextlib.suppress(Exception):
                    loop.remove_reader(ep.fileno())
            ep.close()

    def _poll_readers(self) -> None:
        ep = self._epoll
        if ep is None:
            return
        readers = self._readers
        for fd, _ in ep.poll(0):
            cb = readers.get(fd)
            if cb is None:
                continue
            try:
                cb()
            except Exception:  # one vehicle's bug must not starve the others' sockets
                self.reader_errors += 1
                if self.reader_errors <= 5:
                    log.exception("sim_stub socket reader failed (error %d)", self.reader_errors)

    def set_noise(self, slot: int, sigma_m: float, seed: int) -> None:
        self.noise_sigma[slot] = sigma_m
        self._noise_on = bool(self.noise_sigma.any())
        self._noise_rng = np.random.default_rng(seed)

    # --- streams --------------------------------------------------------------------------
    def schedule(self, vehicle: MockVehicle, st: StreamState, due: float) -> None:
        """(Re)schedule ``st`` of ``vehicle`` at absolute time ``due``; older entries die."""
        ent = [due, vehicle, st]
        st.entry = ent
        self._insert(ent)

    def _insert(self, ent: list) -> None:
        k = int((ent[0] - self._t0) * self.tick_hz)
        if k <= self._k_done:
            k = self._k_done + 1
        elif k - self._k_done >= _WHEEL_SIZE:
            k = self._k_done + _WHEEL_SIZE - 1
        self._buckets[k & self._mask].append(ent)

    # --- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        if self._handle is not None:
            return
        self._loop = asyncio.get_running_loop()
        now = self.now()
        self._t0 = now
        self._last = now
        self._k_done = int((now - self._t0) * self.tick_hz) - 1
        self._handle = self._loop.call_soon(self._tick)

    def stop(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    @property
    def running(self) -> bool:
        return self._handle is not None

    # --- the tick -------------------------------------------------------------------------
    def _export(self, push_on: bool | None = None) -> None:
        """Export the state of this tick as Python lists for the message builders: the estimate
        (``p_rows``, ``v_rows``: what PX4 reports and its position loops use) at once, every
        other row set (:data:`_LAZY_ROWS`) on its first use in the tick (a lite fleet whose GCS
        switched the attitude streams off never computes the quaternion or IMU rows)."""
        d = self.dyn
        e = self.est
        cache = self.__dict__
        for name in _LAZY_ROWS:
            cache.pop(name, None)
        if push_on is None:
            push_on = bool(self.push.any())
        self._v_pushed = v = d.v + self.push if push_on else d.v
        self.p_rows = (d.p + e.e_p + self.noise).tolist()
        self.v_rows = (v + e.e_v).tolist()

    def __getattr__(self, name: str) -> list:
        """A row set of :data:`_LAZY_ROWS`, computed on its first use after :meth:`_export`."""
        build = _LAZY_ROWS.get(name)
        if build is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        rows = build(self)
        self.__dict__[name] = rows
        return rows

    def _tick(self) -> None:
        """One tick; whatever happens, the next tick is scheduled (a failing vehicle is logged
        and skipped, it never stops the fleet's clock)."""
        try:
            self._tick_body()
        except Exception:  # pragma: no cover - defensive: a bug must not freeze every vehicle
            self.errors += 1
            if self.errors <= 5:
                log.exception("sim_stub scheduler tick failed (error %d)", self.errors)
        finally:
            loop = self._loop
            if self._handle is not None and loop is not None:
                nxt = self._t0 + (int((self.now() - self._t0) * self.tick_hz) + 1) * self.dt
                lt = loop.time()
                if self._clock is not None:  # custom clock: keep the loop's cadence
                    nxt = lt + max(0.0, nxt - self.now())
                self._handle = loop.call_at(nxt, self._tick)

    def _tick_body(self) -> None:
        now = self.now()
        dt = now - self._last
        if 0.0 < dt < 1e-3:
            # a catch-up tick within a millisecond of the last (the loop ran late): its state
            # would go out with the same time_boot_ms as the last one but another position,
            # which PX4 never does (one estimate per stamp) and the links refuse as a second
            # source; the next tick on the grid does the work
            return
        self._last = now
        self._ticks += 1
        for v in self.vehicles[self._ticks & 1::2]:
            if v is not None:
                try:
                    v.control(now)
                except Exception:
                    self._vehicle_error(v, "PX4 logic")
        # dynamics for everyone
        push_on = None
        if dt > 0.0:
            est = self.est
            frozen = self.frozen
            est.step(dt, self.airborne, frozen, bool(frozen.any()))
            u = self.u - est.e_v  # PX4 tracks the estimated velocity: the truth flies u − e_v
            if self._slow_on:  # Faults.slow_*: a vehicle that follows less than it is told
                u[:, :2] = self.u[:, :2] * self.xy_gain[:, None] - est.e_v[:, :2]
            self.dyn.step(dt, u, self.airborne, frozen, self.yaw_sp, self.yaw_rate_sp)
            push_on = bool(self.push.any())
            if push_on:
                pushed = self.push.any(axis=1) & self.airborne & ~frozen
                if pushed.any():  # a gust the vehicle cannot hold against (Faults.push_*)
                    self.dyn.p[pushed] += self.push[pushed] * dt
            if self._noise_on:
                self._step_noise(dt)
        self._export(push_on)
        # telemetry
        k_now = int((now - self._t0) * self.tick_hz)
        k_start = self._k_done + 1
        if k_now > k_start:
            self.late_ticks += k_now - k_start  # grid ticks that did not get their own call
        if k_now - k_start >= _WHEEL_SIZE:  # stalled for longer than the wheel: resync
            k_start = k_now - _WHEEL_SIZE + 1
        self._k_done = k_now  # re-inserted entries go to k_now + 1 or later
        buckets = self._buckets
        mask = self._mask
        max_lag = self.max_lag_s
        horizon = now + self.dt
        t0 = self._t0
        hz = self.tick_hz
        wheel = _WHEEL_SIZE
        for k in range(k_start, k_now + 1):
            bucket = buckets[k & mask]
            if not bucket:
                continue
            buckets[k & mask] = []
            for ent in bucket:
                due, veh, st = ent
                if st.entry is not ent:
                    continue
                if due > horizon:  # lapped entry (interval longer than the wheel)
                    self._insert(ent)
                    continue
                interval = st.interval
                try:
                    payload = st.build(now)
                    if payload is not None:
                        veh.send_stream(st, payload)
                    due += interval
                    while due <= now:
                        if now - due > max_lag:
                            self.skipped_msgs += int((now - due) / interval) + 1
                            due = now + interval
                            break
                        payload = st.build(now)
                        if payload is not None:
                            veh.send_stream(st, payload)
                        due += interval
                except Exception:
                    self._vehicle_error(veh, st.name)
                    due = now + interval
                ent[0] = due
                kk = int((due - t0) * hz)
                if kk <= k_now:
                    kk = k_now + 1
                elif kk - k_now >= wheel:
                    kk = k_now + wheel - 1
                buckets[kk & mask].append(ent)
        if self.delayed:
            for veh in list(self.delayed):
                try:
                    veh.flush_delayed(now)
                except Exception:
                    self.delayed.discard(veh)
                    self._vehicle_error(veh, "delayed datagrams")

    def _vehicle_error(self, vehicle: MockVehicle, what: str) -> None:
        self.errors += 1
        if self.errors <= 5:
            log.exception("sim_stub vehicle %d: %s failed (error %d)", vehicle.instance, what,
                          self.errors)  # fmt: skip

    def _step_noise(self, dt: float) -> None:
        tau = 2.0
        a = math.exp(-dt / tau)
        sigma = self.noise_sigma[:, None]
        w = self._noise_rng.standard_normal(self.noise.shape)
        self.noise = self.noise * a + sigma * math.sqrt(1.0 - a * a) * w


def _gnss_p_rows(s: Scheduler) -> list:  # the GNSS receiver (GPS_RAW_INT)
    return (s.dyn.p + s.est.e_gnss + s.noise).tolist()


def _att_rows(s: Scheduler) -> list:
    d = s.dyn
    return np.stack(
        (d.roll, d.pitch, d.yaw, d.roll_rate, d.pitch_rate, d.yaw_rate), axis=1
    ).tolist()


def _q_rows(s: Scheduler) -> list:
    """Attitude quaternion (ZYX Euler angles)."""
    d = s.dyn
    hr, hp, hy = 0.5 * d.roll, 0.5 * d.pitch, 0.5 * d.yaw
    cr, sr, cp, sp, cy, sy = (np.cos(hr), np.sin(hr), np.cos(hp), np.sin(hp), np.cos(hy),
                              np.sin(hy))  # fmt: skip
    return np.stack(
        (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ),
        axis=1,
    ).tolist()


def _imu_rows(s: Scheduler) -> list:
    """IMU in the body frame: specific force, magnetic field."""
    d = s.dyn
    f = d.acc.copy()
    f[:, 2] -= GRAVITY
    mag = np.broadcast_to(np.array([0.21, 0.0, 0.43]), f.shape)  # Zurich field [gauss]
    return np.concatenate(
        (_to_body(f, d.roll, d.pitch, d.yaw), _to_body(mag, d.roll, d.pitch, d.yaw)), axis=1
    ).tolist()


#: row sets the scheduler computes on first use per tick (name -> builder); true state,
#: GNSS receiver, accelerations, attitude, ground contact, quaternion, IMU
_LAZY_ROWS: dict[str, Callable[[Scheduler], list]] = {
    "p_true_rows": lambda s: s.dyn.p.tolist(),
    "v_true_rows": lambda s: s._v_pushed.tolist(),
    "gnss_p_rows": _gnss_p_rows,
    "gnss_v_rows": lambda s: (s._v_pushed + s.est.e_gnss_v).tolist(),
    "acc_rows": lambda s: s.dyn.acc.tolist(),
    "att_rows": _att_rows,
    "contact_rows": lambda s: s.dyn.contact.tolist(),
    "q_rows": _q_rows,
    "imu_rows": _imu_rows,
}


def _to_body(v: np.ndarray, roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate NED vectors (n, 3) into the body frame (ZYX Euler angles, each (n,))."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    x1 = cy * v[:, 0] + sy * v[:, 1]
    y1 = -sy * v[:, 0] + cy * v[:, 1]
    cp, sp = np.cos(pitch), np.sin(pitch)
    x2 = cp * x1 - sp * v[:, 2]
    z2 = sp * x1 + cp * v[:, 2]
    cr, sr = np.cos(roll), np.sin(roll)
    return np.stack((x2, cr * y1 + sr * z2, -sr * y1 + cr * z2), axis=1)
