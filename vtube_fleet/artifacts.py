"""Writing run outputs atomically: ``summary.json`` and the simulator's npz and png files.

Every ``summary.json`` (fleet, simulator, coordinator, agents) goes through
:func:`write_summary`: written to a temporary file in the same folder, then renamed, so an
interrupted run never leaves a half-written file; NaN and inf are written as ``null``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "json_safe",
    "write_npz_atomic",
    "write_sim_outputs",
    "SUMMARY_NAME",
    "SUMMARY_EVERY_S",
    "SummaryPacer",
    "write_interim_summary",
    "write_json_atomic",
    "write_summary",
]

#: File name of a run's summary in its output folder.
SUMMARY_NAME = "summary.json"
#: While flying, ``summary.json`` is rewritten (atomically, ``complete: false``) this often (less
#: often when writing it takes more than 1 % of the time), so a run killed without cleaning up
#: (SIGKILL) still leaves its last summary (``run`` and ``mission start --wait`` alike).
SUMMARY_EVERY_S = 2.0


class SummaryPacer:
    """When the next interim summary is due (:data:`SUMMARY_EVERY_S`, stretched so that
    writing takes at most ~1 % of the time); times in seconds of one monotonic clock."""

    def __init__(self, first_s: float) -> None:
        self.next_s = first_s

    def due(self, now_s: float) -> bool:
        return now_s >= self.next_s

    def written(self, start_s: float, end_s: float) -> None:
        """One interim summary took ``start_s``..``end_s``: schedule the next."""
        self.next_s = end_s + max(SUMMARY_EVERY_S, 100.0 * (end_s - start_s))


def json_safe(obj: Any) -> Any:
    """Dataclasses, numpy arrays/scalars, enums, paths → JSON types (inf/NaN → None)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: json_safe(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if not f.name.startswith("_")}
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, bool | None | str):
        return obj
    if hasattr(obj, "value") and isinstance(obj.value, str | int):
        return obj.value
    if isinstance(obj, np.integer | int):
        return int(obj)
    if isinstance(obj, np.floating | float):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return str(obj)


def write_json_atomic(path: Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` through a temporary file and a rename.

    NaN and inf become ``null`` (JSON has neither), so a summary is never lost to a bad number.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=2, allow_nan=False) + "\n")
    tmp.replace(path)
    return path


def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    """Write ``out/summary.json`` atomically; returns its path."""
    return write_json_atomic(out / SUMMARY_NAME, summary)


#: Outcomes an interim summary keeps: a limit already broken, or a run already aborted, stays
#: visible in the last summary of a run that is then killed.
KEPT_INTERIM_OUTCOMES = ("unsafe", "aborted")


def write_interim_summary(out: Path, summary: dict[str, Any], doing: str) -> bool:
    """The interim summary (``complete: false``) of a run still going on, written atomically
    so that a run killed without a chance to clean up (SIGKILL, power loss) still leaves its
    last one: ``outcome: running`` (unless it is already one of
    :data:`KEPT_INTERIM_OUTCOMES`) and the reason "``doing`` when this summary was written;
    it ended without writing its own". A failed write is logged, never raised (a checkpoint
    never stops a flight); returns whether it was written."""
    try:
        if summary.get("outcome") not in KEPT_INTERIM_OUTCOMES:
            summary.update(outcome="running", reason=f"{doing} when this summary was written; "
                                                     f"it ended without writing its own")
        summary["complete"] = False
        write_summary(out, summary)
        return True
    except Exception as exc:  # noqa: BLE001 - a checkpoint never stops the flight
        logging.getLogger(__name__).warning("cannot write the interim summary.json in %s: %s",
                                            out, exc)
        return False


def write_npz_atomic(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` as a compressed ``.npz`` through a temporary file and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("wb") as f:
        np.savez_compressed(f, **arrays)
    tmp.replace(path)
    return path


def write_sim_outputs(result: Any, out: Path, *, plots: bool = True) -> list[Path]:
    """Write summary.json, trajectory.npz, metrics.npz and the PNG plots; returns the paths."""
    from vtube_fleet.plots import pick_snapshot_frames, plot_safety, plot_snapshots

    out.mkdir(parents=True, exist_ok=True)
    written = []
    written.append(write_summary(out, result.summary))

    written.append(write_npz_atomic(out / "trajectory.npz", result.trajectory_arrays()))

    arrays = {"t": result.step_t, **result.metrics.as_dict()}
    if result.metrics_center is not None:
        arrays.update({f"{k}_center": v for k, v in result.metrics_center.as_dict().items()})
    written.append(write_npz_atomic(out / "metrics.npz", arrays))

    if plots:
        sc = result.scenario
        r = sc.robots
        title = (f"{Path(sc.source).name}: {r.count} robots, controller {result.controller}, "
                 f"dt = {result.dt:g} s")
        safety = out / "safety.png"
        plot_safety(safety, result.step_t, result.metrics, r_s=r.r_s, v_min=r.v_min,
                    v_max=r.v_max, obstacle_radii=[o.radius for o in sc.obstacles],
                    title=title, center=result.metrics_center)
        written.append(safety)
        if result.t.size:
            frames = pick_snapshot_frames(result.t, result.pos, 4)
            part = result.partition if result.controller != "apf" else None
            route = getattr(result, "route", None)
            if route is not None:  # a route: every segment, all their sub-tubes
                part = route
            snaps = out / "snapshots.png"
            plot_snapshots(
                snaps, sc.corridor.segments,
                [(float(result.t[i]), result.pos[i]) for i in frames],
                r_s=r.r_s, obstacles=sc.obstacles,
                sub_tubes=part.sub_tubes if part is not None and part.K > 1 else (),
                triangles=part.triangles if part is not None else (),
                headings=None if result.heading is None else [result.heading[i] for i in frames],
                title=title,
            )
            written.append(snaps)
    return written
