"""Configuration files, parsed strictly once into typed objects: scenarios (``[tube]``,
``[[obstacles]]``, ``[robots]``, ``[controller]``, ``[sim]``; :mod:`.scenario`) and missions
(a scenario plus ``[mission]``; :mod:`.mission`)."""
