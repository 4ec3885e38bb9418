"""Clocks (issue 34, part 6): every MQTT agent measures its clock offset to the coordinator's
before it joins a run, refuses above the mission's ``max_clock_offset_s``, budgets what is left,
and the summaries hold the offsets.

* the NTP arithmetic and the wire formats (a round trip, the status that carries the result);
* over a real mosquitto (``tests/broker.py``): a coordinator's bus answers, an agent's bus
  whose wall clock is skewed on purpose measures the skew, within half the round trip;
* whole runs, every agent in this process with its own injected wall clock: agents 0.4 s ahead
  and 0.4 s behind refuse before anything connects to a vehicle, with the numbers, and the
  coordinator's start fails naming them; an agent 30 ms ahead flies a mock mission with one
  that is not skewed, its offset in its own summary and in the coordinator's.

No sleeps as synchronisation and no timing asserts: the NTP bound is arithmetic (the true
offset lies within the measured one ± half the round trip, whatever the delays).
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from pathlib import Path

import pytest
from broker import LocalBroker
from fleet_ports import free_ports
from missions import straight_mission, write_mission

from vtube_fleet.bus.codec import (
    ClockMsg,
    ClockOffset,
    Status,
    decode_clock,
    decode_status,
    encode_clock,
    encode_status,
)
from vtube_fleet.bus.mqtt import MqttBus
from vtube_fleet.bus.topics import MissionTopics
from vtube_fleet.bus.validate import MAX_FUTURE_S
from vtube_fleet.config.mission import MAX_CLOCK_OFFSET_S
from vtube_fleet.fleet.distributed.coordinator import (
    Coordinator,
    MissionRunError,
    bus_safety_budget,
    clock_latency_s,
    default_max_age_s,
)
from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess, AgentRefused
from vtube_fleet.fleet.launch import mock_fleet

pytestmark = [pytest.mark.timeout(240)]


def test_the_ntp_arithmetic_and_the_wire_formats() -> None:
    # the agent's clock 0.3 s ahead; 10 ms there, 30 ms back, the coordinator holds it 2 ms
    true = 100.0
    t1 = true + 0.3
    t2 = true + 0.010
    t3 = t2 + 0.002
    t4 = (t3 + 0.030) + 0.3
    c = ClockOffset.from_stamps(t1, t2, t3, t4)
    assert c.delay_s == pytest.approx(0.040)
    assert c.offset_s == pytest.approx(0.3 + 0.010)  # off by half the legs' difference
    assert abs(c.offset_s - 0.3) <= c.delay_s / 2  # NTP's bound
    assert c.bound_s == pytest.approx(0.310 + 0.020)
    assert c.describe() == ("clock offset +310.0 ms to the coordinator's (round trip 40.0 ms, "
                            "best of 1: within 330.0 ms)")
    msg = ClockMsg(3, 7, t1, t2, t3)
    assert decode_clock(encode_clock(msg)) == msg
    st = Status(3, "online", "h", "r", 1.0, "", "joined", ClockOffset(-0.002, 0.004, 8))
    assert decode_status(encode_status(st)) == st
    old = Status(3, "online", "h", "r", 1.0)  # no clock: as before
    assert decode_status(encode_status(old)) == old and b"clock" not in encode_status(old)
    t = MissionTopics("m")
    assert t.classify(t.clock_ask(4)) == ("clock_ask", 4)
    assert t.classify(t.clock_echo(4)) == ("clock_echo", 4)
    # the bound's ceiling: two agents within it of the coordinator are within the bus's
    # future-stamp limit of each other
    assert MAX_CLOCK_OFFSET_S == MAX_FUTURE_S / 2


def test_clocks_in_the_budget(tmp_path: Path) -> None:
    """The coordinator budgets 2 × max_clock_offset_s; an agent its own bound + the bound (never
    more, since an agent above the bound refuses), and L grows by exactly that."""
    m = write_mission(tmp_path, straight_mission(20.0, [[2.0, 3.0], [2.0, -3.0]],
                                                 extra="max_clock_offset_s = 0.05\n"))
    age = default_max_age_s(m)
    assert clock_latency_s(m) == pytest.approx(0.1)
    assert clock_latency_s(m, 0.01) == pytest.approx(0.06)
    run = bus_safety_budget(m, None, age)
    agent = bus_safety_budget(m, None, age, 0.01)
    assert run.latency_s - agent.latency_s == pytest.approx(0.04)
    assert agent.delta_m < run.delta_m


@pytest.fixture
def broker():
    with LocalBroker(kind="mosquitto") as b:  # a real mosquitto (fails without one)
        yield b


@pytest.mark.parametrize("skew_s", [0.0, 0.35, -0.35])
async def test_an_agent_bus_measures_its_skewed_clock(broker, skew_s: float) -> None:
    async with (MqttBus(broker.url, "clk", serve_clock=True) as coord,
                MqttBus(broker.url, "clk", 1, wall_clock=lambda: time.time() + skew_s) as agent):
        await coord.wait_connected(10)
        await agent.wait_connected(10)
        c = await agent.measure_clock(8, 2.0)
    print(f"\nskew {1000 * skew_s:+.0f} ms: {c.describe()}")
    assert c.samples == 8
    assert abs(c.offset_s - skew_s) <= c.delay_s / 2 + 1e-6  # the true offset, within NTP's bound
    assert 0.0 <= c.delay_s


async def test_clock_round_trips_pass_the_secured_brokers_acl(tmp_path: Path) -> None:
    """Through the broker ``vtube-fleet bus-setup`` configures (TLS, passwords, the ACL): the
    coordinator's account answers, each vehicle account measures its own clock; vehicle 1's
    account cannot answer vehicle 0's asks (the coordinator's alone)."""
    from broker import free_port

    from vtube_fleet.bus.security import bus_setup

    setup = bus_setup(tmp_path / "bus", "clk", 2, port=free_port(), bind="127.0.0.1")
    with LocalBroker(config=setup.conf, ca_file=setup.ca_file) as secured:
        async with (MqttBus(secured.url, "clk", 0, credentials=setup.vehicle_credentials(0),
                            wall_clock=_skewed(0.2)) as zero,
                    MqttBus(secured.url, "clk", 1, credentials=setup.vehicle_credentials(1),
                            serve_clock=True) as impostor):
            await zero.wait_connected(10)
            await impostor.wait_connected(10)
            with pytest.raises(TimeoutError):  # vehicle 1's echoes never reach vehicle 0
                await zero.measure_clock(2, 0.5)
            async with MqttBus(secured.url, "clk", credentials=setup.coordinator_credentials,
                               serve_clock=True) as coord:
                await coord.wait_connected(10)
                await coord.sync()
                c = await zero.measure_clock(8, 2.0)
    assert abs(c.offset_s - 0.2) <= c.delay_s / 2 + 1e-6 and c.samples == 8


# ----------------------------------------------------------------------------------------------
# whole runs: coordinator and agents in this process, each agent with its own clock
# ----------------------------------------------------------------------------------------------
def _mission(tmp_path: Path) -> Path:
    write_mission(tmp_path, straight_mission(14.0, [[2.0, 3.0], [2.0, -3.0]],
                                             extra="max_clock_offset_s = 0.1\n"))
    return tmp_path / "mission.toml"


def _skewed(skew_s: float):
    return lambda: time.time() + skew_s


async def test_agents_whose_clocks_are_off_refuse_before_arming(broker, tmp_path: Path) -> None:
    """Vehicle 0's clock 0.4 s ahead, vehicle 1's 0.4 s behind (the run's announcement then
    looks stamped in its future): each refuses to join, with its measured offset, before it
    even connects to its vehicle; the coordinator's start fails naming the refusals."""
    path = _mission(tmp_path)
    said: list[str] = []
    agents = [AgentProcess(path, v, broker=broker.url, join_timeout_s=60,
                           endpoint="udpin://127.0.0.1:1", wall_clock=_skewed(s))
              for v, s in ((0, 0.4), (1, -0.4))]
    tasks = [asyncio.ensure_future(a.run()) for a in agents]
    async with Coordinator(path, broker.url, vehicles=2, say=said.append) as coord:
        with pytest.raises(MissionRunError) as err:
            await coord.start_run(asyncio.Event(), ready_timeout_s=60)
        refused = []
        for t in tasks:
            with pytest.raises(AgentRefused) as agent_err:
                await t
            refused.append(str(agent_err.value))
        assert coord.bus.command is None or coord.bus.command.command != "start"
    print("\n" + str(err.value) + "\n" + "\n".join(refused))
    assert re.match(r"1 agent\(s\) refused run \w+ of mission: vehicle [01]: clock offset ",
                    str(err.value)) or re.match(r"2 agent\(s\) refused", str(err.value))
    for text, skew in zip(refused, (0.4, -0.4), strict=True):
        m = re.search(r"clock offset ([+-]\d+\.\d) ms to the coordinator's \(round trip "
                      r"(\d+\.\d) ms, best of \d: within (\d+\.\d) ms\) > max_clock_offset_s = "
                      r"100 ms: synchronise this machine's clock", text)
        assert m, text
        offset, delay = float(m.group(1)) / 1000, float(m.group(2)) / 1000
        assert abs(offset - skew) <= delay / 2 + 1e-3  # (the numbers are printed to 0.1 ms)
    assert all(a.pilot is None for a in agents)  # never reached their vehicles


async def test_a_slightly_skewed_agent_flies_and_both_summaries_hold_the_offsets(
        broker, tmp_path: Path) -> None:
    """Vehicle 1's clock 30 ms ahead (within the mission's 100 ms): it joins, budgets the rest,
    and the two agents fly the mock mission to the end; each agent's summary holds its own
    offset, the coordinator's holds both."""
    path = _mission(tmp_path)
    from vtube_fleet.config.mission import load_mission

    mission = load_mission(path)
    said: list[str] = []
    async with mock_fleet(mission, 2, boot_time_scale=0.3, port_scheme=free_ports(2)) as fleet:
        agents = [AgentProcess(path, v, broker=broker.url, join_timeout_s=60,
                               endpoint=fleet.endpoints[v], out=tmp_path / f"agent-{v}",
                               wall_clock=_skewed(s))
                  for v, s in ((0, 0.0), (1, 0.03))]
        tasks = [asyncio.ensure_future(a.run()) for a in agents]
        async with Coordinator(path, broker.url, vehicles=2, say=said.append) as coord:
            stop = asyncio.Event()
            assert await coord.start_run(stop, ready_timeout_s=120)
            result = await coord.follow_run(stop, tmp_path / "run", timeout_s=180)
        codes = await asyncio.gather(*tasks)
    print("\n" + "\n".join(line for line in said if line.startswith("clocks")))
    assert codes == [0, 0], (codes, result.reason)
    assert result.outcome == "completed", result.reason
    clocks = result.summary["clocks"]
    assert [c["vehicle"] for c in clocks] == [0, 1]
    for v, skew in ((0, 0.0), (1, 0.03)):
        own = json.loads((tmp_path / f"agent-{v}" / "summary.json").read_text())["clock"]
        print(f"agent {v}: {own}")
        assert own == {k: clocks[v][k] for k in ("offset_s", "delay_s", "within_s", "samples")
                       } | {"max_clock_offset_s": 0.1,
                            "budgeted_s": pytest.approx(own["within_s"] + 0.1)}
        assert abs(own["offset_s"] - skew) <= own["delay_s"] / 2 + 1e-6
        assert own["within_s"] <= 0.1
    assert result.summary["max_clock_offset_s"] == 0.1
    assert any(line.startswith("clocks: vehicle 0 ") for line in said)
