"""The neighbour bus of the distributed agents: MQTT (one agent process per vehicle).

Each agent publishes its own state at the control rate and reads the others' latest
(:class:`~vtube_fleet.bus.mqtt.MqttBus`); a supervisor needs none (its fleet's table holds every
vehicle, :mod:`vtube_fleet.fleet.tick`). Time stamps are wall-clock seconds (``time.time()``) so
that states from other processes or machines can be aged; a state older than the run's maximum
age is never used as if it were fresh (:mod:`vtube_fleet.fleet.neighbour_view`).
"""
