"""Every input bounded (issue 12): the declared keys and options, their bounds, and the bad
inputs a hostile user sent — each refused with ONE ``error:`` line and exit 2 before anything
connects or flies.

* the ``[mission]`` table is declared once (``MISSION_KEYS``): the parser and docs/fleet.md's
  table come from it;
* bounds are physical: ``altitude_m`` within the documented ceiling, ``rate_hz`` within the
  position stream rate both link backends ask the vehicles for, vertical speeds within PX4's
  defaults, timeouts finite and positive, relations between keys;
* every numeric option of ``run``, ``mock-fleet``, ``sitl-homes``, ``agent`` and ``mission`` is
  declared (``cli/_args.py``): NaN, inf, negative or out-of-range values are refused;
* ``run --endpoints ""`` is an error; ``review --out FILE`` is an error, not a traceback;
  ``sitl-homes`` / ``mock-fleet`` refuse overlapping slots and slots outside the tube;
* every scenario key (``SCENARIO_KEYS``: [tube], [[obstacles]], [partition], [robots],
  [controller], [sim]) is declared once too: the parser and docs/config.md's table come from it;
  ``check`` and ``sim`` options are declared (docs/config.md's options table);
* a hypothesis test throws random out-of-bounds values at every declared key and option.
"""

from __future__ import annotations

import argparse
import inspect
import math
import re
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from missions import MISSION_TABLE, NARROWING

from vtube_fleet.cli import build_parser, main
from vtube_fleet.cli._args import OptionType
from vtube_fleet.config.keys import Key
from vtube_fleet.config.mission import (
    MAX_ALTITUDE_M,
    MISSION_KEYS,
    POSITION_STREAM_HZ,
    MissionConfig,
    load_mission,
    mission_keys_table,
)
from vtube_fleet.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper.toml"
ROBOTARIUM = ROOT / "configs" / "robotarium.toml"
#: an endpoint nobody answers on: if a refusal ever failed, the run would time out connecting
#: (and create its output folder), never fly the built-in mock
DEAD_ENDPOINT = "udpin://127.0.0.1:9"
#: the commands of this issue (check / sim have their own tests)
COMMANDS = ("run", "mock-fleet", "sitl-homes", "sitl", "review", "agent", "mission")


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _toml(value: Any) -> str:
    """A TOML value: numbers (nan / inf too), strings, booleans, arrays, an inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):  # a basic string: escape quotes, backslashes, control chars
        return '"' + "".join(
            "\\" + c if c in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F
            else c for c in value) + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    raise TypeError(value)


def mission_text(**mission: Any) -> str:
    """NARROWING + MISSION_TABLE with ``[mission]`` keys set (replaced or added)."""
    table = tomllib.loads(MISSION_TABLE)["mission"]
    table.update(mission)
    return NARROWING + "\n[mission]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in table.items())


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


def run_refused(path: Path, out: Path, capsys: pytest.CaptureFixture[str],
                *extra: str) -> str:
    """``vtube-fleet run`` of ``path`` must exit 2 with one error line, before any output."""
    rc = main(["run", str(path), "--endpoints", DEAD_ENDPOINT, "--out", str(out), "--no-rerun",
               "-q", *extra])
    cap = capsys.readouterr()
    assert rc == 2, cap.err
    assert cap.out == ""
    assert not out.exists(), "the run got as far as its output folder"
    return one_error_line(cap.err)


# ----------------------------------------------------------------------------------------------
# the declared table
# ----------------------------------------------------------------------------------------------
def test_docs_table_is_generated_from_the_declared_keys() -> None:
    text = (ROOT / "docs" / "fleet.md").read_text()
    m = re.search(r"<!-- mission-keys:[^>]*-->\n(.*?)<!-- /mission-keys -->", text, re.S)
    assert m, "docs/fleet.md lost its generated [mission] table"
    assert m.group(1) == mission_keys_table(), (
        "docs/fleet.md's [mission] table differs from MISSION_KEYS: paste "
        "vtube_fleet.config.mission.mission_keys_table()")


def test_docs_options_table_is_generated_from_the_parser() -> None:
    from vtube_fleet.cli._args import options_table

    text = (ROOT / "docs" / "fleet.md").read_text()
    m = re.search(r"<!-- cli-options:[^>]*-->\n(.*?)<!-- /cli-options -->", text, re.S)
    assert m, "docs/fleet.md lost its generated options table"
    want = options_table(build_parser(), tuple(c for c in COMMANDS if c != "review"))
    assert m.group(1) == want, "docs/fleet.md's options table differs: paste options_table()"


def test_help_shows_the_bounds(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["agent", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "seconds to wait for `mission start` (default 600) [s, > 0]" in text


def test_declared_keys_are_the_dataclass() -> None:
    """MISSION_KEYS and MissionConfig name the same keys with the same defaults."""
    import dataclasses

    fields = {f.name: f for f in dataclasses.fields(MissionConfig)}
    assert [k.name for k in MISSION_KEYS] == list(fields)
    for k in MISSION_KEYS:
        f = fields[k.name]
        if k.required:
            assert f.default is dataclasses.MISSING, k.name
        else:
            assert f.default == k.default, k.name
        assert k.meaning and (k.unit or k.kind != "number" or k.name == "accuracy_factor")


def test_rate_bound_is_the_position_stream_the_links_ask_for() -> None:
    from vtube_fleet.link.mavlink import DEFAULT_MESSAGE_RATES_HZ, MSG_LOCAL_POSITION_NED
    from vtube_fleet.link.mavsdk_link import MavsdkLink

    assert DEFAULT_MESSAGE_RATES_HZ[MSG_LOCAL_POSITION_NED] == POSITION_STREAM_HZ
    default = inspect.signature(MavsdkLink.__init__).parameters["position_rate_hz"].default
    assert default == POSITION_STREAM_HZ


# ----------------------------------------------------------------------------------------------
# the bounds of the mission file
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("mission", "pattern"), [
    ({"altitude_m": 1e7}, r"\[mission\]\.altitude_m: must be <= 120 \(the documented ceiling.*"
                          r"GF_MAX_VER_DIST.*\), got 10000000\.0"),
    ({"altitude_m": 120.5}, r"altitude_m: must be <= 120"),
    ({"rate_hz": 1e6}, r"\[mission\]\.rate_hz: must be <= 50 \(the position stream rate the "
                       r"vehicles send: LOCAL_POSITION_NED at 50 Hz\), got 1000000\.0"),
    ({"rate_hz": 50.5}, r"rate_hz: must be <= 50"),
    ({"climb_speed_m_s": 5.0}, r"climb_speed_m_s: must be <= 3 \(PX4's MPC_Z_VEL_MAX_UP"),
    ({"max_vertical_speed_m_s": 2.0}, r"max_vertical_speed_m_s: must be <= 1\.5 \(PX4's "
                                      r"MPC_Z_VEL_MAX_DN"),
    ({"takeoff_timeout_s": math.nan}, r"takeoff_timeout_s: expected a finite number, got nan"),
    ({"mission_timeout_s": -5}, r"mission_timeout_s: must be > 0, got -5"),
    ({"land_timeout_s": math.inf}, r"land_timeout_s: expected a finite number, got inf"),
    ({"connect_timeout_s": 0}, r"connect_timeout_s: must be > 0, got 0"),
    ({"origin_alt_m": 1e5}, r"origin_alt_m: must be <= 9000 \(the Earth's surface"),
    ({"heading_deg": 720.0}, r"heading_deg: must be within \[-360, 360\]"),
    ({"altitude_m": 30.0, "climb_speed_m_s": 0.5},
     r"takeoff_timeout_s: must be at least altitude_m / climb_speed_m_s = 30 / 0\.5 = 60 s"),
    ({"altitude_m": 0.2}, r"altitude_tolerance_m: must be less than altitude_m = 0\.2"),
    ({"altitude_gain_1_s": 30.0}, r"altitude_gain_1_s: must be at most rate_hz = 20"),
])
def test_out_of_bounds_mission_values_are_refused(tmp_path: Path, mission: dict[str, Any],
                                                  pattern: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.toml"
    path.write_text(mission_text(**mission))
    with pytest.raises(ConfigError, match=pattern):
        load_mission(path)
    line = run_refused(path, tmp_path / "out", capsys)
    assert re.search(pattern, line) and "m.toml" in line


def test_v_max_within_px4s_horizontal_limit(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.toml"
    path.write_text(mission_text().replace("v_max = 1.6", "v_max = 15.0"))
    line = run_refused(path, tmp_path / "out", capsys)
    assert "[robots].v_max: must be <= 12 (PX4's MPC_XY_VEL_MAX default" in line
    assert "got 15" in line


def test_the_bounds_themselves_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text(mission_text(altitude_m=MAX_ALTITUDE_M, rate_hz=POSITION_STREAM_HZ,
                                 climb_speed_m_s=3.0, max_vertical_speed_m_s=1.5,
                                 takeoff_timeout_s=MAX_ALTITUDE_M / 3.0))
    c = load_mission(path).config
    assert (c.altitude_m, c.rate_hz) == (MAX_ALTITUDE_M, POSITION_STREAM_HZ)


# ----------------------------------------------------------------------------------------------
# the command-line options
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mission_file() -> Any:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.toml"
        p.write_text(NARROWING + MISSION_TABLE)
        yield p


@pytest.mark.parametrize("argv", [
    ["agent", "{m}", "--vehicle", "0", "--broker-hold-limit", "nan"],
    ["agent", "{m}", "--vehicle", "0", "--broker-hold-limit=-5"],
    ["agent", "{m}", "--vehicle", "0", "--join-timeout", "nan"],
    ["agent", "{m}", "--vehicle=-1"],
    ["mission", "start", "{m}", "--ready-timeout", "nan"],
    ["mission", "start", "{m}", "--broker-timeout=-1"],
    ["mission", "start", "{m}", "--timeout", "inf"],
    ["mission", "start", "{m}", "--max-age", "0"],
    ["mission", "start", "{m}", "--vehicles", "0"],
    ["mission", "status", "{m}", "--listen=-1"],
    ["mission", "abort", "{m}", "--broker-timeout", "nan"],
    ["run", "{m}", "--mock-boot-time-scale", "nan"],
    ["run", "{m}", "--rerun-decimate", "0"],
    ["mock-fleet", "{m}", "--gcs-port", "70000"],
    ["mock-fleet", "{m}", "--count", "0"],
    ["mock-fleet", "{m}", "--boot-time-scale", "inf"],
    ["mock-fleet", "{m}", "--tick-hz", "5"],
    ["sitl-homes", "{m}", "--count=-3"],
])
def test_bad_option_values_are_one_line_errors(argv: list[str], mission_file: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([a.format(m=mission_file) for a in argv])
    assert info.value.code == 2
    cap = capsys.readouterr()
    line = one_error_line(cap.err)
    opt = [a for a in argv if a.startswith("--")][-1].split("=")[0]
    assert opt in line, line


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()
              ) -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """(argv prefix, parser) of every leaf command below ``parser``."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [(prefix, parser)]
    out = []
    for name, p in subs[0].choices.items():
        out += _commands(p, (*prefix, name))
    return out


def _declared_options(commands: tuple[str, ...] = COMMANDS
                      ) -> list[tuple[tuple[str, ...], str, Key]]:
    """(argv prefix, option, key) of every declared numeric option of ``commands``."""
    out = []
    for prefix, p in _commands(build_parser()):
        if prefix[0] not in commands:
            continue
        for a in p._actions:
            if isinstance(a.type, OptionType) and a.option_strings:
                out.append((prefix, a.option_strings[-1], a.type.key))
    return out


#: the scenario commands (the keys of docs/config.md)
SCENARIO_COMMANDS = ("check", "sim")
DECLARED = _declared_options((*COMMANDS, *SCENARIO_COMMANDS))


def test_every_numeric_option_is_declared() -> None:
    """No bare int/float option is left in the commands of this issue; the timeouts are."""
    for prefix, p in _commands(build_parser()):
        if prefix[0] not in (*COMMANDS, *SCENARIO_COMMANDS):
            continue
        for a in p._actions:
            assert a.type not in (int, float), f"{' '.join(prefix)} {a.option_strings}"
    names = {opt for _, opt, _ in DECLARED}
    for opt in ("--broker-hold-limit", "--join-timeout", "--ready-timeout", "--broker-timeout",
                "--timeout", "--max-age", "--listen", "--vehicle", "--vehicles", "--count",
                "--gcs-port", "--mock-boot-time-scale", "--rerun-decimate", "--latency-s",
                "--accuracy-m", "--dt", "--duration", "--robots", "--record-every"):
        assert opt in names, opt


# ----------------------------------------------------------------------------------------------
# the concrete bad inputs of the issue
# ----------------------------------------------------------------------------------------------
def test_empty_endpoints_is_an_error_not_the_mock(tmp_path: Path, mission_file: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    for text in ("", " ", ",", " , "):
        out = tmp_path / "out"
        rc = main(["run", str(mission_file), "--endpoints", text, "--out", str(out),
                   "--no-rerun", "-q"])
        cap = capsys.readouterr()
        assert rc == 2, cap.err
        line = one_error_line(cap.err)
        assert "--endpoints: no endpoint given" in line and "built-in mock" in line
        assert not out.exists()


@pytest.mark.parametrize(("text", "expect"), [
    (f"{DEAD_ENDPOINT},,udpin://127.0.0.1:10", "item 2 of 3 is empty"),
    (f",{DEAD_ENDPOINT}", "item 1 of 2 is empty"),
    (f"{DEAD_ENDPOINT},", "item 2 of 2 is empty"),
    (f"{DEAD_ENDPOINT},{DEAD_ENDPOINT}", f"{DEAD_ENDPOINT} listed twice (slots 0, 1)"),
])
def test_an_empty_or_repeated_endpoint_is_an_error_not_a_slot_shift(
        text: str, expect: str, tmp_path: Path, mission_file: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Endpoint i flies slot i: ``"$A,$B,$C"`` with an empty $B used to drop it silently, and
    C then flew B's slot."""
    out = tmp_path / "out"
    rc = main(["run", str(mission_file), "--endpoints", text, "--out", str(out), "--no-rerun",
               "-q"])
    cap = capsys.readouterr()
    assert rc == 2, cap.err
    assert expect in one_error_line(cap.err)
    assert not out.exists()


def test_review_out_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from vtube_fleet.config.scenario import parse_scenario
    from vtube_fleet.recording.writer import open_recorder
    from vtube_fleet.sim import simulate

    sc = parse_scenario({
        "tube": {"p_h0": [0.0, 0.0], "p_h1": [6.0, 0.0], "p_r0": [0.0, 4.0],
                 "p_r1": [6.0, 4.0]},
        "robots": {"r_s": 0.2, "r_a": 0.6, "v_min": 0.5, "v_max": 3.5,
                   "positions": [[0.8, 2.0]]},
        "controller": {"v": 2.0, "v_max_prime": 1.5},
        "sim": {"dt": 0.01, "duration": 1.0}}, "tiny.toml")
    rrd = tmp_path / "recording.rrd"
    with open_recorder(rrd, kind="sim") as rec:
        simulate(sc, recorder=rec)
    blocker = tmp_path / "hostname"
    blocker.write_text("not a folder\n")
    for out, why in ((blocker, "not a folder"), (blocker / "sub", "cannot make the folder")):
        rc = main(["review", str(rrd), "--out", str(out)])
        cap = capsys.readouterr()
        assert rc == 2 and cap.out == ""
        line = one_error_line(cap.err)
        assert f"--out {out}" in line and why in line
    assert main(["review", str(rrd), "--out", str(tmp_path / "plots")]) == 0  # the control
    assert list((tmp_path / "plots").glob("*.png"))


@pytest.mark.parametrize("where", ["file", "under_file", "proc"])
def test_run_and_sim_refuse_an_unwritable_out_before_anything(
        where: str, tmp_path: Path, mission_file: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """An --out that cannot hold the summary is one error line before anything connects or is
    simulated (found: ``run --out /proc/x --no-rerun`` flew, then logged that summary.json could
    not be written; ``sim --out /proc/x`` simulated, then died with a traceback), and the check
    leaves nothing behind."""
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder\n")
    out = {"file": blocker, "under_file": blocker / "sub" / "deeper",
           "proc": Path("/proc/vtube-fleet-no-such-folder")}[where]
    why = "exists and is not a folder" if where == "file" else "cannot write there"
    for argv in (["run", str(mission_file), "--endpoints", DEAD_ENDPOINT, "--no-rerun", "-q"],
                 ["sim", str(mission_file), "--no-rerun", "--quiet", "--no-plots"]):
        rc = main([*argv, "--out", str(out)])
        cap = capsys.readouterr()
        assert rc == 2, (argv, cap.err)
        err = "\n".join(x for x in cap.err.splitlines() if not x.startswith("note: "))
        line = one_error_line(err)
        assert f"--out {out}: {why}" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
    assert blocker.read_text() == "not a folder\n"


def test_an_out_folder_to_be_made_is_checked_and_left_unmade(
        tmp_path: Path, mission_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The write test of --out makes the missing folders and removes them again (a run refused
    after it leaves no folder behind), and leaves an existing folder as it was."""
    from vtube_fleet.cli._args import check_out_dir

    out = tmp_path / "a" / "b"
    check_out_dir(out)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()
    check_out_dir(tmp_path / "kept")
    assert [p.name for p in tmp_path.iterdir()] == ["kept"]
    assert list((tmp_path / "kept").iterdir()) == []


def _slots_mission(tmp_path: Path, positions: list[list[float]]) -> Path:
    path = tmp_path / "slots.toml"
    path.write_text(NARROWING.replace("positions = [[2.0, 0.0], [2.0, 2.5]]",
                                      f"positions = {positions}") + MISSION_TABLE)
    return path


@pytest.mark.parametrize(("positions", "expect"), [
    ([[2.0, 0.0], [2.3, 0.0]], "slots 0 and 1 overlap: distance 0.3 m ≤ 2 r_s = 0.6 m"),
    ([[2.0, 0.0], [-3.0, 0.0]], "slot 1 at (-3.0, 0.0) is not inside T"),
    ([[2.0, 0.0], [2.0, 4.9]], "slot 1 at (2.0, 4.9) is not inside T"),
])
def test_sitl_homes_and_mock_fleet_refuse_bad_slots(
        tmp_path: Path, positions: list[list[float]], expect: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    path = _slots_mission(tmp_path, positions)
    # (mock-fleet on ports that cannot all open: without the slot check it would fail later,
    # with another message, instead of flying vehicles in those slots)
    for argv in (["sitl-homes", str(path)], ["mock-fleet", str(path), "--gcs-port", "65535"]):
        rc = main(argv)
        cap = capsys.readouterr()
        assert rc == 2 and cap.out == "", (argv, cap)
        line = one_error_line(cap.err)
        assert expect in line and "[robots].positions" in line, line
    # only the slots flown count: slot 0 alone is fine
    if "slot 1" in expect or "slots 0 and 1" in expect:
        assert main(["sitl-homes", str(path), "--count", "1"]) == 0
        assert capsys.readouterr().out.startswith("0 PX4_HOME_LAT=")


# ----------------------------------------------------------------------------------------------
# property: random out-of-bounds values at every declared key and option
# ----------------------------------------------------------------------------------------------
def _bad_values(key: Key) -> st.SearchStrategy[Any]:
    """Values ``key`` must refuse: wrong types, and numbers outside its bound."""
    wrong = [st.text(max_size=8), st.lists(st.integers(0, 9), max_size=3),
             st.just({"a": 1})]
    if key.kind in ("number", "integer"):
        b = key.bound
        assert b is not None
        nums: list[st.SearchStrategy[Any]] = [st.sampled_from([math.nan, math.inf, -math.inf])]
        if b.low is not None:
            nums.append(st.floats(max_value=b.low, allow_nan=False, allow_infinity=False))
        if b.high is not None:
            nums.append(st.floats(min_value=b.high, allow_nan=False, allow_infinity=False))
        out = st.one_of(*nums).filter(lambda x: b.problem(x) is not None)
        return st.one_of(out, st.booleans(), *wrong)
    if key.kind == "choice":
        return st.one_of(st.text(max_size=8).filter(lambda s: s not in key.choices),
                         st.booleans(), st.integers(-5, 5))
    if key.kind == "flag":
        return st.one_of(st.integers(-5, 5), st.text(max_size=5), st.floats(allow_nan=True))
    return st.one_of(st.integers(), st.booleans())


@st.composite
def _bad_mission(draw: st.DrawFn) -> tuple[str, Any]:
    key = draw(st.sampled_from(MISSION_KEYS))
    return key.name, draw(_bad_values(key))


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(bad=_bad_mission())
def test_property_bad_mission_values(bad: tuple[str, Any],
                                     capsys: pytest.CaptureFixture[str]) -> None:
    name, value = bad
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "m.toml"
        path.write_text(mission_text(**{name: value}))
        line = run_refused(path, Path(d) / "out", capsys)
    assert f"[mission].{name}:" in line, line


def _bad_option_text(key: Key) -> st.SearchStrategy[str]:
    b = key.bound
    assert b is not None
    texts: list[st.SearchStrategy[str]] = [
        st.sampled_from(["nan", "inf", "-inf", "", "abc", "1e999", "0x10"])]
    integer = key.kind == "integer"
    if b.low is not None:
        texts.append((st.integers(max_value=int(b.low)) if integer else
                      st.floats(max_value=b.low, allow_nan=False, allow_infinity=False)
                      ).filter(lambda x: b.problem(float(x)) is not None).map(str))
    if b.high is not None:
        texts.append((st.integers(min_value=int(b.high)) if integer else
                      st.floats(min_value=b.high, allow_nan=False, allow_infinity=False)
                      ).filter(lambda x: b.problem(float(x)) is not None).map(str))
    if integer:
        texts.append(st.floats(allow_nan=False, allow_infinity=False)
                     .filter(lambda x: not float(x).is_integer()).map(repr))
    return st.one_of(*texts)


@st.composite
def _bad_option(draw: st.DrawFn) -> tuple[tuple[str, ...], str, str]:
    prefix, opt, key = draw(st.sampled_from(DECLARED))
    return prefix, opt, draw(_bad_option_text(key))


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(bad=_bad_option())
def test_property_bad_option_values(bad: tuple[tuple[str, ...], str, str], mission_file: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    prefix, opt, text = bad
    argv = [*prefix, str(mission_file)]
    if prefix[0] in SCENARIO_COMMANDS:
        argv = [*prefix, str(PAPER)]
    if prefix[0] == "review":
        argv = [*prefix, str(mission_file.with_suffix(".rrd"))]
    if prefix[0] == "agent" and opt != "--vehicle":
        argv += ["--vehicle", "0"]
    argv.append(f"{opt}={text}")
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2, argv
    cap = capsys.readouterr()
    line = one_error_line(cap.err)
    assert opt in line, (argv, line)
    assert cap.out == ""


def test_the_library_refuses_the_same_durations(mission_file: Path) -> None:
    """Called as a library (tests, benchmarks), the agent and the coordinator refuse NaN and
    negative durations as the command line does."""
    from vtube_fleet.errors import UserError
    from vtube_fleet.fleet.distributed.coordinator import Coordinator
    from vtube_fleet.fleet.distributed.vehicle_agent import AgentProcess

    for kw in ({"join_timeout_s": math.nan}, {"broker_hold_limit_s": -5.0}):
        with pytest.raises(UserError, match=r"must be > 0|finite") as info:
            AgentProcess(mission_file, 0, **kw)
        assert info.value.exit_code == 2
    with pytest.raises(UserError, match=r"--broker-timeout: must be > 0, got -1"):
        Coordinator(mission_file, "mqtt://127.0.0.1:1883", broker_timeout_s=-1.0)


# ----------------------------------------------------------------------------------------------
# the scenario file: every key declared once (SCENARIO_KEYS), bounded, and the check/sim options
# ----------------------------------------------------------------------------------------------
def test_config_docs_tables_are_generated() -> None:
    from vtube_fleet.cli._args import options_table
    from vtube_fleet.config.scenario import scenario_keys_table

    text = (ROOT / "docs" / "config.md").read_text()
    m = re.search(r"<!-- scenario-keys:[^>]*-->\n(.*?)<!-- /scenario-keys -->", text, re.S)
    assert m, "docs/config.md lost its generated scenario table"
    assert m.group(1) == scenario_keys_table(), (
        "docs/config.md's scenario table differs from SCENARIO_KEYS: paste "
        "vtube_fleet.config.scenario.scenario_keys_table()")
    m = re.search(r"<!-- check-sim-options:[^>]*-->\n(.*?)<!-- /check-sim-options -->", text,
                  re.S)
    assert m, "docs/config.md lost its generated options table"
    assert m.group(1) == options_table(build_parser(), SCENARIO_COMMANDS), (
        "docs/config.md's options table differs: paste options_table(..., ('check', 'sim'))")


def test_scenario_keys_are_the_parser_and_the_controller_params() -> None:
    """The parser accepts exactly the declared keys; the controller's rows are ControllerParams'
    own names and defaults (core/params.py, not a copy)."""
    from vtube_fleet.config.scenario import SCENARIO_KEYS
    from vtube_fleet.core.params import CONTROLLER_DEFAULTS, CONTROLLER_REQUIRED

    ctrl = SCENARIO_KEYS["controller"]
    assert [k.name for k in ctrl] == [*CONTROLLER_REQUIRED, *CONTROLLER_DEFAULTS]
    for k in ctrl:
        assert k.required == (k.name in CONTROLLER_REQUIRED)
        assert k.default == CONTROLLER_DEFAULTS.get(k.name)
    for section, keys in SCENARIO_KEYS.items():
        for k in keys:
            assert k.meaning, (section, k.name)
            if k.kind in ("number", "point") and k.name not in CONTROLLER_DEFAULTS:
                assert k.unit, (section, k.name)
    for section in ("tube", "partition", "robots", "controller", "sim"):
        data = tomllib.loads(PAPER.read_text())
        data.setdefault(section, {})["surely_not_a_key"] = 1
        with pytest.raises(ConfigError, match=rf"\[{section}\]\.surely_not_a_key: unknown key "
                                              rf"\(allowed: {keys_of(section)}\)"):
            from vtube_fleet.config.scenario import parse_scenario
            parse_scenario(data, "paper.toml")


def keys_of(section: str) -> str:
    from vtube_fleet.config.scenario import SCENARIO_KEYS
    return re.escape(", ".join(k.name for k in SCENARIO_KEYS[section]))


def _scenario_doc(data: dict[str, Any]) -> str:
    """A decoded scenario back as TOML text (tables, one array of tables, inline tables)."""
    out = []
    for name, value in data.items():
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for item in value:
                out.append(f"[[{name}]]\n" + "".join(f"{k} = {_toml(v)}\n"
                                                      for k, v in item.items()))
        elif isinstance(value, dict):
            out.append(f"[{name}]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in value.items()))
        else:
            out.append(f"{name} = {_toml(value)}\n")
    return "\n".join(out)


def scenario_refused(path: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """``check`` and ``sim`` of ``path`` both exit 2 with one error line, print nothing on
    stdout and simulate nothing (no output folder); returns the (same) error line."""
    lines = []
    for argv in (["check", str(path)],
                 ["sim", str(path), "--out", str(out), "--no-rerun", "--quiet", "--no-plots"]):
        rc = main(argv)
        cap = capsys.readouterr()
        assert rc == 2, (argv, cap.err)
        assert cap.out == "", argv
        lines.append(one_error_line(cap.err))
    assert not out.exists(), "sim got as far as its output folder"
    assert lines[0] == lines[1]
    return lines[0]


@pytest.mark.parametrize(("edit", "pattern"), [
    ({"robots.v_max": 15.0}, r"\[robots\]\.v_max: must be <= 12 \(PX4's MPC_XY_VEL_MAX default: "
                             r"faster setpoints are clipped\), got 15\.0"),
    ({"robots.v_min": 13}, r"\[robots\]\.v_min: must be <= 12 \(PX4's MPC_XY_VEL_MAX"),
    ({"controller.v": 20.0}, r"\[controller\]\.v: must be <= 12 \(PX4's MPC_XY_VEL_MAX"),
    ({"controller.k_t": 0.5}, r"\[controller\]: k_t = 0\.5 must be ≥ 1"),
    ({"robots.r_s": 0}, r"\[robots\]\.r_s: must be > 0, got 0"),
    ({"obstacles.0.radius": -1.0}, r"\[\[obstacles\]\]\[0\]\.radius: must be > 0, got -1\.0"),
    ({"obstacles.0.apex_distance": "far"},
     r'\[\[obstacles\]\]\[0\]\.apex_distance: expected a number or "auto", got "far"'),
    ({"sim.dt": 1e-9}, r"\[sim\]\.dt: must be >= 1e-06, got 1e-09"),
    ({"sim.dt": 2.0}, r"\[sim\]\.dt: must be <= 1 \(a second: .*\), got 2\.0"),
    ({"sim.dt": 1e-6, "sim.duration": 1000.0},
     r"\[sim\]\.dt: duration / dt must be <= 1e\+08 steps, got 1000 / 1e-06 = 1e\+09"),
    ({"sim.duration": math.inf}, r"\[sim\]\.duration: expected a finite number, got inf"),
    ({"sim.duration": 1e6}, r"\[sim\]\.duration: must be <= 86400 \(a day"),
    ({"robots.grid.rows": 10**9}, r"\[robots\]\.grid\.rows: must be <= 10000 \(the documented "
                                  r"ceiling of the swarm\), got 1000000000"),
    ({"robots.grid.rows": 200, "robots.grid.cols": 200},
     r"\[robots\]\.grid\.cols: rows × cols must be <= 10000 .*got 200 × 200"),
    ({"partition.apex_distance": 1.5},
     r'\[partition\]\.apex_distance: expected one of "auto", "default", got 1\.5'),
    ({"sim.integrator": "leapfrog"}, r'\[sim\]\.integrator: expected one of "adaptive"'),
])
def test_out_of_bounds_scenario_values_are_refused(tmp_path: Path, edit: dict[str, Any],
                                                   pattern: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    data = tomllib.loads(PAPER.read_text())
    for dotted, value in edit.items():
        _put(data, dotted, value)
    path = tmp_path / "s.toml"
    path.write_text(_scenario_doc(data))
    line = scenario_refused(path, tmp_path / "out", capsys)
    assert re.search(pattern, line), line
    assert str(path) in line


def _put(data: dict[str, Any], dotted: str, value: Any) -> None:
    *parents, last = dotted.split(".")
    d: Any = data
    for k in parents:
        d = d[int(k)] if isinstance(d, list) else d.setdefault(k, {})
    d[last] = value


def test_too_many_positions_are_refused(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from vtube_fleet.config.scenario import MAX_ROBOTS

    data = tomllib.loads(ROBOTARIUM.read_text())
    data["robots"]["positions"] = [[0.0, 0.0]] * (MAX_ROBOTS + 1)
    data["robots"].pop("headings", None)
    path = tmp_path / "s.toml"
    path.write_text(_scenario_doc(data))
    line = scenario_refused(path, tmp_path / "out", capsys)
    assert f"[robots].positions: at most {MAX_ROBOTS} robots" in line and "got 10001" in line


def test_the_scenario_bounds_themselves_are_accepted() -> None:
    from vtube_fleet.config.scenario import PX4_MAX_HORIZONTAL_M_S, parse_scenario

    data = tomllib.loads(PAPER.read_text())
    data["robots"]["v_max"] = PX4_MAX_HORIZONTAL_M_S
    data["sim"] = {"dt": 1.0, "duration": 86400.0}
    sc = parse_scenario(data, "paper.toml")
    assert sc.robots.v_max == 12.0 and (sc.sim.dt, sc.sim.duration) == (1.0, 86400.0)
    data["sim"] = {"dt": 1e-6, "duration": 100.0}  # 1e8 steps: the ceiling itself
    assert parse_scenario(data, "paper.toml").sim.dt == 1e-6


def test_check_and_sim_help_show_the_bounds(capsys: pytest.CaptureFixture[str]) -> None:
    for cmd, want in (("sim", "time step in seconds (default: [sim].dt of the config) "
                              "[s, [1e-06, 1]]"),
                      ("check", "(default 0.3: what PX4 SITL reports; RTK: ~0.02) [m, [0, 100]]")):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        assert want in " ".join(capsys.readouterr().out.split())


# the base document of each key: the paper (grid, obstacles), the Robotarium (unicycles with
# positions and headings)
_UNICYCLE_KEYS = {"nid_distance", "headings", "positions"}


def _where(section: str, name: str) -> str:
    if section == "obstacles":
        return f"[[obstacles]][0].{name}"
    if section == "robots.grid":
        return f"[robots].grid.{name}"
    if section == "route.waypoints":
        return f"[[route.waypoints]][0].{name}"
    return f"[{section}].{name}"


def _bad_scenario_value(section: str, key: Key) -> st.SearchStrategy[Any]:
    """Values the scenario key must refuse."""
    from vtube_fleet.core.params import parameter_problems

    wrong = st.one_of(st.text(max_size=6), st.booleans(), st.just({"a": 1}))
    if key.kind == "point":
        return st.one_of(
            wrong, st.floats(allow_nan=True),
            st.lists(st.floats(allow_nan=True), max_size=4).filter(
                lambda v: len(v) != 2 or not all(math.isfinite(x) for x in v)),
            st.lists(st.text(max_size=2), min_size=2, max_size=2))
    if key.kind == "other":
        if key.name == "grid":
            return st.one_of(st.text(max_size=6), st.integers(-5, 5), st.just({}),
                             st.lists(st.integers(0, 9), max_size=3),
                             st.just({"origin": [0.0, 0.0], "rows": 2}))
        if key.name == "positions":
            return st.one_of(wrong.filter(lambda v: not isinstance(v, dict)), st.just([]),
                             st.lists(st.text(max_size=2), min_size=1, max_size=3),
                             st.just([[math.nan, 0.0]]), st.just([[0.0]]))
        if key.name == "waypoints":  # (a route: docs/route.md)
            return st.one_of(st.text(max_size=6), st.integers(-5, 5), st.just({}),
                             st.just([]), st.lists(st.integers(0, 9), min_size=1, max_size=3),
                             st.just([{"position": [0.0, 0.0], "half_width": 1.0}]))
        if key.name == "lat_lon":  # (a scenario has no [mission] anchor: refused whatever)
            return st.one_of(wrong, st.lists(st.floats(allow_nan=True), max_size=3),
                             st.just([91.0, 0.0]), st.just([47.0, 8.0]))
        assert key.name == "headings", key.name
        return st.one_of(st.text(max_size=6), st.booleans(), st.just({"a": 1}),
                         st.sampled_from([math.nan, math.inf, -math.inf]),
                         st.lists(st.floats(allow_nan=False), max_size=3),
                         st.just([math.nan] * 7))
    if key.kind == "integer":
        b = key.bound
        assert b is not None
        ints = []
        if b.low is not None:
            ints.append(st.integers(-2**63, int(b.low) - (1 if b.low_inclusive else 0)))
        if b.high is not None:
            ints.append(st.integers(int(b.high) + 1, 2**63 - 1))
        return st.one_of(*ints, st.floats(allow_nan=True), wrong)
    base = _bad_values(key)
    if section == "controller":  # also the ControllerParams domain (k_t >= 1, ε's <= 1 …)
        domain = st.floats(1e-300, 12.0).filter(lambda x: bool(parameter_problems({key.name: x})))
        return st.one_of(base, domain) if key.name in ("k_t", "eps_m", "eps_t", "eps_s",
                                                       "eps_o") else base
    return base


def _scenario_cases() -> list[tuple[str, Key]]:
    from vtube_fleet.config.scenario import SCENARIO_KEYS

    return [(section, k) for section, keys in SCENARIO_KEYS.items() for k in keys]


@st.composite
def _bad_scenario(draw: st.DrawFn) -> tuple[str, str, Any]:
    section, key = draw(st.sampled_from(_scenario_cases()))
    return section, key.name, draw(_bad_scenario_value(section, key))


_BASES = {"paper": tomllib.loads(PAPER.read_text()),
          "robotarium": tomllib.loads(ROBOTARIUM.read_text()),
          # a route (its [mission] table left out: a scenario)
          "route": {k: v for k, v in tomllib.loads(
              (ROOT / "configs" / "route_mock.toml").read_text()).items() if k != "mission"}}


def test_the_bases_of_the_property_test_are_valid(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The control: without the bad value, both documents (as the property test writes them,
    with an obstacle and [partition]) check fine."""
    for name, data in _BASES.items():
        path = tmp_path / f"{name}.toml"
        doc = {**data, "partition": {"apex_distance": "default"}}
        path.write_text(_scenario_doc(doc))
        assert main(["check", str(path), "--no-fixes"]) == 0, capsys.readouterr()
        capsys.readouterr()


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(bad=_bad_scenario())
def test_property_bad_scenario_values(bad: tuple[str, str, Any],
                                      capsys: pytest.CaptureFixture[str]) -> None:
    import copy

    section, name, value = bad
    base = "robotarium" if (section == "robots" and name in _UNICYCLE_KEYS) else (
        "route" if section.startswith("route") else "paper")
    data = copy.deepcopy(_BASES[base])
    data["partition"] = {"apex_distance": "default"}
    if section == "obstacles":
        data["obstacles"][0][name] = value
    elif section == "route.waypoints":
        wp = data["route"]["waypoints"][0]
        if name == "lat_lon":
            del wp["position"]
        wp[name] = value
    elif section == "robots.grid":
        data["robots"]["grid"][name] = value
    else:
        data.setdefault(section, {})[name] = value
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.toml"
        path.write_text(_scenario_doc(data))
        line = scenario_refused(path, Path(d) / "out", capsys)
    if section == "controller":
        assert "[controller]" in line and name in line, line
    else:
        assert _where(section, name) in line, line
