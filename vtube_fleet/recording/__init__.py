"""Recording a run to rerun (.rrd) and reading it back for ``vtube-fleet review``.

Both the simulator (``vtube-fleet sim``) and the fleet (``vtube-fleet run`` / ``agent``) record
through the same small :class:`Recorder` interface:

* :meth:`Recorder.log_scene` — once, static: the main tube, the obstacles O_k (obstacle) with
  their extended areas O'_k (radius r_o + r_s), the sub-tubes T_o,k and circumscribed triangles
  I_k of the partition (ObstacleController), and the scenario metadata ``review`` needs (tube
  points, obstacles, r_s, r_a, v_min, v_max, ε_0, robot count and ids, dt, decimation, run kind)
  as a JSON :class:`rerun.TextDocument` at ``meta/scenario``.
* :meth:`Recorder.log_tick` — every control tick / simulation frame: positions, velocities,
  optional phases and commands of ALL vehicles as arrays, the safety metrics of the tick, and
  optionally the exact inputs of the run's safety metrics (``safety=``).
* :meth:`Recorder.log_metrics` (per-step metric series in bulk, the simulator),
  :meth:`Recorder.log_exits`, :meth:`Recorder.log_partition`, :meth:`Recorder.log_event`,
  :meth:`Recorder.log_summary`.

Cost on the control loop (see ``bench/bench_recording.py`` and ``docs/recording.md``): a call
that is not recorded (decimation) only copies its arrays, updates the metric extrema and the
exit detection; a recorded call appends the copies to a buffer. Every ``batch_ticks`` recorded
ticks (or ``max_delay_s`` of wall time, whichever comes first) a sender thread sends the buffer
as ONE :meth:`rerun.RecordingStream.send_columns` call per entity with explicit
``mission_time`` / ``tick`` time columns — never one call per vehicle, and no reliance on
rerun's per-thread ``set_time`` state (shared by every coroutine of an asyncio loop). Each
recorder owns its own :class:`rerun.RecordingStream` (no global rerun state), so several
recorders can live in one process. Nothing touches the file system before the first thing is
recorded.

Decimation keeps the extremes: a recorded tick carries the minimum of every ``min_*`` metric and
the maximum of every ``max_*`` metric, of ``tick_duration_s`` and of ``link_latency_s`` over the
ticks since the previous recorded one. The last call before :meth:`close` is always recorded.

Exits (Assumption 2, (TraCondition)) are detected at every call, decimated or not: a vehicle
whose phase becomes ``exited``, or — when no phases are given (the simulator) — a vehicle present
at the previous call whose row is now NaN or missing. They are logged at ``events/exits`` with
the exact time, so ``review`` recovers the exit times the run itself saw.

Layout of a recording (entity paths):

======================  =========================================================
``meta/scenario``       static JSON (:data:`META_FORMAT`), read by :func:`load_recording`
``meta/summary``        static JSON: the run's own ``summary.json`` (:meth:`log_summary`)
``world``               the tube frame, no transform (the 2-D view draws y downwards); static
                        AnnotationContext: one class per phase (``layout.PHASE_CLASSES``)
``world/axes``          static: the +x / +y axis key; ``world/legend``: the phase colour key
``world/tube``          static: the main tube T (closed line strip)
``world/obstacles``     static: O_k as discs; ``world/obstacles/extended``: O'_k outlines
``world/sub_tubes``     sub-tubes T_o,k (at t = 0, again at each :meth:`log_partition`)
``world/triangles``     circumscribed triangles I_k (same)
``world/vehicles``      the exact float64 state of the fleet per tick as
                        ``vtube_fleet.VehicleState:*`` components (what ``review`` reads)
``world/vehicles/ID``  one entity per vehicle, drawn: a point (radius r_s, phase class), its
                        velocity arrow (``arrow_scale_s`` × v) and its trail (the last few
                        seconds of its path); cleared when the vehicle leaves the rows
``world/vehicles/ID``   (with a geodetic anchor) also ``GeoPoints`` and a ``GeoLineStrings`` trail:
                        the vehicle on the map
``map/*``               static ``GeoLineStrings`` (WGS84): tube outline, obstacles, the uploaded
                        fence, the start slots (:mod:`vtube_fleet.recording.geo`)
``world/commands``      Arrows2D of the velocity command, when given
``safety/main|center``  the exact (position, velocity) inputs of the run's safety metrics per
                        summary stream, when given (``log_tick(safety=...)``)
``metrics/<key>``       Scalars, one entity per metric key; ``limits/<key>`` the safety limit
``status``              TextDocument: a table of every vehicle (id, phase, position, speed)
``events``              TextLog of run-wide events; ``events/vehicles``: per-vehicle events
                        (phase changes — once, also when the owner tells them —, :meth:`log_event`
                        with a vehicle id; the id also as ``vtube_fleet.Event:vehicle_id``);
                        ``events/exits``: exit times (text only when no phase change told it)
======================  =========================================================

Live viewing (:mod:`vtube_fleet.recording.live`): ``serve_web=PORT`` serves the rerun web viewer
(page on PORT, data on PORT + 1, bound to ``serve_bind``), ``viewer=True`` spawns the native
viewer; both are more sinks of the same stream, fed by the same sender thread.

Timelines: ``mission_time`` (duration, seconds since the mission/simulation start) and ``tick``
(the control tick / simulation step counter).
"""

from vtube_fleet.recording.api import NullRecorder, Recorder, RecordingError
from vtube_fleet.recording.layout import (
    DEFAULT_CONNECT_URL,
    DEFAULT_RECORDING_NAME,
    META_FORMAT,
    SIM_MIN_PERIOD_S,
    TIMELINE_TICK,
    TIMELINE_TIME,
)
from vtube_fleet.recording.reader import RecordingData, load_recording
from vtube_fleet.recording.writer import (
    RerunRecorder,
    default_blueprint,
    normalize_connect_url,
    open_recorder,
)

__all__ = [
    "DEFAULT_CONNECT_URL",
    "DEFAULT_RECORDING_NAME",
    "META_FORMAT",
    "SIM_MIN_PERIOD_S",
    "TIMELINE_TICK",
    "TIMELINE_TIME",
    "NullRecorder",
    "Recorder",
    "RecordingData",
    "RecordingError",
    "RerunRecorder",
    "default_blueprint",
    "load_recording",
    "normalize_connect_url",
    "open_recorder",
]
