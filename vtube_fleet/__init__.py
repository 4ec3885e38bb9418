"""vtube_fleet: fly a PX4 swarm through a trapezoid virtual tube containing obstacles.

The core modules (``tube``, ``barrier``, ``controller``, ``partition``, ``validation``,
``models``, ``neighbours``, ``metrics``) are pure numpy: no I/O, no asyncio, no global state.
Runtime modules (``link``, ``fleet``, ``recording``, ``bus``, ``cli``) are thin layers on top.
"""

__version__ = "0.1.0"
