"""``mavlink`` backend: pymavlink's MAVLink 2 codec on an asyncio UDP socket, one per vehicle.

* One UDP socket per endpoint (:class:`~vtube_fleet.link.udp.DatagramSocket`; the loop's
  sockets share one ``epoll``, read in rounds of one datagram per ready socket).
  ``udpin://HOST:PORT`` binds locally and learns the vehicle's address from its first valid
  packet (PX4 SITL's API link sends from 14580+i to 14540+i); ``udpout://HOST:PORT`` sends to
  the vehicle from an ephemeral port.
* Decoding: a pymavlink ``MAVLink`` object (``robust_parsing``) fed one datagram at a time with
  ``parse_buffer``; leftovers of a datagram are discarded (a datagram never continues in the next
  one). Cheap path for 200 vehicles in one process: once the vehicle is known, a datagram that is
  exactly one MAVLink 2 packet from it whose message id we do not use (ATTITUDE at 100 Hz,
  HIGHRES_IMU …) is only counted, never decoded; used ids dispatch through a dict to handlers
  that update :class:`~vtube_fleet.link.base.VehicleState` in place and wake waiters only when
  someone waits. Garbage, bad CRCs and cut-off packets are counted (``bad_packets``) with a
  rate-limited warning; other systems' packets and other GCSs' heartbeats are counted
  (``foreign_packets``) and ignored; message ids the dialect lacks (PX4's 8, 380, 410, 411, 436)
  are fine.
* Identity and source (issue 33, docs/links.md): the link flies one system id (given, or the
  first autopilot heard) and refuses every other (``telemetry_refused["other_sysid"]``); a
  ``udpin`` link learns the vehicle's address from its autopilot's first packet and refuses its
  id from any other address (``other_source``), re-learning only from 3 HEARTBEATs of one new
  address while the learned one has been silent for 3 s (logged). Other vehicles heard, and
  the id's HEARTBEAT from a second address, make :meth:`MavlinkLink.identity_problem`: a
  :class:`~vtube_fleet.link.base.LinkConflict` from ``wait_ready`` and ``arm``.
* Plausibility (:mod:`vtube_fleet.link.guard`, ``telemetry=``): LOCAL_POSITION_NED (also on
  its fast path) and GLOBAL_POSITION_INT that the vehicle cannot have flown are refused and
  counted; persistent refusals set ``state.telemetry_fault``.
* GCS identity sysid 255 / compid 190, HEARTBEAT (type GCS, autopilot INVALID) every second,
  as the capture GCS did. On connect: SET_MESSAGE_INTERVAL for LOCAL_POSITION_NED (50 Hz),
  GLOBAL_POSITION_INT (10 Hz), EXTENDED_SYS_STATE (5 Hz), HOME_POSITION (1 Hz) and
  REQUEST_MESSAGE for HOME_POSITION and GPS_GLOBAL_ORIGIN (re-requested every second while
  :meth:`~vtube_fleet.link.base.VehicleLink.wait_ready` still misses them).
* Commands: COMMAND_LONG, ``command_tries`` tries (default 3) of ``command_timeout_s`` (0.5 s)
  each, ``confirmation`` incremented per try; one command per id in flight (PX4 ACKs carry only
  the command id). IN_PROGRESS extends the wait. Non-ACCEPTED → :class:`CommandRejected`.
* Setpoints: :meth:`MavlinkLink.send_velocity_ned` sends one SET_POSITION_TARGET_LOCAL_NED
  (frame LOCAL_NED, type_mask 3527 = velocity only, or 2503 = velocity + yaw) immediately and
  nothing else ever does: if our control loop stalls, the stream stops and PX4's offboard-loss
  failsafe fires after COM_OF_LOSS_T (1.0 s default; captures: "Failsafe activated" 1.07 s
  after the last setpoint, then POSCTL and descent). The link only logs a warning then.
* Latency: half the smoothed round trip of TIMESYNC requests (1 Hz; PX4 answers them) or, until
  one is answered, of first-try COMMAND_ACKs (those include PX4's ~10 ms command handling).
* Onboard safety (installed on first use, ``_onboard``): PX4 parameters by name
  (PARAM_REQUEST_READ / PARAM_SET → PARAM_VALUE, integers bytewise in the float as PX4 sends
  them) and the fence (mission protocol with ``mission_type`` FENCE: upload, download).
* MAVLink 2 signing (``signing=``, :mod:`vtube_fleet.link.signing`): every packet we send is
  signed (timestamps from the persistent :class:`~vtube_fleet.link.signing.TimestampStore`);
  a received packet counts only if its signature verifies with the key and its timestamp is
  newer than the last of its stream (checked in that order, so a forged packet cannot poison
  the replay window), apart from RADIO_STATUS, ADSB_VEHICLE and COLLISION (not HEARTBEAT: it
  drives our armed/mode view). Refusals are counted by reason (``signing_refused``), never
  decoded further; the skip-undecoded cheap path is off (every packet is verified).
  :meth:`MavlinkLink.provision_signing` sends SETUP_SIGNING (``vtube-fleet sign-setup``).
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import math
import struct
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from vtube_fleet.link import px4
from vtube_fleet.link.base import (
    CommandRejected,
    FenceItem,
    FenceRejected,
    GeoPoint,
    LinkError,
    LinkTimeout,
    StatusText,
    VehicleLink,
    cancel_tasks,
)
from vtube_fleet.link.endpoints import Endpoint, shared_port_cause
from vtube_fleet.link.guard import DEFAULT_BOUNDS, TelemetryBounds, TelemetryGuard
from vtube_fleet.link.signing import LINK_UNSIGNED_ALLOWED, LinkSigning, SigningError
from vtube_fleet.link.udp import DatagramSocket
from vtube_fleet.link.wire import WireCodec, mcrf4xx

__all__ = [
    "MavlinkLink",
    "DEFAULT_MESSAGE_RATES_HZ",
    "UNUSED_STREAMS_OFF",
    "TYPE_MASK_VELOCITY",
    "TYPE_MASK_VELOCITY_YAW",
    "command_name",
]

log = logging.getLogger(__name__)

#: SET_POSITION_TARGET_LOCAL_NED type_mask: ignore position, acceleration, yaw, yaw rate.
TYPE_MASK_VELOCITY = 3527
#: Same but with yaw used (bit 10 cleared).
TYPE_MASK_VELOCITY_YAW = TYPE_MASK_VELOCITY & ~1024

MSG_HEARTBEAT = 0
MSG_SYS_STATUS = 1
MSG_LOCAL_POSITION_NED = 32
MSG_GLOBAL_POSITION_INT = 33
MSG_GPS_RAW_INT = 24
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_COMMAND_ACK = 77
MSG_TIMESYNC = 111
MSG_HIL_STATE_QUATERNION = 115
MSG_ESTIMATOR_STATUS = 230
MSG_HOME_POSITION = 242
MSG_EXTENDED_SYS_STATE = 245
MSG_STATUSTEXT = 253
MSG_SET_POSITION_TARGET_LOCAL_NED = 84

#: received through the struct fast path (vtube_fleet/link/wire.py) when unsigned: the position
#: streams and every status message the link reads more than once a second or so (at 1,000
#: vehicles the four status messages were 12 of 40 datagrams per vehicle and second, and half
#: of the receive time through pymavlink), and the TIMESYNC answers (one per vehicle and second)
_FAST_RX = frozenset((MSG_HEARTBEAT, MSG_LOCAL_POSITION_NED, MSG_GLOBAL_POSITION_INT,
                      MSG_SYS_STATUS, MSG_EXTENDED_SYS_STATE, MSG_GPS_RAW_INT,
                      MSG_ESTIMATOR_STATUS, MSG_TIMESYNC))
#: sent through the struct fast path when unsigned: the setpoints, and the GCS heartbeat and
#: TIMESYNC every vehicle gets once a second (1,000 vehicles: 2,000 pymavlink packs a second)
_FAST_TX = (MSG_SET_POSITION_TARGET_LOCAL_NED, MSG_HEARTBEAT, MSG_TIMESYNC)
_WIRE = WireCodec((*_FAST_RX, *_FAST_TX))
#: LOCAL_POSITION_NED, the stream of the control loop, on a path of its own (feed_datagram):
#: the frame's first four bytes (magic, payload length 28, no flags), its length, the payload
#: struct and the CRC extra
_LPN_HEAD = bytes((0xFD, 28, 0, 0))
_LPN_FRAME_LEN = 12 + 28
_LPN = struct.Struct("<Iffffff")
_LPN_EXTRA = bytes((mavlink2.MAVLink_local_position_ned_message.crc_extra,))
_CRC16 = struct.Struct("<H")

CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_COMPONENT_ARM_DISARM = 400
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512

#: Message id → rate requested on connect (as the capture GCS did). 0 disables a stream.
DEFAULT_MESSAGE_RATES_HZ: Mapping[int, float] = {
    MSG_LOCAL_POSITION_NED: 50.0,
    MSG_GLOBAL_POSITION_INT: 10.0,
    MSG_EXTENDED_SYS_STATE: 5.0,
    MSG_HOME_POSITION: 1.0,
    MSG_ESTIMATOR_STATUS: 2.0,  # the position accuracy of the safety budget
}

#: The streams the fleet does not use, switched off on connect (SET_MESSAGE_INTERVAL −1 via
#: rate 0) to save link bandwidth and CPU on both ends: ATTITUDE (100 Hz in the captures),
#: ATTITUDE_QUATERNION, HIGHRES_IMU, ODOMETRY, POSITION_TARGET_LOCAL_NED (10 Hz). A fleet's
#: links (``open_links``) switch them off unless told otherwise; every stream a link changed is
#: given back to PX4's own rate when it closes (:meth:`MavlinkLink.restore_streams`).
UNUSED_STREAMS_OFF: Mapping[int, float] = {30: 0.0, 31: 0.0, 105: 0.0, 331: 0.0, 85: 0.0}

_RESULT_ACCEPTED = 0
_RESULT_TEMPORARILY_REJECTED = 1
_RESULT_IN_PROGRESS = 5
_MAV_COMP_ID_AUTOPILOT1 = 1
_MAV_AUTOPILOT_INVALID = 8  # a GCS's HEARTBEAT
_MAV_TYPE_GCS = 6
#: system ids of ground stations by convention (MAVSDK 245, QGroundControl and us 255)
_GCS_IDS_FROM = 245
_WARN_INTERVAL_S = 5.0
_HEARTBEAT_LOST_S = 3.0
#: the vehicle's address is re-learned only from this many HEARTBEATs of its id from one new
#: address, all while the learned address has been silent for RELEARN_SILENCE_S or longer
RELEARN_HEARTBEATS = 3
RELEARN_SILENCE_S = 3.0
#: addresses kept per other vehicle / other source for the conflict report (a flood of forged
#: addresses must not grow the link)
_HEARD_MAX = 8
_RTT_ALPHA = 0.2


def command_name(command: int) -> str:
    """``COMPONENT_ARM_DISARM`` for 400 (MAV_CMD name without prefix)."""
    entry = mavlink2.enums["MAV_CMD"].get(command)
    return entry.name.removeprefix("MAV_CMD_") if entry is not None else f"MAV_CMD({command})"


def _message_name(msgid: int) -> str:
    cls = mavlink2.mavlink_map.get(msgid)
    return cls.msgname if cls is not None else f"MSG({msgid})"


class MavlinkLink(VehicleLink):
    """One PX4 vehicle over pymavlink + asyncio UDP. See the module docstring.

    ``sysid``: the vehicle's system id, or None to lock onto the first autopilot (compid 1)
    that sends a valid packet. ``message_rates_hz`` overrides/extends
    :data:`DEFAULT_MESSAGE_RATES_HZ` (0 disables a stream, e.g. ``{30: 0}`` for ATTITUDE).
    ``decode_all`` disables the skip-undecoded cheap path (tests, debugging); ``fast_codec``
    False sends and decodes everything through pymavlink (the struct fast path of
    :mod:`vtube_fleet.link.wire` is byte-identical; tests compare both).
    """

    def __init__(
        self,
        endpoint: str | Endpoint,
        sysid: int | None = None,
        *,
        gcs_sysid: int = 255,
        gcs_compid: int = 190,
        target_compid: int = _MAV_COMP_ID_AUTOPILOT1,
        message_rates_hz: Mapping[int, float] | None = None,
        command_tries: int = 3,
        command_timeout_s: float = 0.5,
        heartbeat_period_s: float = 1.0,
        decode_all: bool = False,
        fast_codec: bool = True,
        signing: LinkSigning | None = None,
        telemetry: TelemetryBounds | None = DEFAULT_BOUNDS,
        pin_source: bool = True,
    ) -> None:
        super().__init__(endpoint, sysid)
        if command_tries < 1 or not command_timeout_s > 0:
            raise LinkError(
                f"{self.name}: command_tries must be >= 1 and command_timeout_s > 0, got "
                f"{command_tries} and {command_timeout_s}"
            )
        self._gcs_ids = (gcs_sysid, gcs_compid, target_compid)  # fixed: _tx_slot keeps them
        rates = dict(DEFAULT_MESSAGE_RATES_HZ)
        rates.update(message_rates_hz or {})
        self.message_rates_hz = rates
        #: the streams whose rate this link set (restored at :meth:`close`)
        self.streams_changed: set[int] = set()
        #: the streams :meth:`restore_streams` could not give back (their names:
        #: :attr:`unrestored_names`); ``warn_unrestored`` False: the owner of many links says
        #: it once for all (the supervisor)
        self.unrestored_streams: list[int] = []
        self.warn_unrestored = True
        self.command_tries = command_tries
        self.command_timeout_s = command_timeout_s
        self.heartbeat_period_s = heartbeat_period_s
        self.decode_all = decode_all
        self._fast_codec = fast_codec
        #: what a batch of setpoints needs of this link (_tx_slot): None = not worked out yet,
        #: False = the batch path does not apply; cleared wherever any of it changes
        self._tx: tuple[Any, ...] | bool | None = None

        mav = mavlink2.MAVLink(None, srcSystem=gcs_sysid, srcComponent=gcs_compid)
        mav.robust_parsing = True
        self._mav = mav
        self._sysid: int | None = self.state.sysid  # (the endpoint's ?sysid= included)
        #: the plausibility checks (link/guard.py); None: off (a test switch)
        self._guard: TelemetryGuard | None = (
            None if telemetry is None else TelemetryGuard(self, self.state, telemetry))
        #: refuse the vehicle's id from any address but the learned one (False: a test switch
        #: that accepts every address and keeps the learned one for sending)
        self.pin_source = bool(pin_source)
        #: other vehicles heard on this port (_admit): sysid -> addresses
        self._vehicles_heard: dict[int, set[Any]] = {}
        #: other addresses that sent this vehicle's HEARTBEAT while the learned one was alive
        self._sources_heard: set[Any] = set()
        #: a re-learning candidate: [address, first HEARTBEAT's time, HEARTBEATs]
        self._relearn: list[Any] | None = None
        self._remote: Any = None if self.endpoint.listens else (
            self.endpoint.host, self.endpoint.port
        )
        self._transport: DatagramSocket | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._connect_lock = asyncio.Lock()
        self._streams_requested = False
        self._pending: dict[int, asyncio.Future[int]] = {}
        self._cmd_locks: dict[int, asyncio.Lock] = {}
        self._handlers: dict[int, Callable[[Any, float], None]] = {
            MSG_HEARTBEAT: self._on_heartbeat,
            MSG_SYS_STATUS: self._on_sys_status,
            MSG_LOCAL_POSITION_NED: self._on_local_position,
            MSG_GLOBAL_POSITION_INT: self._on_global_position,
            MSG_GPS_GLOBAL_ORIGIN: self._on_origin,
            MSG_COMMAND_ACK: self._on_command_ack,
            MSG_TIMESYNC: self._on_timesync,
            MSG_HOME_POSITION: self._on_home,
            MSG_EXTENDED_SYS_STATE: self._on_extended_sys_state,
            MSG_STATUSTEXT: self._on_statustext,
            MSG_ESTIMATOR_STATUS: self._on_estimator_status,
            MSG_GPS_RAW_INT: self._on_gps_raw,
            MSG_HIL_STATE_QUATERNION: self._on_truth,
        }
        self._t0 = time.monotonic()
        self._warned_at: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._text_chunks: dict[int, list[str]] = {}
        self._text_severity: dict[int, int] = {}
        self._text_started: dict[int, float] = {}
        self._rtt_s: float | None = None
        self._rtt_source: str | None = None
        self._timesync_ts1: int | None = None
        self._timesync_waiters: dict[int, asyncio.Future[float]] = {}
        self._stall_warned = False
        self._hb_lost_warned = False
        self.tx_packets = 0
        #: packets refused by signing, by reason: unsigned, bad_signature, stale
        self.signing_refused: Counter[str] = Counter()
        self.signing: LinkSigning | None = None
        if signing is not None:
            self._install_signing(signing)

    # -- properties ----------------------------------------------------------------------------
    @property
    def gcs_sysid(self) -> int:
        """Our system id (the GCS's), fixed at construction."""
        return self._gcs_ids[0]

    @property
    def gcs_compid(self) -> int:
        """Our component id, fixed at construction."""
        return self._gcs_ids[1]

    @property
    def target_compid(self) -> int:
        """The vehicle's component our commands and setpoints address, fixed at construction."""
        return self._gcs_ids[2]

    @property
    def fast_codec(self) -> bool:
        """The struct fast path (:mod:`vtube_fleet.link.wire`) is on; False: pymavlink only."""
        return self._fast_codec

    @fast_codec.setter
    def fast_codec(self, value: bool) -> None:
        self._fast_codec = bool(value)
        self._tx = None

    @property
    def latency_s(self) -> float | None:
        """Half the smoothed round trip (TIMESYNC, else first-try COMMAND_ACK); None if none."""
        return None if self._rtt_s is None else self._rtt_s / 2.0

    @property
    def latency_source(self) -> str | None:
        """``"TIMESYNC"`` or ``"COMMAND_ACK"``: where :attr:`latency_s` comes from."""
        return self._rtt_source

    @property
    def remote_address(self) -> Any:
        """The vehicle's (host, port) once known."""
        return self._remote

    @property
    def local_address(self) -> Any:
        """The bound (host, port) of our socket (None before :meth:`open`)."""
        if self._transport is None:
            return None
        return self._transport.get_extra_info("sockname")

    # -- warnings --------------------------------------------------------------------------------
    def _warn_limited(self, key: str, message: str) -> None:
        now = time.monotonic()
        last = self._warned_at.get(key)
        if last is not None and now - last < _WARN_INTERVAL_S:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        suppressed = self._suppressed.pop(key, 0)
        self._warned_at[key] = now
        if suppressed:
            message += f" ({suppressed} more like this in the last {now - last:.0f} s)"
        log.warning(message)

    # -- receive path ----------------------------------------------------------------------------
    def feed_datagram(self, data: bytes, addr: Any, now: float | None = None) -> None:
        """Handle one received datagram (the protocol calls this; tests may too)."""
        if now is None:
            now = time.monotonic()
        st = self.state
        # the hot case first (25-50 a second per vehicle): one unsigned LOCAL_POSITION_NED of
        # full length from the known vehicle, its CRC good (else the general path below)
        if (len(data) == _LPN_FRAME_LEN and data[7] == MSG_LOCAL_POSITION_NED
                and data[:4] == _LPN_HEAD and not data[8] and not data[9]
                and data[5] == self._sysid and addr == self._remote and self.signing is None
                and self._fast_codec
                and mcrf4xx(_LPN_EXTRA, mcrf4xx(data[1:38])) == _CRC16.unpack_from(data, 38)[0]):
            tb, n, e, d, vn, ve, vd = _LPN.unpack_from(data, 10)
            g = self._guard
            if g is not None and not g.check_local(tb, n, e, d, vn, ve, vd, now):
                return  # refused: counted in state.telemetry_refused
            (st.time_boot_ms, st.north_m, st.east_m, st.down_m, st.vn_m_s, st.ve_m_s,
             st.vd_m_s) = tb, n, e, d, vn, ve, vd
            st.rx_packets += 1
            st.last_packet_s = st.last_position_s = now
            if self._position_waiters or self._state_waiters:
                self._notify_position()
            return
        if (
            self.signing is None
            and addr == self._remote
            and len(data) >= 12
            and data[0] == 0xFD
            and data[5] == self._sysid
            and len(data) == data[1] + (25 if data[2] & 1 else 12)
        ):
            msgid = data[7] | (data[8] << 8) | (data[9] << 16)
            # Cheap path: exactly one MAVLink 2 packet from the known vehicle, id we do not use.
            if not self.decode_all and msgid not in self._handlers:
                st.rx_packets += 1
                st.last_packet_s = now
                return
            # Fast path: a hot message, one valid unsigned frame (anything else: pymavlink)
            if msgid in _FAST_RX and self.fast_codec:
                m = _WIRE.unpack(data)
                if m is not None:
                    if msgid == MSG_HEARTBEAT and m.autopilot == _MAV_AUTOPILOT_INVALID:
                        st.foreign_packets += 1  # a GCS using the vehicle's id
                        return
                    st.rx_packets += 1
                    st.last_packet_s = now
                    handler = self._handlers.get(msgid)
                    if handler is not None:
                        handler(m, now)
                    return
        self._decode(data, addr, now)

    def _decode(self, data: bytes, addr: Any, now: float) -> None:
        mav = self._mav
        st = self.state
        bad: str | None = None
        try:
            msgs = mav.parse_buffer(data)
        except Exception as exc:  # robust_parsing should prevent this; never crash
            msgs = None
            bad = f"parser error {exc!r}"
        if mav.buf_len():
            bad = bad or f"{mav.buf_len()} trailing bytes (cut-off packet)"
            mav.buf = bytearray()
            mav.buf_index = 0
            mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
        if msgs:
            for m in msgs:
                if isinstance(m, mavlink2.MAVLink_bad_data):
                    if self.signing is not None and "Invalid signature" in str(m.reason):
                        self._warn_signing_refused(addr)
                        continue
                    bad = bad or str(m.reason)
                    continue
                if isinstance(m, mavlink2.MAVLink_unknown):
                    buf = m._msgbuf
                    if (self.signing is not None and self.signing.require_signed
                            and not (buf[0] == 0xFD and buf[2] & 1)):
                        self.signing_refused["unsigned"] += 1  # (ids pymavlink cannot verify)
                        continue
                    sysid = buf[5] if buf[0] == 0xFD else buf[3]
                    compid = buf[6] if buf[0] == 0xFD else buf[4]
                    if self._sysid is None or self._admit(sysid, compid, None, addr, now):
                        st.rx_packets += 1
                        st.last_packet_s = now
                    continue
                hdr = m._header
                msgid = hdr.msgId
                if not self._admit(hdr.srcSystem, hdr.srcComponent,
                                   m if msgid == MSG_HEARTBEAT else None, addr, now):
                    continue
                st.rx_packets += 1
                st.last_packet_s = now
                handler = self._handlers.get(msgid)
                if handler is not None:
                    handler(m, now)
        if bad is not None:
            st.bad_packets += 1
            self._warn_limited(
                "bad",
                f"{self.name}: dropped malformed datagram of {len(data)} bytes from {addr}: "
                f"{bad} (bad so far: {st.bad_packets})",
            )
            self._notify_state()

    # -- identity and source (docs/links.md, "Identity, source and plausibility") -------------
    def _admit(self, sysid: int, compid: int, hb: Any, addr: Any, now: float) -> bool:
        """Whether one valid packet speaks for this link's vehicle (``hb``: the packet if it
        is a HEARTBEAT). Its system id only: another vehicle's packets are refused, counted,
        and kept for :meth:`identity_problem` when they come from a vehicle (a HEARTBEAT not
        of a GCS, or a packet of an autopilot, compid 1, below id 245); a GCS's HEARTBEAT is
        foreign. From the learned address only: a ``udpin`` link learns it from the first
        packet of its vehicle's autopilot; :meth:`_relearned` is the one way to another."""
        st = self.state
        gcs_hb = hb is not None and hb.autopilot == _MAV_AUTOPILOT_INVALID
        if sysid != self._sysid:
            if self._sysid is None and compid == self.target_compid and not gcs_hb:
                self._sysid = st.sysid = sysid  # unpinned: the first autopilot is it
                self._tx = None
            else:
                st.foreign_packets += 1
                if not gcs_hb:
                    # another vehicle: a vehicle's HEARTBEAT, or its autopilot's packets
                    # (not of ids 245-255, where ground stations live: their tools' packets
                    # can come from compid 1 and be forwarded by PX4)
                    if (hb.type != _MAV_TYPE_GCS if hb is not None
                            else compid == _MAV_COMP_ID_AUTOPILOT1 and sysid < _GCS_IDS_FROM):
                        heard = self._vehicles_heard.setdefault(sysid, set())
                        if len(heard) < _HEARD_MAX:
                            heard.add(addr)
                    self._refuse_at_door("other_sysid", lambda: (
                        f"a packet of system {sysid} from {_addr(addr)}; this link flies "
                        f"system {self._sysid}"))
                return False
        if gcs_hb:
            st.foreign_packets += 1  # a GCS using the vehicle's id
            return False
        if addr != self._remote:
            if self._remote is None and self.endpoint.listens:
                if compid != self.target_compid:
                    return False  # learned from the autopilot only
                self._remote = addr
                self._tx = None
                log.debug("%s: vehicle at %s", self.name, _addr(addr))
            elif not self.pin_source:
                pass  # the test switch: anyone may speak for the vehicle
            elif not (hb is not None and compid == self.target_compid
                      and self._relearned(addr, now)):
                self._refuse_at_door("other_source", lambda: (
                    f"system {sysid} from {_addr(addr)}, but the vehicle is at "
                    f"{_addr(self._remote)}"))
                return False
        return True

    def _relearned(self, addr: Any, now: float) -> bool:
        """A HEARTBEAT of the vehicle's id from ``addr``, not its learned address: re-learn
        ``addr`` once :data:`RELEARN_HEARTBEATS` came from it while the learned address has
        been silent for :data:`RELEARN_SILENCE_S` (a modem that reconnected from another
        port), logged; else remember it for :meth:`identity_problem` and refuse."""
        last = self.state.last_packet_s
        if (last is not None and now - last < RELEARN_SILENCE_S) or not self.endpoint.listens:
            self._relearn = None
            if len(self._sources_heard) < _HEARD_MAX:
                self._sources_heard.add(addr)
            return False
        cand = self._relearn
        if cand is None or cand[0] != addr or (last is not None and cand[1] < last):
            self._relearn = cand = [addr, now, 0]  # (all of them after the old one's last)
        cand[2] += 1
        if cand[2] < RELEARN_HEARTBEATS:
            return False
        silent = "never heard" if last is None else f"silent for {now - last:.1f} s"
        log.warning("%s: vehicle address re-learned: %s -> %s (%d HEARTBEATs of system %s from "
                    "the new address in %.1f s while the old one was %s)", self.name,
                    _addr(self._remote), _addr(addr), cand[2], self._sysid, now - cand[1],
                    silent)
        self._remote = addr
        self._tx = None
        self._relearn = None
        self.state.source_changes += 1
        return True

    def identity_problem(self) -> str | None:
        """Other vehicles heard on this port, or this vehicle's id from a second address while
        the first one spoke: the port does not carry one vehicle (refused before arming, with
        the likely cause)."""
        me = self._sysid
        problems = []
        if self._vehicles_heard:
            ids = sorted({*self._vehicles_heard, *([] if me is None else [me])})
            froms = sorted({a for s in self._vehicles_heard.values() for a in s}, key=str)
            problems.append(
                f"its port hears {len(ids)} vehicles, systems "
                f"{_id_list(ids)} (this link flies system {me}; the others from "
                f"{', '.join(_addr(a) for a in froms[:4])}{' …' if len(froms) > 4 else ''}): "
                + shared_port_cause([self.endpoint.port],
                                    [a[1] for a in froms if isinstance(a, tuple)]))
        if self._sources_heard:
            others = sorted(self._sources_heard, key=str)
            problems.append(
                f"system {me} speaks from {len(others) + 1} addresses, {_addr(self._remote)} "
                f"and {', '.join(_addr(a) for a in others[:4])}: two vehicles with one "
                f"MAV_SYS_ID on this port, one vehicle's two MAVLink links (PX4 SITL's GCS "
                f"link sends from 18570+i), or someone else sending as system {me}")
        return "; ".join(problems) or None

    def _refuse_at_door(self, kind: str, why: Callable[[], str]) -> None:
        """Count a refusal of the identity/source rules; ``why()`` is made only when it is
        warned about (at most every 5 s: a flood must not cost a formatted line each)."""
        st = self.state
        st.telemetry_refused[kind] += 1
        key = "refused " + kind
        last = self._warned_at.get(key)
        if last is not None and time.monotonic() - last < _WARN_INTERVAL_S:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        self._warn_limited(key, f"{self.name}: refused ({kind}): {why()} (refused so far: "
                                f"{st.telemetry_refused[kind]})")

    # -- message handlers ------------------------------------------------------------------------
    def _on_heartbeat(self, m: Any, now: float) -> None:
        st = self.state
        st.last_heartbeat_s = now
        st.base_mode = m.base_mode
        st.armed = bool(m.base_mode & 0x80)
        st.system_status = px4.system_status_name(m.system_status)
        if m.base_mode & 0x01:  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            cm = m.custom_mode
            if cm != st.custom_mode:
                st.custom_mode = cm
                st.flight_mode = px4.flight_mode_name(cm)
                st.px4_mode = px4.px4_mode_name(cm)
        else:
            st.custom_mode = None
            st.flight_mode = st.px4_mode = "UNKNOWN"
        if self._hb_lost_warned:
            self._hb_lost_warned = False
            log.warning("%s: HEARTBEAT back", self.name)
        self._notify_state()

    def _on_sys_status(self, m: Any, now: float) -> None:
        st = self.state
        pct = m.battery_remaining  # -1: the vehicle does not know
        st.battery_remaining = pct * 0.01 if 0 <= pct <= 100 else math.nan
        problems = tuple(px4.health_problems(m.onboard_control_sensors_health))
        if problems != st.health_problems:
            st.health_problems = problems
            st.health_ok = not problems
            self._notify_state()

    def _on_local_position(self, m: Any, now: float) -> None:
        g = self._guard
        if g is not None and not g.check_local(m.time_boot_ms, m.x, m.y, m.z, m.vx, m.vy, m.vz,
                                               now):
            return
        st = self.state
        st.time_boot_ms = m.time_boot_ms
        st.north_m = m.x
        st.east_m = m.y
        st.down_m = m.z
        st.vn_m_s = m.vx
        st.ve_m_s = m.vy
        st.vd_m_s = m.vz
        st.last_position_s = now
        self._notify_position()

    def _on_global_position(self, m: Any, now: float) -> None:
        g = self._guard
        if g is not None and not g.check_global(m.time_boot_ms, m.lat * 1e-7, m.lon * 1e-7,
                                                m.alt * 1e-3, m.vx * 0.01, m.vy * 0.01,
                                                m.vz * 0.01, now):
            return
        st = self.state
        st.lat_deg = m.lat * 1e-7
        st.lon_deg = m.lon * 1e-7
        st.alt_m = m.alt * 1e-3
        st.relative_alt_m = m.relative_alt * 1e-3
        st.heading_deg = m.hdg * 0.01 if m.hdg != 65535 else math.nan
        st.last_global_s = now
        self._notify_state()

    def _on_estimator_status(self, m: Any, now: float) -> None:
        acc = float(m.pos_horiz_accuracy)
        self.state.pos_accuracy_m = acc if math.isfinite(acc) and acc >= 0 else math.nan
        if self._guard is not None:
            self._guard.set_accuracy(self.state.pos_accuracy_m)

    def _on_gps_raw(self, m: Any, now: float) -> None:
        st = self.state
        st.gnss_fix_type = int(m.fix_type)
        h_acc = getattr(m, "h_acc", 0)
        st.gnss_h_acc_m = h_acc * 1e-3 if h_acc else math.nan

    def _on_truth(self, m: Any, now: float) -> None:
        st = self.state
        st.truth_lat_deg = m.lat * 1e-7
        st.truth_lon_deg = m.lon * 1e-7
        st.truth_alt_m = m.alt * 1e-3
        st.truth_vn_m_s = m.vx * 0.01
        st.truth_ve_m_s = m.vy * 0.01
        st.last_truth_s = now

    def _on_origin(self, m: Any, now: float) -> None:
        st = self.state
        origin = GeoPoint(m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
        if st.origin is not None and origin != st.origin:
            log.warning("%s: GPS global origin changed from %s to %s", self.name, st.origin,
                        origin)
        st.origin = origin
        self._notify_state()

    def _on_home(self, m: Any, now: float) -> None:
        self.state.home = GeoPoint(m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
        self._notify_state()

    def _on_extended_sys_state(self, m: Any, now: float) -> None:
        name = px4.landed_state_name(m.landed_state)
        if name != self.state.landed_state:
            self.state.landed_state = name
            self._notify_state()

    def _on_command_ack(self, m: Any, now: float) -> None:
        if m.target_system not in (0, self.gcs_sysid):
            return
        fut = self._pending.get(m.command)
        if fut is not None and not fut.done():
            fut.set_result(m.result)

    def _on_timesync(self, m: Any, now: float) -> None:
        if m.tc1 == 0:
            return
        rtt = time.monotonic_ns() * 1e-9 - m.ts1 * 1e-9
        fut = self._timesync_waiters.pop(m.ts1, None)
        if fut is not None and not fut.done():
            fut.set_result(rtt)
        if self._timesync_ts1 is not None and m.ts1 == self._timesync_ts1:
            self._timesync_ts1 = None
        elif fut is None:
            return
        self._rtt_sample(rtt, "TIMESYNC")
        self._notify_state()

    def _on_statustext(self, m: Any, now: float) -> None:
        text = m.text if isinstance(m.text, str) else bytes(m.text).decode("ascii", "replace")
        chunks = self._text_chunks
        key = m.id
        for other in [k for k in chunks if k != key]:  # an unfinished message: flush it
            self._text_started.pop(other, None)
            self._emit_statustext(self._text_severity.pop(other), "".join(chunks.pop(other)), now)
        if key not in chunks:
            self._text_started[key] = now
        chunks.setdefault(key, []).append(text)
        self._text_severity[key] = m.severity
        if len(text) < 50:  # the last chunk is NUL-terminated (PX4: first chunks exactly 50)
            self._text_started.pop(key, None)
            self._emit_statustext(self._text_severity.pop(key), "".join(chunks.pop(key)), now)

    def _flush_statustexts(self, now: float, older_than_s: float = 0.5) -> None:
        """Emit chunked texts whose last chunk never came (e.g. exactly 50 characters)."""
        for key in [k for k, t in self._text_started.items() if now - t > older_than_s]:
            del self._text_started[key]
            if key in self._text_chunks:
                self._emit_statustext(
                    self._text_severity.pop(key), "".join(self._text_chunks.pop(key)), now
                )

    def _emit_statustext(self, severity: int, text: str, now: float) -> None:
        text = text.rstrip("\t\r\n \x00")
        self.state.statustexts.append(StatusText(now, severity, text))
        self._log_statustext(log, severity, text)
        self._notify_state()

    def _rtt_sample(self, rtt_s: float, source: str) -> None:
        if not 0.0 <= rtt_s < 10.0:
            return
        if source == "COMMAND_ACK" and self._rtt_source == "TIMESYNC":
            return
        if self._rtt_s is None or self._rtt_source != source:
            self._rtt_s = rtt_s
        else:
            self._rtt_s += _RTT_ALPHA * (rtt_s - self._rtt_s)
        self._rtt_source = source

    # -- send path --------------------------------------------------------------------------------
    def _send(self, msg: Any) -> None:
        transport = self._transport
        if transport is None or transport.is_closing():
            raise LinkError(f"{self.name}: link is closed")
        if self._remote is None:
            raise LinkError(f"{self.name}: vehicle not seen yet; call connect() first")
        mav = self._mav
        if self.signing is not None:
            self._signing_tick()
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) & 0xFF
        self._send_bytes(transport, buf)

    def _send_bytes(self, transport: DatagramSocket, buf: bytes) -> None:
        if self.endpoint.listens:
            transport.sendto(buf, self._remote)
        else:
            transport.sendto(buf)
        self.tx_packets += 1

    def _time_boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000.0) & 0xFFFFFFFF

    def send_velocity_ned(
        self,
        north_m_s: float,
        east_m_s: float,
        down_m_s: float,
        yaw_deg: float | None = None,
    ) -> None:
        """Send one SET_POSITION_TARGET_LOCAL_NED (LOCAL_NED, velocity only; with yaw if given)
        now. Raises :class:`LinkError` before the vehicle is known or after close."""
        self._check_setpoint(north_m_s, east_m_s, down_m_s)
        if yaw_deg is None:
            mask, yaw = TYPE_MASK_VELOCITY, 0.0
        else:
            mask, yaw = TYPE_MASK_VELOCITY_YAW, math.radians(yaw_deg)
        if not self._send_fast(
                MSG_SET_POSITION_TARGET_LOCAL_NED, self._time_boot_ms(), 0.0, 0.0, 0.0,
                north_m_s, east_m_s, down_m_s, 0.0, 0.0, 0.0, yaw, 0.0, mask,
                self._sysid or 0, self.target_compid, mavlink2.MAV_FRAME_LOCAL_NED):
            self._send(self._mav.set_position_target_local_ned_encode(
                self._time_boot_ms(), self._sysid or 0, self.target_compid,
                mavlink2.MAV_FRAME_LOCAL_NED, mask,
                0.0, 0.0, 0.0, north_m_s, east_m_s, down_m_s, 0.0, 0.0, 0.0, yaw, 0.0,
            ))
        self._last_setpoint_s = time.monotonic()
        self._setpoints_sent += 1
        self._stall_warned = False

    @classmethod
    def _send_velocities(cls, links: Sequence[VehicleLink], north: np.ndarray,
                         east: np.ndarray, down: np.ndarray) -> list[LinkError | None]:
        """:meth:`VehicleLink.send_velocities_ned` (checked setpoints): the links on the struct
        fast path get their SET_POSITION_TARGET_LOCAL_NED frames built together
        (:meth:`WireCodec.pack_many`, the bytes :meth:`send_velocity_ned` sends) and then one
        ``sendto`` each; the others (signed, ``fast_codec`` off, not connected, closed) go one
        by one."""
        out: list[LinkError | None] = [None] * len(links)
        now = time.monotonic()
        rows: list[int] = []
        slots: list[tuple[Any, ...]] = []
        seqs: list[int] = []
        # every Python object a link's send touches, touched here, before the sendto loop (a
        # send's kernel work evicts them from the caches: interleaved, each costs a miss)
        for k, link in enumerate(links):
            tx = link._tx if link._tx is not None else link._tx_slot()  # type: ignore
            if not tx:
                try:
                    link.send_velocity_ned(float(north[k]), float(east[k]), float(down[k]))
                except LinkError as exc:
                    out[k] = exc
                continue
            rows.append(k)
            slots.append(tx)
            seqs.append(tx[2].seq)
        if not rows:
            return out
        meta = np.array([tx[3:8] for tx in slots], dtype=float).reshape(len(rows), 5)
        frames = _WIRE.pack_many(
            MSG_SET_POSITION_TARGET_LOCAL_NED, np.array(seqs, dtype=np.int64),
            meta[:, 1].astype(np.int64), meta[:, 2].astype(np.int64),
            {"time_boot_ms": ((now - meta[:, 0]) * 1000.0).astype(np.int64) & 0xFFFFFFFF,
             "vx": north[rows], "vy": east[rows], "vz": down[rows],
             "type_mask": TYPE_MASK_VELOCITY, "target_system": meta[:, 3].astype(np.int64),
             "target_component": meta[:, 4].astype(np.int64),
             "coordinate_frame": mavlink2.MAV_FRAME_LOCAL_NED})  # _time_boot_ms, for all
        for k, tx, seq in zip(rows, slots, seqs, strict=True):  # (objects still warm)
            tx[2].seq = (seq + 1) & 0xFF  # as _send_fast: counted whatever the kernel says
            link = links[k]
            link.tx_packets += 1  # type: ignore[attr-defined]
            link._last_setpoint_s = now
            link._setpoints_sent += 1
            link._stall_warned = False  # type: ignore[attr-defined]
        for tx, buf in zip(slots, frames, strict=True):
            try:
                # the socket's own sendto, with DatagramSocket.sendto's error rules; a udpout
                # socket gets its own peer as the address; a closed link has no _tx
                tx[0](buf, tx[1])
            except (BlockingIOError, InterruptedError):
                tx[8].tx_dropped += 1
            except OSError as exc:
                tx[8]._on_error(exc)
        return out

    def _tx_slot(self) -> tuple[Any, ...] | bool:
        """What :meth:`send_velocities_ned` needs of this link, kept in ``_tx`` until any of
        it changes: (the socket's ``sendto``, the vehicle's address, the codec object with the
        sequence number, time_boot_ms's zero, GCS system and component id, target system and
        component id, the :class:`DatagramSocket`); False where the batch path does not apply
        (closed, signing, ``fast_codec`` off, no socket or vehicle yet)."""
        tr = self._transport
        tx: tuple[Any, ...] | bool = False
        if (not self._closed and self._fast_codec and self.signing is None and tr is not None
                and self._remote is not None and not tr.is_closing()):
            sock = tr.get_extra_info("socket")
            send, addr = ((sock.sendto, self._remote) if sock is not None
                          else (tr.sendto, self._remote if self.endpoint.listens else None))
            tx = (send, addr, self._mav, self._t0, self.gcs_sysid, self.gcs_compid,
                  self._sysid or 0, self.target_compid, tr)
        self._tx = tx
        return tx

    def _send_fast(self, msgid: int, *values: Any) -> bool:
        """Send ``msgid`` with ``values`` (wire order) as the frame pymavlink would build, byte
        for byte (tests/test_link_wire.py), without pymavlink; False (nothing sent) when the
        fast path does not apply: signing, ``fast_codec`` off, no socket or vehicle yet."""
        transport = self._transport
        if (not self.fast_codec or self.signing is not None or transport is None
                or self._remote is None or transport.is_closing()):
            return False
        mav = self._mav
        self._send_bytes(transport, _WIRE.pack(msgid, mav.seq, self.gcs_sysid,
                                               self.gcs_compid, *values))
        mav.seq = (mav.seq + 1) & 0xFF
        return True

    def send_heartbeat(self) -> None:
        """Send one GCS HEARTBEAT (type GCS, autopilot INVALID, state ACTIVE)."""
        if not self._send_fast(MSG_HEARTBEAT, 0, mavlink2.MAV_TYPE_GCS,
                               mavlink2.MAV_AUTOPILOT_INVALID, 0, mavlink2.MAV_STATE_ACTIVE, 3):
            self._send(self._mav.heartbeat_encode(
                mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                mavlink2.MAV_STATE_ACTIVE, 3,
            ))

    # -- lifecycle ------------------------------------------------------------------------------
    async def open(self) -> None:
        """Bind/open the UDP socket and start the GCS heartbeat (no waiting)."""
        if self._closed:
            raise LinkError(f"{self.name}: link is closed")
        if self._transport is not None:
            return
        loop = asyncio.get_running_loop()
        ep = self.endpoint
        try:  # read in bursts (vtube_fleet/link/udp.py), not one datagram per callback
            transport = await DatagramSocket.open(ep.host, ep.port, listens=ep.listens,
                                                  on_datagram=self.feed_datagram,
                                                  on_error=self._socket_error)
        except OSError as exc:
            verb = "bind" if ep.listens else "open"
            raise LinkError(f"{self.name}: cannot {verb} {ep.url}: {exc.strerror or exc}") from None
        self._transport = transport
        if not ep.listens:  # compare received addresses with the resolved peer
            self._remote = transport.get_extra_info("peername") or self._remote
        self._t0 = time.monotonic()
        self._tx = None
        self._tasks.append(loop.create_task(self._heartbeat_loop(), name=f"gcs-hb {ep.url}"))

    def _socket_error(self, exc: OSError) -> None:
        # e.g. ICMP port unreachable for udpout while the vehicle is not up yet
        self._warn_limited("socket", f"{self.name}: socket error: {exc}")

    async def connect(self, timeout_s: float = 10.0) -> None:
        """Open the socket, wait for the vehicle's HEARTBEAT, request the telemetry streams.

        ``timeout_s`` bounds the whole: a stream request that gets no COMMAND_ACK is repeated
        (as a GCS does) until then, at least ``command_tries`` times; the streams turned off
        go first (they cut the load of a busy link). Raises :class:`LinkTimeout` saying what
        arrived (nothing / packets but no HEARTBEAT / no ACK after n tries). Safe to call
        concurrently and repeatedly.
        """
        async with self._connect_lock:
            deadline = asyncio.get_running_loop().time() + timeout_s
            await self.open()
            if self.state.last_heartbeat_s is None:
                try:
                    await self.wait_until(
                        lambda s: s.last_heartbeat_s is not None, timeout_s, "first HEARTBEAT"
                    )
                except LinkTimeout:
                    st = self.state
                    if st.rx_packets:
                        what = f"{st.rx_packets} packets from system {st.sysid} but no HEARTBEAT"
                    else:
                        what = "nothing received"
                    raise LinkTimeout(
                        f"{self.name}: no HEARTBEAT within {timeout_s:.1f} s ({what}; "
                        f"{st.bad_packets} malformed, {st.foreign_packets} from others"
                        f"{self._signing_note()}){self._other_ids_note()}"
                    ) from None
            if not self._streams_requested:
                await self._request_streams(deadline)
                self._streams_requested = True
            log.info("%s: connected", self.name)

    def _other_ids_note(self) -> str:
        """Why no HEARTBEAT came when other vehicles' did: the id is not the vehicle's."""
        heard = sorted(self._vehicles_heard)
        if not heard or self._sysid is None:
            return ""
        url = self.endpoint.transport_url
        return (f"; heard system {_id_list(heard)} instead: this link flies system "
                f"{self._sysid} (the endpoint's ?sysid=, PX4 SITL's 14540+i scheme or the "
                f"slot's id); give the vehicle's id, e.g. {url}?sysid={heard[0]}")

    async def _request_streams(self, deadline: float | None = None) -> None:
        """SET_MESSAGE_INTERVAL for every stream (those turned off first), then REQUEST_MESSAGE
        for home and origin; each repeated without ACK until ``deadline`` (loop time)."""
        rates = sorted(self.message_rates_hz.items(), key=lambda kv: kv[1] > 0)
        for msgid, rate in rates:
            interval_us = -1.0 if rate <= 0 else 1e6 / rate
            self.streams_changed.add(msgid)  # (given back at close, acknowledged or not)
            await self._try_command(CMD_SET_MESSAGE_INTERVAL, float(msgid), interval_us,
                                    what=f"{_message_name(msgid)} at {rate:g} Hz",
                                    deadline=deadline)
        for msgid in (MSG_HOME_POSITION, MSG_GPS_GLOBAL_ORIGIN):
            await self._try_command(CMD_REQUEST_MESSAGE, float(msgid),
                                    what=_message_name(msgid), deadline=deadline)

    #: Seconds :meth:`restore_streams` waits for the vehicle's acknowledgements at most.
    RESTORE_S = 1.5

    async def restore_streams(self) -> list[int]:
        """Give every stream this link changed back to PX4's own rate (SET_MESSAGE_INTERVAL 0:
        "the default rate"), all at once, one try each, within :attr:`RESTORE_S`; returns the
        streams whose restoration was not acknowledged (warned about). Called by
        :meth:`close` on every exit path."""
        todo = sorted(self.streams_changed)
        if not todo or self._closed or self._remote is None:
            return []
        self.streams_changed.clear()

        async def one(msgid: int) -> int | None:
            try:
                result = await self.command_long(CMD_SET_MESSAGE_INTERVAL, float(msgid), 0.0,
                                                 tries=1, raise_on_reject=False)
            except LinkError:
                return msgid
            return None if result == "ACCEPTED" else msgid

        try:
            async with asyncio.timeout(self.RESTORE_S):
                left = [m for m in await asyncio.gather(*(one(m) for m in todo)) if m is not None]
        except TimeoutError:
            left = todo
        self.unrestored_streams = list(left)
        if left:
            log.log(logging.WARNING if self.warn_unrestored else logging.DEBUG,
                    "%s: PX4's own rate not confirmed for %s (the vehicle keeps our rates "
                    "until it reboots or a ground station sets them)", self.name,
                    ", ".join(self.unrestored_names))
        return left

    @property
    def unrestored_names(self) -> list[str]:
        """The names of :attr:`unrestored_streams`."""
        return [_message_name(m) for m in self.unrestored_streams]

    async def _try_command(self, command: int, *params: float, what: str,
                           deadline: float | None = None) -> None:
        tries = self.command_tries
        if deadline is not None:  # as many tries as fit before the deadline, at least the usual
            left = deadline - asyncio.get_running_loop().time()
            tries = max(tries, int(left / self.command_timeout_s))
        result = await self.command_long(command, *params, tries=tries, raise_on_reject=False)
        if result != "ACCEPTED":
            # REQUEST_MESSAGE is repeated by wait_ready while home/origin are missing
            level = logging.INFO if command == CMD_REQUEST_MESSAGE else logging.WARNING
            log.log(level, "%s: %s %s answered %s", self.name, command_name(command), what,
                    result)

    async def _ready_tick(self, missing: list[str]) -> None:
        if self._remote is None or self._closed:
            return
        # Fire and forget: the vehicle sends these (again) once it has them.
        for msgid, what in ((MSG_HOME_POSITION, "no home position"),
                            (MSG_GPS_GLOBAL_ORIGIN, "no GPS global origin")):
            if what in missing:
                self._send(self._mav.command_long_encode(
                    self._sysid or 0, self.target_compid, CMD_REQUEST_MESSAGE, 0,
                    float(msgid), 0, 0, 0, 0, 0, 0,
                ))

    async def _heartbeat_loop(self) -> None:
        period = self.heartbeat_period_s
        while not self._closed:
            if self._remote is not None and self._transport is not None:
                try:
                    self.send_heartbeat()
                    ts1 = time.monotonic_ns()
                    self._timesync_ts1 = ts1
                    if not self._send_fast(MSG_TIMESYNC, 0, ts1):
                        self._send(self._mav.timesync_encode(0, ts1))
                    self._check_liveness()
                except LinkError:
                    return
                except Exception:  # never let the heartbeat die silently
                    log.exception("%s: GCS heartbeat failed", self.name)
            await asyncio.sleep(period)

    def _check_liveness(self) -> None:
        now = time.monotonic()
        st = self.state
        if self._text_started:
            self._flush_statustexts(now)
        if st.last_heartbeat_s is not None and not self._hb_lost_warned:
            age = now - st.last_heartbeat_s
            if age > _HEARTBEAT_LOST_S:
                self._hb_lost_warned = True
                log.warning("%s: no HEARTBEAT for %.1f s (last packet %.1f s ago)", self.name,
                            age, now - (st.last_packet_s or st.last_heartbeat_s))
        if (
            st.flight_mode == "OFFBOARD"
            and st.armed
            and self._last_setpoint_s is not None
            and not self._stall_warned
        ):
            age = now - self._last_setpoint_s
            if age > 1.0:
                self._stall_warned = True
                log.warning(
                    "%s: no velocity setpoint sent for %.1f s while in OFFBOARD; PX4's "
                    "offboard-loss failsafe (COM_OF_LOSS_T, default 1.0 s) takes over",
                    self.name, age,
                )

    async def measure_round_trip_s(self, samples: int = 3, timeout_s: float = 1.0
                                   ) -> float | None:
        """TIMESYNC round trips, one after another; the largest answered one (None if none)."""
        loop = asyncio.get_running_loop()
        worst: float | None = None
        for _ in range(max(1, samples)):
            if self._remote is None or self._closed:
                break
            ts1 = time.monotonic_ns()
            fut: asyncio.Future[float] = loop.create_future()
            self._timesync_waiters[ts1] = fut
            try:
                self._send(self._mav.timesync_encode(0, ts1))
                async with asyncio.timeout(timeout_s):
                    rtt = await fut
            except TimeoutError:
                continue
            finally:
                self._timesync_waiters.pop(ts1, None)
            worst = rtt if worst is None else max(worst, rtt)
        return worst

    async def request_truth(self, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL for HIL_STATE_QUATERNION (PX4 SITL and sim_stub accept it)."""
        await self.command_long(CMD_SET_MESSAGE_INTERVAL, float(MSG_HIL_STATE_QUATERNION),
                                1e6 / rate_hz)

    async def close(self) -> None:
        if self._closed:
            return
        try:
            await self.restore_streams()  # PX4's stream rates as we found them
        except Exception as exc:  # noqa: BLE001 - closing goes on whatever happens
            log.warning("%s: restoring the stream rates failed: %s", self.name, exc)
        self._closed = True
        self._tx = None
        await cancel_tasks(self._tasks)
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(LinkError(f"{self.name}: link closed"))
        self._pending.clear()
        if self._transport is not None:
            if self._transport.tx_dropped:
                log.warning("%s: %d datagram(s) not sent: the kernel's send buffer was full",
                            self.name, self._transport.tx_dropped)
            self._transport.close()
            # the socket is closed by a call_soon callback: let it run, so that the port can
            # be bound again as soon as close() returns (asyncio runs callbacks in FIFO order)
            await asyncio.sleep(0)
        self._wake_all_closed()

    # -- commands -------------------------------------------------------------------------------
    async def command_long(
        self,
        command: int,
        *params: float,
        tries: int | None = None,
        timeout_s: float | None = None,
        raise_on_reject: bool = True,
        in_progress_timeout_s: float = 10.0,
    ) -> str:
        """Send COMMAND_LONG ``command`` (params 1..7, missing ones 0) with retries; return the
        MAV_RESULT name. :class:`LinkTimeout` if no ACK after all tries;
        :class:`CommandRejected` for a non-ACCEPTED result if ``raise_on_reject``."""
        if len(params) > 7:
            raise ValueError(f"COMMAND_LONG has 7 params, got {len(params)}")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        tries = self.command_tries if tries is None else tries
        per_try = self.command_timeout_s if timeout_s is None else timeout_s
        name = command_name(command)
        if self._remote is None:
            raise LinkError(f"{self.name}: {name}: vehicle not seen yet; call connect() first")
        lock = self._cmd_locks.get(command)
        if lock is None:
            lock = self._cmd_locks[command] = asyncio.Lock()
        loop = asyncio.get_running_loop()
        async with lock:
            result: int | None = None
            for attempt in range(tries):
                fut: asyncio.Future[int] = loop.create_future()
                self._pending[command] = fut
                t_sent = loop.time()
                try:
                    self._send(self._mav.command_long_encode(
                        self._sysid or 0, self.target_compid, command, attempt, *p
                    ))
                    async with asyncio.timeout(per_try):
                        result = await fut
                except TimeoutError:
                    continue
                finally:
                    if self._pending.get(command) is fut:
                        del self._pending[command]
                if attempt == 0:
                    self._rtt_sample(loop.time() - t_sent, "COMMAND_ACK")
                if result == _RESULT_IN_PROGRESS:
                    result = await self._wait_final_ack(command, in_progress_timeout_s, name)
                break
            if result is None:
                raise LinkTimeout(
                    f"{self.name}: no COMMAND_ACK for {name} after {tries} tries of "
                    f"{per_try:.2f} s (last packet from the vehicle "
                    f"{self._age(self.state.last_packet_s)})"
                )
        rname = px4.result_name(result)
        if result != _RESULT_ACCEPTED and raise_on_reject:
            raise CommandRejected(
                f"{self.name}: {name} {rname}{self._recent_text()}", command=name, result=rname
            )
        return rname

    async def _wait_final_ack(self, command: int, timeout_s: float, name: str) -> int:
        loop = asyncio.get_running_loop()
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    fut: asyncio.Future[int] = loop.create_future()
                    self._pending[command] = fut
                    try:
                        result = await fut
                    finally:
                        if self._pending.get(command) is fut:
                            del self._pending[command]
                    if result != _RESULT_IN_PROGRESS:
                        return result
        except TimeoutError:
            raise LinkTimeout(
                f"{self.name}: {name} still IN_PROGRESS after {timeout_s:.1f} s"
            ) from None

    def _age(self, t: float | None) -> str:
        return "never" if t is None else f"{time.monotonic() - t:.1f} s ago"

    def _recent_text(self, window_s: float = 2.0) -> str:
        texts = self.state.statustexts
        if texts and time.monotonic() - texts[-1].time_s <= window_s and texts[-1].severity <= 4:
            return f'; vehicle says "{texts[-1].text}"'
        return ""

    async def set_flight_mode(self, flight_mode: str) -> None:
        """DO_SET_MODE(1, main, sub) for a MAVSDK-style name (``HOLD``, ``OFFBOARD`` …) or a
        PX4 name (``AUTO.LOITER``)."""
        try:
            main, sub = px4.mode_for_flight_mode(flight_mode)
        except ValueError as exc:
            raise LinkError(f"{self.name}: {exc}") from None
        await self.command_long(CMD_DO_SET_MODE, 1.0, float(main), float(sub))

    async def arm(self, timeout_s: float = 10.0, retry_interval_s: float = 0.5) -> None:
        """ARM; retries TEMPORARILY_REJECTED (PX4 in its first ~3-4 s, pre-arm checks failing)
        every ``retry_interval_s`` until ``timeout_s``. Returns on ACCEPTED (the HEARTBEAT shows
        armed up to 1 s later)."""
        self.check_identity()  # a port carrying other vehicles is refused before arming
        loop = asyncio.get_running_loop()
        t_start = loop.time()
        attempts = 0
        while True:
            attempts += 1
            result = await self.command_long(CMD_COMPONENT_ARM_DISARM, 1.0, raise_on_reject=False)
            if result == "ACCEPTED":
                return
            elapsed = loop.time() - t_start
            if (
                result != px4.result_name(_RESULT_TEMPORARILY_REJECTED)
                or elapsed + retry_interval_s > timeout_s
            ):
                raise CommandRejected(
                    f"{self.name}: COMPONENT_ARM_DISARM (arm) {result} after {attempts} "
                    f"attempt(s) in {elapsed:.1f} s{self._recent_text(5.0)}",
                    command="COMPONENT_ARM_DISARM",
                    result=result,
                )
            await asyncio.sleep(retry_interval_s)  # back-off between attempts, not a sync

    async def disarm(self) -> None:
        await self.command_long(CMD_COMPONENT_ARM_DISARM, 0.0)

    async def takeoff(self, altitude_m: float) -> None:
        """NAV_TAKEOFF to ``altitude_m`` above the current global altitude (param7 is AMSL in
        PX4); lat/lon/yaw NaN = here. Arm first."""
        if not (math.isfinite(altitude_m) and altitude_m > 0):
            raise LinkError(f"{self.name}: takeoff altitude must be > 0 m, got {altitude_m}")
        alt = self.state.alt_m
        if not math.isfinite(alt):
            raise LinkError(f"{self.name}: takeoff needs the global position (none received yet)")
        nan = math.nan
        await self.command_long(CMD_NAV_TAKEOFF, 0.0, 0.0, 0.0, nan, nan, nan, alt + altitude_m)

    async def land(self) -> None:
        """NAV_LAND here (PX4 AUTO.LAND); PX4 disarms by itself ~2 s after landing."""
        nan = math.nan
        await self.command_long(CMD_NAV_LAND, 0.0, 0.0, 0.0, nan, nan, nan, nan)

    async def hold(self) -> None:
        await self.set_flight_mode("HOLD")

    async def start_offboard(self) -> None:
        """DO_SET_MODE OFFBOARD after checking that we stream setpoints (PX4 would ACCEPT it
        even without, then refuse to arm: captures 1d). Returns on the ACK; the HEARTBEAT shows
        OFFBOARD up to 1 s later (``wait_until(lambda s: s.flight_mode == "OFFBOARD", …)``)."""
        self._require_fresh_setpoints()
        await self.set_flight_mode("OFFBOARD")

    async def stop_offboard(self) -> None:
        await self.hold()

    # -- MAVLink 2 signing (vtube_fleet/link/signing.py) ---------------------------------------
    def _install_signing(self, signing: LinkSigning) -> None:
        """Sign with ``signing`` from now on (a :class:`_SigningMAVLink` codec that keeps our
        seq, and a timestamp never below the one already used)."""
        old = self._mav
        mav = _SigningMAVLink(self, srcSystem=self.gcs_sysid, srcComponent=self.gcs_compid)
        mav.robust_parsing = True
        mav.seq = old.seq
        sg = mav.signing
        sg.secret_key = signing.key
        sg.sign_outgoing = True
        sg.link_id = signing.link_id
        sg.allow_unsigned_callback = mav.allow_unsigned
        sg.timestamp = max(signing.store.start(), old.signing.timestamp)
        if isinstance(old, _SigningMAVLink):
            sg.stream_timestamps = dict(old.signing.stream_timestamps)
        signing.store.ensure(sg.timestamp)
        self._mav = mav
        self.signing = signing
        self._tx = None

    def _signing_tick(self) -> None:
        """Before each signed packet: timestamp = max(last + 1, the wall clock), below the
        reserved mark on disk (pymavlink's ``sign_packet`` uses it, then adds 1)."""
        assert self.signing is not None
        sg = self._mav.signing
        store = self.signing.store
        now = store.now()
        if now > sg.timestamp:
            sg.timestamp = now
        store.ensure(sg.timestamp)

    def _warn_signing_refused(self, addr: Any) -> None:
        self._warn_limited(
            "signing", f"{self.name}: refused a packet from {addr} that is not signed with "
            f"our key or replays an old timestamp (so far: {self._signing_counts()})")

    def _signing_counts(self) -> str:
        return ", ".join(f"{n} {k}" for k, n in sorted(self.signing_refused.items())) or "none"

    def _signing_note(self) -> str:
        if self.signing is None or not self.signing_refused:
            return ""
        return (f"; refused by signing: {self._signing_counts()}: does the vehicle hold our "
                f"key ({self.signing.key_file or 'the mission key'})? provision it with "
                f"vtube-fleet sign-setup")

    async def provision_signing(self, signing: LinkSigning, timeout_s: float = 10.0,
                                tries: int = 3) -> int:
        """SETUP_SIGNING with ``signing.key`` (sent ``tries`` times, signed with the link's
        current key), then sign with the new key, require signed traffic and wait for a
        HEARTBEAT signed with it (PX4 sends no ACK). Refused while armed, as PX4 refuses.
        Returns the initial timestamp sent. Connect first."""
        if self._remote is None:
            raise LinkError(f"{self.name}: SETUP_SIGNING: vehicle not seen yet; connect first")
        if self.state.armed:
            raise SigningError(f"{self.name}: vehicle is armed: PX4 refuses SETUP_SIGNING "
                               f"while armed; land and disarm it first")
        if self.signing is not None:
            self._signing_tick()
        initial = max(self._mav.signing.timestamp, signing.store.start())
        msg = self._mav.setup_signing_encode(self._sysid or 0, self.target_compid,
                                             list(signing.key), initial)
        for _ in range(max(1, tries)):
            self._send(msg)
        # packets the vehicle sent before it took the key are refused now: expected, so the
        # rate-limited warning starts as if it had just been given (they are still counted)
        self._warned_at["signing"] = time.monotonic()
        self._install_signing(LinkSigning(signing.key, signing.store, signing.link_id,
                                          require_signed=True, key_file=signing.key_file))
        t0 = time.monotonic()
        try:
            await self.wait_until(
                lambda s: s.last_heartbeat_s is not None and s.last_heartbeat_s > t0,
                timeout_s, "a HEARTBEAT signed with the new key")
        except LinkTimeout:
            raise SigningError(
                f"{self.name}: the vehicle did not sign with the new key within "
                f"{timeout_s:g} s after SETUP_SIGNING (refused: {self._signing_counts()}); "
                f"PX4 older than 1.18 ignores SETUP_SIGNING, an armed one refuses it, one "
                f"holding another key takes a new key only signed with that key "
                f"(--current-key)") from None
        return initial

    # -- onboard safety: parameters and the fence (PX4's mission protocol, mission_type FENCE) --
    # Kept apart from the rest of the link: the handlers are installed on first use.
    def _onboard(self) -> _OnboardState:
        ob: _OnboardState | None = getattr(self, "_onboard_state", None)
        if ob is None:
            ob = self._onboard_state = _OnboardState()
            self._handlers[MSG_PARAM_VALUE] = self._on_param_value
            for msgid in _MISSION_MSGS:
                self._handlers[msgid] = self._on_mission_message
        return ob

    def _on_param_value(self, m: Any, now: float) -> None:
        ob = self._onboard()
        name = m.param_id if isinstance(m.param_id, str) else bytes(m.param_id).decode(
            "ascii", "replace")
        name = name.split("\x00", 1)[0]
        ob.types[name] = int(m.param_type)
        value = _param_from_wire(float(m.param_value), int(m.param_type))
        for fut in ob.param_waiters.pop(name, []):
            if not fut.done():
                fut.set_result(value)

    def _on_mission_message(self, m: Any, now: float) -> None:
        ob = self._onboard()
        if ob.mission_rx is None or getattr(m, "mission_type", 0) != _MISSION_TYPE_FENCE:
            return
        if getattr(m, "target_system", self.gcs_sysid) not in (0, self.gcs_sysid):
            return
        ob.mission_rx.put_nowait(m)

    async def _param_exchange(self, name: str, msg: Any, tries: int, timeout_s: float,
                              what: str) -> float:
        ob = self._onboard()
        loop = asyncio.get_running_loop()
        for _ in range(tries):
            fut: asyncio.Future[float] = loop.create_future()
            ob.param_waiters.setdefault(name, []).append(fut)
            self._send(msg)
            try:
                async with asyncio.timeout(timeout_s):
                    return await fut
            except TimeoutError:
                continue
        raise LinkTimeout(f"{self.name}: no PARAM_VALUE for {name} after {tries} {what} of "
                          f"{timeout_s:.2f} s (PX4 does not answer unknown parameters)")

    async def read_param(self, name: str, tries: int = 3, timeout_s: float = 0.5) -> float:
        """PARAM_REQUEST_READ by name → the PARAM_VALUE's value (INT32 decoded bytewise, as
        PX4 encodes it: capture)."""
        if len(name) > 16:
            raise LinkError(f"{self.name}: parameter names have at most 16 characters: {name!r}")
        msg = self._mav.param_request_read_encode(self._sysid or 0, self.target_compid,
                                                  name.encode("ascii"), -1)
        return await self._param_exchange(name, msg, tries, timeout_s, "requests")

    async def set_param(self, name: str, value: float, tries: int = 3,
                        timeout_s: float = 0.5) -> float:
        """PARAM_SET with the type PX4 reported for ``name`` (read first if unknown); returns
        the echoed value, :class:`LinkError` if PX4 kept another one."""
        ob = self._onboard()
        if name not in ob.types:
            await self.read_param(name)
        ptype = ob.types[name]
        if not math.isfinite(value):
            raise LinkError(f"{self.name}: {name} must be finite, got {value}")
        msg = self._mav.param_set_encode(self._sysid or 0, self.target_compid,
                                         name.encode("ascii"), _param_to_wire(value, ptype),
                                         ptype)
        got = await self._param_exchange(name, msg, tries, timeout_s, "PARAM_SETs")
        want = float(round(value)) if ptype in _PARAM_INT_TYPES else float(value)
        if not math.isclose(got, want, rel_tol=1e-6, abs_tol=1e-6):
            raise LinkError(f"{self.name}: PARAM_SET {name} = {value:g}: the vehicle kept "
                            f"{got:g}")
        return got

    async def _mission_next(self, ob: _OnboardState, timeout_s: float) -> Any | None:
        assert ob.mission_rx is not None
        try:
            async with asyncio.timeout(timeout_s):
                return await ob.mission_rx.get()
        except TimeoutError:
            return None

    async def upload_fence(self, items: list[FenceItem], timeout_s: float = 10.0) -> None:
        """MISSION_COUNT(FENCE) → answer each MISSION_REQUEST(_INT) with its MISSION_ITEM_INT
        (frame GLOBAL_INT) → the final MISSION_ACK; MISSION_COUNT is repeated while no request
        comes (PX4 treats a repeated count at seq 0 as a retry), and the last item while no
        ACK comes after it (PX4 ACKs a repeated last item again: a lost ACK is not a failed
        upload). :class:`FenceRejected` on a non-ACCEPTED ACK, :class:`LinkTimeout` after
        ``timeout_s``."""
        ob = self._onboard()
        loop = asyncio.get_running_loop()
        sysid, comp = self._sysid or 0, self.target_compid
        async with ob.lock:
            ob.mission_rx = asyncio.Queue()
            try:
                deadline = loop.time() + timeout_s
                count_msg = self._mav.mission_count_encode(sysid, comp, len(items),
                                                           _MISSION_TYPE_FENCE)
                self._send(count_msg)
                requested = -1
                last_item: Any = None
                while True:
                    left = deadline - loop.time()
                    if left <= 0:
                        raise LinkTimeout(
                            f"{self.name}: fence upload of {len(items)} items not acknowledged "
                            f"within {timeout_s:g} s (last item requested: {requested})")
                    m = await self._mission_next(ob, min(1.0, left))
                    if m is None:
                        if requested < 0:
                            self._send(count_msg)
                        elif requested == len(items) - 1:  # the ACK may have been lost
                            self._send(last_item)
                        continue
                    msgid = m.get_msgId()
                    if msgid in (MSG_MISSION_REQUEST, MSG_MISSION_REQUEST_INT):
                        seq = int(m.seq)
                        if not 0 <= seq < len(items):
                            continue
                        requested = max(requested, seq)
                        it = items[seq]
                        item_msg = self._mav.mission_item_int_encode(
                            sysid, comp, seq, _FRAME_GLOBAL_INT, int(it.command), 0, 0,
                            float(it.param1), 0.0, 0.0, 0.0, round(it.lat_deg * 1e7),
                            round(it.lon_deg * 1e7), 0.0, _MISSION_TYPE_FENCE)
                        if seq == len(items) - 1:
                            last_item = item_msg
                        self._send(item_msg)
                    elif msgid == MSG_MISSION_ACK:
                        result = _mission_result_name(int(m.type))
                        if int(m.type) != 0:
                            where = (f"after item {requested} of {len(items)}" if requested >= 0
                                     else f"to MISSION_COUNT {len(items)}")
                            raise FenceRejected(
                                f"{self.name}: fence upload refused: MISSION_ACK {result} "
                                f"({where}){self._recent_text(2.0)}", result=result)
                        if requested != len(items) - 1:
                            raise FenceRejected(
                                f"{self.name}: fence upload ACCEPTED after only {requested + 1}"
                                f" of {len(items)} items", result=result)
                        return
            finally:
                ob.mission_rx = None

    async def download_fence(self, tries: int = 6, timeout_s: float = 1.0) -> list[FenceItem]:
        """MISSION_REQUEST_LIST(FENCE) → MISSION_COUNT, MISSION_REQUEST_INT(seq) →
        MISSION_ITEM_INT for each, then MISSION_ACK(ACCEPTED); each request asked up to
        ``tries`` times (with 5 % loss each way an ask or its answer is lost about one time
        in ten: 3 tries fail one ask in a thousand, about one 12-vehicle fence check in
        fourteen; 6 tries one ask in a million)."""
        ob = self._onboard()
        sysid, comp = self._sysid or 0, self.target_compid
        async with ob.lock:
            ob.mission_rx = asyncio.Queue()
            try:
                count = await self._mission_ask(
                    ob, self._mav.mission_request_list_encode(sysid, comp, _MISSION_TYPE_FENCE),
                    MSG_MISSION_COUNT, None, tries, timeout_s, "MISSION_COUNT")
                out: list[FenceItem] = []
                for seq in range(int(count.count)):
                    m = await self._mission_ask(
                        ob, self._mav.mission_request_int_encode(sysid, comp, seq,
                                                                 _MISSION_TYPE_FENCE),
                        MSG_MISSION_ITEM_INT, seq, tries, timeout_s, f"fence item {seq}")
                    out.append(FenceItem(int(m.command), m.x * 1e-7, m.y * 1e-7,
                                         float(m.param1)))
                self._send(self._mav.mission_ack_encode(sysid, comp, 0, _MISSION_TYPE_FENCE))
                return out
            finally:
                ob.mission_rx = None

    async def _mission_ask(self, ob: _OnboardState, msg: Any, want: int, seq: int | None,
                           tries: int, timeout_s: float, what: str) -> Any:
        loop = asyncio.get_running_loop()
        for _ in range(tries):
            self._send(msg)
            end = loop.time() + timeout_s
            while (left := end - loop.time()) > 0:
                m = await self._mission_next(ob, left)
                if m is None:
                    break
                msgid = m.get_msgId()
                if msgid == MSG_MISSION_ACK and int(m.type) != 0:
                    result = _mission_result_name(int(m.type))
                    raise FenceRejected(f"{self.name}: fence download refused while waiting "
                                        f"for {what}: MISSION_ACK {result}", result=result)
                if msgid == want and (seq is None or int(m.seq) == seq):
                    return m
        raise LinkTimeout(f"{self.name}: no {what} after {tries} requests of "
                          f"{timeout_s:.2f} s (fence download)")


MSG_PARAM_VALUE = 22
MSG_MISSION_REQUEST = 40
MSG_MISSION_COUNT = 44
MSG_MISSION_ACK = 47
MSG_MISSION_REQUEST_INT = 51
MSG_MISSION_ITEM_INT = 73
_MISSION_MSGS = (MSG_MISSION_REQUEST, MSG_MISSION_COUNT, MSG_MISSION_ACK,
                 MSG_MISSION_REQUEST_INT, MSG_MISSION_ITEM_INT)
_MISSION_TYPE_FENCE = 1
_FRAME_GLOBAL_INT = 5
_PARAM_INT_TYPES = (1, 2, 3, 4, 5, 6)  # MAV_PARAM_TYPE_UINT8 … INT32: PX4 sends them bytewise
_F32 = struct.Struct("<f")
_I32 = struct.Struct("<i")


class _OnboardState:
    """Per-link state of the parameter and fence exchanges (created on first use)."""

    def __init__(self) -> None:
        self.types: dict[str, int] = {}
        self.param_waiters: dict[str, list[asyncio.Future[float]]] = {}
        self.mission_rx: asyncio.Queue[Any] | None = None
        self.lock = asyncio.Lock()


def _param_from_wire(value: float, ptype: int) -> float:
    """PARAM_VALUE.param_value → the value: integers are the float's bytes (PX4, capture)."""
    if ptype in _PARAM_INT_TYPES:
        return float(_I32.unpack(_F32.pack(value))[0])
    return value


def _param_to_wire(value: float, ptype: int) -> float:
    if ptype in _PARAM_INT_TYPES:
        return _F32.unpack(_I32.pack(int(round(value))))[0]
    return float(value)


def _mission_result_name(result: int) -> str:
    entry = mavlink2.enums["MAV_MISSION_RESULT"].get(result)
    return entry.name.removeprefix("MAV_MISSION_") if entry is not None else str(result)


class _SigningMAVLink(mavlink2.MAVLink):
    """pymavlink's codec with the signature checked *before* the replay window is moved
    (pymavlink 2.4 records a stream's timestamp before comparing the signature, so one forged
    packet with a huge timestamp would make every genuine one "old"), refusals counted."""

    def __init__(self, link: MavlinkLink, *, srcSystem: int, srcComponent: int) -> None:
        super().__init__(None, srcSystem=srcSystem, srcComponent=srcComponent)
        self._link = link
        self._why: str | None = None

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        sg = self.signing
        assert sg.secret_key is not None
        if hashlib.sha256(bytes(sg.secret_key) + bytes(msgbuf[:-6])).digest()[:6] != bytes(
                msgbuf[-6:]):
            self._why = "bad_signature"
            return False
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(bytes(msgbuf[-12:-6]), "little")
        stream = (link_id, srcSystem, srcComponent)
        last = sg.stream_timestamps.get(stream)
        if (timestamp + 6_000_000 < sg.timestamp) if last is None else timestamp <= last:
            self._why = "stale"  # a replay, or a new stream more than a minute old
            return False
        sg.stream_timestamps[stream] = timestamp
        sg.timestamp = max(sg.timestamp, timestamp)
        return True

    def allow_unsigned(self, mav: Any, msgid: int) -> bool:
        """pymavlink asks this for every unsigned or refused packet."""
        why, self._why = self._why or "unsigned", None
        link = self._link
        if msgid in LINK_UNSIGNED_ALLOWED or (
                link.signing is not None and not link.signing.require_signed):
            return True
        link.signing_refused[why] += 1
        return False


def _addr(addr: Any) -> str:
    """``127.0.0.1:14580`` for a UDP address tuple."""
    if isinstance(addr, tuple) and len(addr) >= 2:
        host = addr[0]
        return f"[{host}]:{addr[1]}" if ":" in str(host) else f"{host}:{addr[1]}"
    return str(addr)


def _id_list(ids: Sequence[int]) -> str:
    """``1, 2, 3 and 11`` (the first 12, then ``…``)."""
    text = [str(i) for i in ids[:12]]
    if len(ids) > 12:
        return ", ".join(text) + f" … ({len(ids)} in all)"
    return ", ".join(text[:-1]) + f" and {text[-1]}" if len(text) > 1 else text[0]
