"""Suite-wide settings: MAVLink 2 for pymavlink, and how the suite spreads over pytest-xdist's
workers (``addopts`` in pyproject.toml: ``-n 4 --dist loadgroup``).

Every file is one group (its tests run in order on one worker, as with ``--dist loadfile``:
a file's fixtures and fixed ports are never shared across processes). The flights that load
the two cores most (12 vehicles, 8 agent processes, a rendering viewer) are marked
``heavy`` (:data:`HEAVY`) and run one after another on one worker: two of them at once starve
the flights of CPU, and the runtime then measures link latencies its budget was not built for
and rightly holds the fleet."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MAVLINK20", "1")

HEAVY = "heavy"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Give every test without an ``xdist_group`` its file's group (before xdist reads them)."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))
