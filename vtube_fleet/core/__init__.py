"""The paper's mathematics, pure numpy (no I/O, no asyncio, no global state; vectorized over
robots): the trapezoid tube and its geometry (:mod:`.tube`), a route of chained tubes
(:mod:`.route`: route → segment → partition → sub-tube), the barrier functions
(:mod:`.barrier`), the controller (:mod:`.controller`) and its parameters (:mod:`.params`),
neighbour search (:mod:`.neighbours`), the obstacle partition and the switching rule
(:mod:`.partition`), the paper's conditions (:mod:`.validation`), robot models (:mod:`.models`)
and the safety metrics, limits and verdict (:mod:`.metrics`).

``tests/test_layers.py`` checks that nothing here imports I/O, concurrency or runtime modules.
"""
