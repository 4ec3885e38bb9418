"""The fleet: the control tick, pilots and the asyncio supervisor (``vtube-fleet run``).

* :mod:`~vtube_fleet.config.mission`: mission files (a scenario plus ``[mission]``);
* :mod:`~vtube_fleet.fleet.flight_plan`: the flight plan (the planned route: its segments,
  obstacles, flown radii, partitions);
* :mod:`~vtube_fleet.fleet.neighbour_view`: vehicle states as a table, the neighbour view;
* :mod:`~vtube_fleet.fleet.table`: the tick state of the vehicles a process flies;
* :mod:`~vtube_fleet.fleet.tick`: THE control tick (one vehicle or a thousand) and its clock;
* :mod:`~vtube_fleet.fleet.budget`: the safety budget (how much r_s and r_a are inflated);
* :mod:`~vtube_fleet.fleet.compensation`: the estimate-disturbance compensation;
* :mod:`~vtube_fleet.fleet.pilot`: one vehicle's flight procedure over a link;
* :mod:`~vtube_fleet.fleet.preflight`: the stages before arming;
* :mod:`~vtube_fleet.fleet.measure`: the supervisor's in-flight measurement;
* :mod:`~vtube_fleet.fleet.summary`: the supervisor's summary;
* :mod:`~vtube_fleet.fleet.supervisor`: a fleet on one control clock (orchestrates the above);
* :mod:`~vtube_fleet.fleet.launch`: the built-in mock fleet, endpoint lists, :func:`fly`;
* :mod:`~vtube_fleet.fleet.distributed`: one agent process per vehicle, over MQTT;
* :mod:`~vtube_fleet.fleet.view`: the live terminal view.

See ``docs/fleet.md``.
"""

from vtube_fleet.config.mission import Mission, MissionConfig, load_mission
from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.fleet.flight_plan import FlightPlan
from vtube_fleet.fleet.pilot import VehiclePilot
from vtube_fleet.fleet.supervisor import FleetResult, MissionAborted, Supervisor

__all__ = [
    "FleetResult",
    "FlightPlan",
    "Mission",
    "MissionAborted",
    "MissionConfig",
    "SafetyBudget",
    "Supervisor",
    "VehiclePilot",
    "load_mission",
]
