"""System ids belong to links, not to the fleet (fleets beyond 255 vehicles).

MAVLink system ids are 8-bit. Every vehicle has its own UDP endpoint, so ids need to be unique
only among vehicles that share one: the ``mavlink`` backend keeps one socket per vehicle and
flies vehicles with repeated ids; the ``mavsdk`` backend serves every link from one MAVSDK
server and refuses repeats with one clear line.
"""

from __future__ import annotations

import pytest
from fleet_ports import PX4_PORTS

import sim_stub
from vtube_fleet.link import LinkError, MavlinkLink, fleet_sysid, open_links

pytestmark = pytest.mark.timeout(120)


def test_fleet_sysids_stay_in_1_to_254_and_repeat() -> None:
    ids = [fleet_sysid(i) for i in range(1000)]
    assert ids[:3] == [1, 2, 3] and ids[253] == 254 and ids[254] == 1
    assert min(ids) == 1 and max(ids) == 254  # 0 is broadcast, 255 our own GCS id


async def test_mavsdk_refuses_repeated_ids_with_one_line() -> None:
    eps = ["udpin://127.0.0.1:24540", "udpin://127.0.0.1:24541"]
    with pytest.raises(LinkError) as err:
        async with open_links(eps, "mavsdk", sysids=[7, 7]):
            pass
    msg = str(err.value)
    assert "system id 7" in msg and eps[0] in msg and eps[1] in msg and "\n" not in msg


async def test_out_of_range_id_is_an_error_not_a_traceback() -> None:
    with pytest.raises(LinkError, match=r"system id must be 1\.\.255, got 256"):
        async with open_links(["udpin://127.0.0.1:24542"], "mavlink", sysids=[256]):
            pass


@pytest.mark.xdist_group(PX4_PORTS)  # PX4 SITL's own ports: one at a time, and
@pytest.mark.solo  # nothing else beside it (another test's mock bound 18570 once)
async def test_three_vehicles_with_one_id_on_separate_links() -> None:
    """Three mock vehicles all with sysid 1, each on its own UDP port pair: each link talks to
    its own vehicle only (arming one arms that one)."""
    async with sim_stub.MockFleet(count=3, spacing_m=10.0, sysids=[1, 1, 1],
                                  boot_time_scale=0.1) as fleet:
        async with open_links(list(fleet.endpoints), "mavlink", sysids=[1, 1, 1]) as links:
            for link in links:
                await link.connect(timeout_s=15.0)
                await link.wait_ready(timeout_s=20.0)
            assert all(isinstance(link, MavlinkLink) and link.sysid == 1 for link in links)
            homes = [(round(link.state.home.lat_deg, 6), round(link.state.home.lon_deg, 6))
                     for link in links]
            assert len(set(homes)) == 3  # three different vehicles answered
            for link, vehicle in zip(links, fleet.vehicles, strict=True):
                assert link.state.home is not None
                assert link.state.home.lat_deg == pytest.approx(vehicle.home[0], abs=1e-6)
            await links[1].arm(timeout_s=15.0, retry_interval_s=0.25)
            assert [v.armed for v in fleet.vehicles] == [False, True, False]
