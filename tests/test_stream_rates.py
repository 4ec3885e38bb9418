"""PX4's streams: a fleet's links switch off what the fleet does not use and give PX4 its own
rates back at the end, on every path (issue 34): the supervisor's run (completed, or stopped
early), and one agent's link, opened as `vtube-fleet agent` opens it. Judged on the mock
vehicle's own stream table (what it sends, not what we asked)."""

from __future__ import annotations

from pathlib import Path

import pytest
from fleet_ports import free_ports
from missions import straight_mission

from vtube_fleet.config.mission import load_mission
from vtube_fleet.fleet.launch import fly, mock_fleet
from vtube_fleet.fleet.supervisor import Supervisor
from vtube_fleet.link import TelemetryBounds, open_links
from vtube_fleet.link.mavlink import UNUSED_STREAMS_OFF

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

#: the mock's names of the streams the fleet switches off, and of the one it speeds up
OFF = ("ATTITUDE", "ATTITUDE_QUATERNION", "HIGHRES_IMU", "ODOMETRY", "POSITION_TARGET_LOCAL_NED")
FAST = "LOCAL_POSITION_NED"


def _intervals(vehicle) -> dict[str, tuple[float, float]]:
    """(interval now, PX4's default interval) of the streams the fleet changes."""
    return {name: (vehicle._streams[name].interval, vehicle._streams[name].default_interval)
            for name in (*OFF, FAST)}


def test_the_names_are_the_streams_switched_off() -> None:
    from sim_stub.telemetry import STREAM_BY_ID

    assert sorted(STREAM_BY_ID[m].name for m in UNUSED_STREAMS_OFF) == sorted(OFF)


@pytest.mark.parametrize("stop_at", [None, "preflight"], ids=["completed", "interrupted"])
async def test_a_run_trims_the_streams_and_gives_them_back(tmp_path: Path,
                                                           stop_at: str | None) -> None:
    path = tmp_path / "m.toml"
    path.write_text(straight_mission(12.0, [[2.0, 3.0], [2.0, -3.0]], heading_deg=90.0))
    mission = load_mission(path)
    seen: dict[str, dict] = {}
    async with mock_fleet(mission, boot_time_scale=0.3, port_scheme=free_ports(2),
                          seed=3) as fleet:
        def hook(tick: int, sup: Supervisor):
            if sup.stage in ("preflight", "tube") and sup.stage not in seen:
                seen[sup.stage] = _intervals(fleet.vehicles[0])
            if stop_at is not None and sup.stage == stop_at and sup._interrupted is None:
                sup.interrupt("test")

        result = await fly(mission, endpoints=fleet.endpoints, out_dir=tmp_path, tick_hook=hook)
        after = [_intervals(v) for v in fleet.vehicles]
    during = seen["tube" if stop_at is None else "preflight"]
    assert all(during[name][0] == 0.0 for name in OFF), during  # switched off
    assert during[FAST][0] == pytest.approx(1 / 50)
    for v in after:  # PX4's own rates again
        assert all(now == default for now, default in v.values()), v
    assert result.outcome == ("completed" if stop_at is None else "interrupted"), result.reason


async def test_one_agents_link_trims_and_restores_like_run() -> None:
    """`vtube-fleet agent` opens its one link with open_links (the registry's defaults): the
    same streams off, PX4's rates back when it closes."""
    mission = load_mission(Path(__file__).resolve().parents[1] / "configs" / "px4_sitl_3.toml")
    async with mock_fleet(mission, 1, boot_time_scale=0.3, port_scheme=free_ports(1),
                          seed=4) as fleet:
        v = fleet.vehicles[0]
        async with open_links(fleet.endpoints, "mavlink", sysids=[1],
                              telemetry=TelemetryBounds.for_mission(mission)) as links:
            await links[0].connect(10.0)
            during = _intervals(v)
        after = _intervals(v)
    assert all(during[name][0] == 0.0 for name in OFF), during
    assert all(now == default for now, default in after.values()), after


async def test_a_fleet_says_once_which_vehicles_kept_our_rates(caplog) -> None:
    """With many vehicles, the streams some did not confirm at close are one line for the
    fleet (naming the vehicles and the streams), not one warning per vehicle."""
    import logging
    from types import SimpleNamespace

    class Link:
        def __init__(self, left: list[int]) -> None:
            self.warn_unrestored, self._left, self.unrestored_streams = True, left, []

        async def close(self) -> None:
            assert self.warn_unrestored is False  # the fleet says it, not each link
            self.unrestored_streams = self._left

        @property
        def unrestored_names(self) -> list[str]:
            return [f"MSG{m}" for m in self.unrestored_streams]

    pilots = [SimpleNamespace(vehicle_id=i, link=Link([30, 31] if i % 2 else []))
              for i in range(30)]
    with caplog.at_level(logging.WARNING):
        await Supervisor._close_links(SimpleNamespace(pilots=pilots))
    lines = [r.getMessage() for r in caplog.records if "not confirmed" in r.getMessage()]
    assert len(lines) == 1, lines
    assert "by 15 of 30 vehicle(s) (1, 3, 5," in lines[0] and "(15 in all)" in lines[0]
    assert "MSG30, MSG31" in lines[0]
