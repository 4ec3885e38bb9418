"""MQTT topic names of a mission: everything lives under ``vtube/<mission>/``.

==================================  ===  ========  ==========================================
topic                               QoS  retained  payload (``vtube_fleet.bus.codec``)
==================================  ===  ========  ==========================================
``vtube/<m>/state/<cx>/<cy>/<id>``  0    no        binary :class:`NeighbourState` (32 B) at
                                                   the control rate, in spatial cell (cx, cy)
``vtube/<m>/status/<id>``           1    yes       JSON ``online`` (+ hash, run, stage) /
                                                   ``offline`` / ``refused``; will: ``lost``
``vtube/<m>/last/<id>``             0    yes       binary state at ~1 Hz: last seen position
``vtube/<m>/config``                1    yes       JSON run announcement (hash, run, count)
``vtube/<m>/cmd``                   1    yes       JSON fleet command (start / abort)
``vtube/<m>/sync/<client>``         1    no        a client's own in-order delivery marker
``vtube/<m>/clock/ask/<id>``        0    no        JSON clock round trip: the agent's stamp
``vtube/<m>/clock/echo/<id>``       0    no        ... and the coordinator's two stamps added
==================================  ===  ========  ==========================================

The QoS choices are justified in ``docs/mqtt.md``. Vehicle ids are the 0-based fleet slots.
"""

from __future__ import annotations

import re

from vtube_fleet.errors import UserError

__all__ = [
    "ROOT",
    "TopicError",
    "MissionTopics",
    "validate_mission_id",
]

#: First topic level of everything this package publishes.
ROOT = "vtube"

_MISSION_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class TopicError(UserError):
    """A mission id that cannot be used as an MQTT topic level."""


def validate_mission_id(mission_id: str) -> str:
    """Return ``mission_id`` if it is a safe topic level (letters, digits, ``_.-``, ≤ 64)."""
    if not isinstance(mission_id, str) or not _MISSION_ID.match(mission_id):
        raise TopicError(
            f"mission id {mission_id!r} is not usable as an MQTT topic level: use 1-64 letters, "
            "digits, '_', '.' or '-' (no '/', '+', '#', spaces)"
        )
    return mission_id


def _is_int(text: str) -> bool:
    return text.lstrip("-").isdigit()


class MissionTopics:
    """The topic names of one mission (``vtube/<mission>/…``) and their parsers."""

    __slots__ = ("mission_id", "base", "config", "cmd", "_state", "_status", "_last",
                 "_clock_ask", "_clock_echo", "_kinds")

    def __init__(self, mission_id: str) -> None:
        self.mission_id = validate_mission_id(mission_id)
        self.base = f"{ROOT}/{mission_id}"
        self.config = f"{self.base}/config"
        self.cmd = f"{self.base}/cmd"
        self._state = f"{self.base}/state/"
        self._status = f"{self.base}/status/"
        self._last = f"{self.base}/last/"
        self._clock_ask = f"{self.base}/clock/ask/"
        self._clock_echo = f"{self.base}/clock/echo/"
        self._kinds: dict[str, tuple[str, int | None]] = {}  # classify()'s answers

    # -- per-vehicle topics -------------------------------------------------------------------
    def state(self, vehicle_id: int, cell: tuple[int, int] = (0, 0)) -> str:
        """The state topic of a vehicle in spatial cell ``cell`` (see ``docs/mqtt.md``)."""
        return f"{self._state}{int(cell[0])}/{int(cell[1])}/{int(vehicle_id)}"

    def cell_states(self, cell: tuple[int, int]) -> str:
        """Subscription filter: the states of every vehicle in ``cell``."""
        return f"{self._state}{int(cell[0])}/{int(cell[1])}/+"

    def status(self, vehicle_id: int) -> str:
        return f"{self._status}{int(vehicle_id)}"

    def last(self, vehicle_id: int) -> str:
        return f"{self._last}{int(vehicle_id)}"

    def clock_ask(self, vehicle_id: int) -> str:
        """Where an agent sends its clock round trips (the coordinator answers)."""
        return f"{self._clock_ask}{int(vehicle_id)}"

    def clock_echo(self, vehicle_id: int) -> str:
        """Where the coordinator answers an agent's clock round trip."""
        return f"{self._clock_echo}{int(vehicle_id)}"

    # -- subscription filters -------------------------------------------------------------------
    @property
    def all_states(self) -> str:
        return f"{self._state}+/+/+"

    @property
    def all_statuses(self) -> str:
        return f"{self._status}+"

    @property
    def all_clock_asks(self) -> str:
        return f"{self._clock_ask}+"

    # -- parsing --------------------------------------------------------------------------------
    def classify(self, topic: str) -> tuple[str, int | None]:
        """``(kind, vehicle_id)`` of a topic of this mission.

        ``kind`` is ``"state"``, ``"status"``, ``"last"``, ``"clock_ask"``, ``"clock_echo"``
        (with the vehicle id), ``"config"``,
        ``"cmd"`` (id ``None``) or ``"unknown"`` (also for a malformed vehicle id).

        Answers are remembered (the same few hundred topics arrive at the control rate); at
        most :data:`_MAX_KNOWN_TOPICS`, then the memory starts anew.
        """
        known = self._kinds.get(topic)
        if known is None:
            known = self._classify(topic)
            if len(self._kinds) >= _MAX_KNOWN_TOPICS:
                self._kinds.clear()
            self._kinds[topic] = known
        return known

    def _classify(self, topic: str) -> tuple[str, int | None]:
        for kind, prefix in (
            ("state", self._state),
            ("status", self._status),
            ("last", self._last),
            ("clock_ask", self._clock_ask),
            ("clock_echo", self._clock_echo),
        ):
            if topic.startswith(prefix):
                tail = topic[len(prefix) :]
                if kind == "state":
                    parts = tail.split("/")
                    if len(parts) != 3 or not all(_is_int(p) for p in parts[:2]):
                        return "unknown", None
                    tail = parts[2]
                if tail.isdigit():
                    return kind, int(tail)
                return "unknown", None
        if topic == self.config:
            return "config", None
        if topic == self.cmd:
            return "cmd", None
        return "unknown", None


#: Topics whose classification :meth:`MissionTopics.classify` remembers at most.
_MAX_KNOWN_TOPICS = 4096
