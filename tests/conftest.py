"""Suite-wide settings: MAVLink 2 for pymavlink, and how the suite spreads over pytest-xdist's
workers (``addopts`` in pyproject.toml: ``-n 4 --dist loadgroup``).

Every file is one group (its tests run in order on one worker, as with ``--dist loadfile``:
a file's fixtures and fixed ports are never shared across processes). The flights that load
the two cores most (12 vehicles, 8 agent processes, a rendering viewer) are marked
``heavy`` (:data:`HEAVY`) and run one after another on one worker: two of them at once starve
the flights of CPU, and the runtime then measures link latencies its budget was not built for
and rightly holds the fleet.

A few tests are marked ``solo`` and run while no other test runs on any worker
(:func:`_solo_lock`): the flights that draw a live view in software on these same cores (a
browser, the native viewer: with three other workers' flights beside them their loop stalled
past its budget and was rightly held, about one full run in five), the eight-agent flight
(its agents measured a link too slow for the slots once) and the two tests that bind PX4
SITL's own ports (tests/fleet_ports.PX4_PORTS)."""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")

HEAVY = "heavy"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Give every test without an ``xdist_group`` its file's group (before xdist reads them)."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))


@contextmanager
def _solo_lock(item: pytest.Item) -> Iterator[None]:
    """A readers-writer lock over the workers of one run (two ``flock`` files): every test holds
    it shared, a ``solo`` test exclusively. A solo test first takes the gate, so that no new test
    starts while it waits for the running ones to end (it is never starved)."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:  # one process: nothing runs beside a test
        yield
        return
    base = Path(tempfile.gettempdir()) / f"vtube-fleet-tests-{run}"
    with open(f"{base}.gate", "a") as gate, open(f"{base}.lock", "a") as lock:
        solo = item.get_closest_marker("solo") is not None
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if solo else fcntl.LOCK_SH)
        finally:
            if not solo:
                fcntl.flock(gate, fcntl.LOCK_UN)
        yield  # the files' closing releases both locks


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Each test (setup, call, teardown) inside :func:`_solo_lock`; the wait for it is outside
    the test's timeout."""
    with _solo_lock(item):
        yield
