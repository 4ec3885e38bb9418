"""The layers of the package, enforced on the source (docs/architecture.md).

* ``vtube_fleet.core`` is the paper's math: pure numpy, no I/O, no concurrency, no transports;
* nothing outside ``vtube_fleet.cli`` imports from ``vtube_fleet.cli``;
* ``sim_stub`` (the mock PX4) does not import ``vtube_fleet``, and ``vtube_fleet`` starts
  ``sim_stub`` only where it starts the built-in mock fleet (``fleet/launch.py``): neither by
  importing it nor by running it as a process (``python -m sim_stub``: a string naming the
  module to run). The SITL launcher (``fleet/sitl.py``) starts whatever command it is given;
  the tests give it ``python -m sim_stub``, the library never does.

Every import statement counts, also those inside functions and ``TYPE_CHECKING`` blocks.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vtube_fleet"
SIM_STUB = ROOT / "sim_stub"

#: Modules the core must never import (top-level package names).
CORE_FORBIDDEN = {
    "asyncio", "socket", "threading", "subprocess", "pathlib", "os", "rerun", "pymavlink",
    "mavsdk", "paho", "aiomqtt", "matplotlib", "sim_stub", "signal", "multiprocessing",
}

#: Where vtube_fleet may import sim_stub: the launcher of the built-in mock fleet.
SIM_STUB_IMPORTERS = {"vtube_fleet/fleet/launch.py"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _imports(path: Path, module: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute dotted module) of every import statement in ``path`` (whose dotted
    name is ``module``, by default from its place in the repository)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module or _module_name(path)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            # `from vtube_fleet import cli` imports the cli package too
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names if mod]
    return out


def _files(top: Path) -> list[Path]:
    return sorted(p for p in top.rglob("*.py") if "__pycache__" not in p.parts)


def _rel(p: Path) -> str:
    return p.relative_to(ROOT).as_posix()


def test_the_layout_shows_the_layers() -> None:
    for sub in ("core", "config", "link", "bus", "fleet", "fleet/distributed", "recording", "cli"):
        assert (PACKAGE / sub / "__init__.py").is_file(), sub
    assert (PACKAGE / "state.py").is_file() and (PACKAGE / "artifacts.py").is_file()


@pytest.mark.parametrize("path", _files(PACKAGE / "core"), ids=_rel)
def test_core_is_pure(path: Path) -> None:
    bad = [f"{_rel(path)}:{line} imports {mod}" for line, mod in _imports(path)
           if mod.split(".")[0] in CORE_FORBIDDEN
           or (mod.startswith("vtube_fleet.") and not mod.startswith(
               ("vtube_fleet.core", "vtube_fleet.errors")))]
    assert not bad, "\n".join(bad)


#: docs/architecture.md's layer table below the runtime: what each may import of vtube_fleet
#: (besides itself). The runtime layers (link, bus, recording, fleet, sim, check) may import
#: these; only the cli imports the cli (test below).
BELOW_RUNTIME: dict[str, set[str]] = {
    "errors": set(), "outcome": set(), "state": set(),
    "frames": {"errors"},
    "config": {"core", "errors", "frames"},
    "plots": {"core"},
    "artifacts": {"plots"},
}
#: The runtime layers that may not import each other (fleet and check sit above them).
RUNTIME_BASE: dict[str, set[str]] = {
    "bus": {"errors", "state"},
    "link": {"config", "errors"},
    "recording": {"artifacts", "config", "core", "errors", "plots"},
    "sim": {"config", "core", "errors"},
}


@pytest.mark.parametrize("layer", sorted(BELOW_RUNTIME | RUNTIME_BASE))
def test_the_layer_table_holds(layer: str) -> None:
    allowed = (BELOW_RUNTIME | RUNTIME_BASE)[layer] | {layer}
    top = PACKAGE / layer
    paths = _files(top) if top.is_dir() else [PACKAGE / f"{layer}.py"]
    bad = [f"{_rel(path)}:{line} imports {mod}" for path in paths
           for line, mod in _imports(path)
           if mod.startswith("vtube_fleet.") and mod.split(".")[1] not in allowed]
    assert not bad, "\n".join(bad)


def test_only_cli_imports_cli() -> None:
    bad = []
    for path in _files(PACKAGE):
        if _rel(path).startswith("vtube_fleet/cli/") or path == PACKAGE / "__main__.py":
            continue
        bad += [f"{_rel(path)}:{line} imports {mod}" for line, mod in _imports(path)
                if mod == "vtube_fleet.cli" or mod.startswith("vtube_fleet.cli.")]
    assert not bad, "\n".join(bad)


def test_commands_do_not_import_each_other() -> None:
    bad = []
    for path in _files(PACKAGE / "cli"):
        me = _module_name(path)
        for line, mod in _imports(path):
            if (mod.startswith("vtube_fleet.cli.") and mod != me
                    and not mod.split(".")[2].startswith("_")
                    and path.name != "__init__.py"):
                bad.append(f"{_rel(path)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


def test_sim_stub_stands_alone() -> None:
    bad = []
    for path in _files(SIM_STUB):
        bad += [f"{_rel(path)}:{line} imports {mod}" for line, mod in _imports(path)
                if mod.split(".")[0] == "vtube_fleet"]
    assert not bad, "\n".join(bad)


def test_only_the_launcher_starts_the_mock() -> None:
    bad = []
    for path in _files(PACKAGE):
        if _rel(path) in SIM_STUB_IMPORTERS:
            continue
        bad += [f"{_rel(path)}:{line} imports {mod}" for line, mod in _imports(path)
                if mod.split(".")[0] == "sim_stub"]
    assert not bad, "\n".join(bad)


def _runs_sim_stub(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every string in ``path`` that names sim_stub as a module to run
    (``"sim_stub"`` alone, as an argv item, or ``-m sim_stub`` in a command line); docstrings
    do not count."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant):
            docs.add(id(body[0].value))
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and id(node) not in docs
            and (node.value.strip() == "sim_stub"
                 or re.search(r"-m\s+sim_stub\b", node.value))]


def test_only_the_launcher_runs_the_mock_as_a_process() -> None:
    bad = [f"{_rel(path)}:{line} runs {text!r}" for path in _files(PACKAGE)
           if _rel(path) not in SIM_STUB_IMPORTERS for line, text in _runs_sim_stub(path)]
    assert not bad, "\n".join(bad)


def test_the_process_rule_sees_a_command_line(tmp_path: Path) -> None:
    f = tmp_path / "probe.py"
    f.write_text('"""Starts python -m sim_stub (a docstring: fine)."""\n'
                 'ARGV = [sys.executable, "-m", "sim_stub", "--count", "2"]\n'
                 'CMD = f"{sys.executable} -m sim_stub --first {i}"\n'
                 'HELP = "the sim_stub mock"\n')
    assert [line for line, _ in _runs_sim_stub(f)] == [2, 3]


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    """The import walker finds relative, nested and TYPE_CHECKING imports (it can fail)."""
    f = tmp_path / "probe.py"
    f.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import asyncio\n"
                 "def g():\n    from ..cli import main\n    from . import tube\n")
    mods = {m for _, m in _imports(f, "vtube_fleet.core.probe")}
    assert {"asyncio", "vtube_fleet.cli", "vtube_fleet.cli.main", "vtube_fleet.core.tube"} <= mods


def _project_imports(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, name) of every ``from <project module> import name`` in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [(node.lineno, node.module, a.name) for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and not node.level and node.module
            and node.module.split(".")[0] in {"vtube_fleet", "sim_stub"} for a in node.names]


def _unresolved(path: Path) -> list[str]:
    import importlib

    where = _rel(path) if path.is_relative_to(ROOT) else str(path)
    bad = []
    for line, mod, name in _project_imports(path):
        try:
            m = importlib.import_module(mod)
        except ImportError as exc:
            bad.append(f"{where}:{line} {mod}: {exc}")
            continue
        if not hasattr(m, name):
            try:
                importlib.import_module(f"{mod}.{name}")
            except ImportError:
                bad.append(f"{where}:{line} {mod} has no {name}")
    return bad


@pytest.mark.parametrize("top", ["vtube_fleet", "sim_stub", "tests", "bench"])
def test_every_project_import_resolves(top: str) -> None:
    """Imports inside functions run only on their path (a late import of a renamed helper
    once broke the agent's summary on exit); all of them must name something that exists."""
    bad = [b for path in _files(ROOT / top) for b in _unresolved(path)]
    assert not bad, "\n".join(bad)


def test_the_import_check_sees_a_missing_name(tmp_path: Path) -> None:
    f = tmp_path / "probe.py"
    f.write_text("def g():\n    from vtube_fleet.core.metrics import no_such_helper\n")
    bad = _unresolved(f)
    assert len(bad) == 1 and "no_such_helper" in bad[0]


#: The control tick's home (issue 31): what only it may call in the fleet layer, and the
#: per-vehicle tick steps no pilot may define again.
TICK_HOME = "vtube_fleet/fleet/tick.py"
TICK_ONLY_CALLS = {"send_velocities_ned", "send_velocity_ned", "local_ned_to_tube",
                   "velocity_command", "classify"}
NO_PILOT_TICK_STEPS = {"sense", "check_faults", "actuate", "tick", "state", "publish",
                       "run_clock", "setpoint", "view", "observe"}


def _calls(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            out.append((node.lineno, name))
    return out


def test_the_tick_has_one_home() -> None:
    """Sending setpoints, turning telemetry into the tube frame and sorting the neighbours
    happen in fleet/tick.py only (the controller itself in fleet/flight_plan.py); the pilot
    keeps the flight procedure and defines no tick step of its own."""
    bad = []
    for path in _files(PACKAGE / "fleet"):
        rel = _rel(path)
        allowed = {TICK_HOME: TICK_ONLY_CALLS,
                   "vtube_fleet/fleet/flight_plan.py": {"velocity_command"}}.get(rel, set())
        bad += [f"{rel}:{line} calls {name}" for line, name in _calls(path)
                if name in TICK_ONLY_CALLS - allowed]
    tree = ast.parse((PACKAGE / "fleet" / "pilot.py").read_text())
    pilot = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "VehiclePilot")
    bad += [f"VehiclePilot.{n.name} is a tick step" for n in pilot.body
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
            and n.name in NO_PILOT_TICK_STEPS]
    assert not bad, "\n".join(bad)
