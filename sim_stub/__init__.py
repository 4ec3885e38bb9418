"""sim_stub: a wire-level PX4 SITL stand-in (MAVLink 2 over UDP) for offline tests.

Independent of ``vtube_fleet``. Behaviour is measured from real PX4 SITL (SIH) captures, see
``docs/sim_stub.md``.

    async with MockFleet(count=3) as fleet:   # PX4 ports: vehicle i binds 14580+i -> GCS 14540+i
        print(fleet.endpoints)                 # ['udpin://127.0.0.1:14540', ...]
"""

from __future__ import annotations

from .errors import SimStubError
from .faults import Faults, parse_fault_spec
from .fleet import MockFleet, grid_homes, load_homes
from .ports import PX4, WIDE, PortScheme, resolve_port_scheme
from .processes import MockProcessError, ProcessFleet
from .scheduler import Scheduler
from .telemetry import PROFILES, STREAM_CATALOG
from .vehicle import DEFAULT_HOME, MockVehicle, VehicleCounters

__all__ = [
    "MockVehicle",
    "MockFleet",
    "MockProcessError",
    "ProcessFleet",
    "Faults",
    "PortScheme",
    "PX4",
    "WIDE",
    "Scheduler",
    "SimStubError",
    "VehicleCounters",
    "DEFAULT_HOME",
    "PROFILES",
    "STREAM_CATALOG",
    "grid_homes",
    "load_homes",
    "parse_fault_spec",
    "resolve_port_scheme",
]
