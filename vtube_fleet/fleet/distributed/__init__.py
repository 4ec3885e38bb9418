"""The distributed fleet: one agent process per vehicle, neighbours over MQTT.

:mod:`.vehicle_agent` flies one vehicle, :mod:`.coordinator` announces, starts, aborts and follows a
run, and :mod:`.monitor` folds the published states into a summary for both.
"""
