"""The fleet: per-vehicle agents, pilots and the asyncio supervisor (``vtube-fleet run``).

* :mod:`~vtube_fleet.config.mission`: mission files (a scenario plus ``[mission]``);
* :mod:`~vtube_fleet.fleet.agent`: the pure per-vehicle decision logic;
* :mod:`~vtube_fleet.fleet.budget`: the safety budget (how much r_s and r_a are inflated);
* :mod:`~vtube_fleet.fleet.compensation`: the estimate-disturbance compensation;
* :mod:`~vtube_fleet.fleet.launch`: the built-in mock fleet, endpoint lists, :func:`fly`;
* :mod:`~vtube_fleet.fleet.distributed`: one agent process per vehicle, over MQTT;
* :mod:`~vtube_fleet.fleet.pilot`: one vehicle's flight procedure over a link;
* :mod:`~vtube_fleet.fleet.supervisor`: N pilots on one control clock, faults, summary;
* :mod:`~vtube_fleet.fleet.view`: the live terminal view.

See ``docs/fleet.md``.
"""

from vtube_fleet.config.mission import Mission, MissionConfig, load_mission
from vtube_fleet.fleet.agent import Agent, FlightPlan, Setpoint
from vtube_fleet.fleet.budget import SafetyBudget
from vtube_fleet.fleet.pilot import VehiclePilot
from vtube_fleet.fleet.supervisor import FleetResult, MissionAborted, Supervisor

__all__ = [
    "Agent",
    "FleetResult",
    "FlightPlan",
    "Mission",
    "MissionAborted",
    "MissionConfig",
    "SafetyBudget",
    "Setpoint",
    "Supervisor",
    "VehiclePilot",
    "load_mission",
]
