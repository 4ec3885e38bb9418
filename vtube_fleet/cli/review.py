"""``vtube-fleet review``: recompute a recorded run's summary and compare."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from vtube_fleet.recording.review import ReviewResult, recorded_every, review

__all__ = [
    "register",
]

def _fmt(v: Any, width: int = 14) -> str:
    if isinstance(v, float):
        text = f"{v:.6g}"
    elif isinstance(v, Mapping):
        text = ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    elif isinstance(v, list) and v and isinstance(v[0], Mapping):
        text = f"[{len(v)} entries]"
    else:
        text = "-" if v is None else str(v)
    return text if len(text) <= max(width, 14) else text[: max(width, 14) - 1] + "…"


def _print_text(res: ReviewResult) -> None:
    d = res.data
    meta = d.meta
    span = f"{d.t_s[0]:.3f}–{d.t_s[-1]:.3f} s" if len(d.t_s) else "no ticks"
    every = recorded_every(d)
    print(f"recording  {d.path}")
    print(f"run        {d.kind}, source {meta.get('source') or '-'}, "
          f"{int(meta.get('robots', len(d.ids)))} robots, positions recorded every "
          f"{every} {'tick' if d.kind == 'fleet' else 'step'}{'s' if every > 1 else ''}")
    print(f"ticks      {len(d.t_s)} recorded ({span}), {len(d.exits)} exits, "
          f"{len(d.events)} events")
    stored = d.summary or {}
    if not stored:
        print("note       the run stored no summary in the recording; nothing to compare")
    print()
    width = max(len(k) for k in res.summary) if res.summary else 10
    print(f"{'key':<{width}}  {'review':>14}  {'run':>14}")
    diff_keys = {k for k, _, _ in res.differences}
    copied = []
    for k, v in res.summary.items():
        if k not in res.recomputed_keys:
            copied.append(k)
            continue
        run = _fmt(stored[k], 60) if k in stored else "-"
        mark = "  ≠" if k in diff_keys else ""
        print(f"{k:<{width}}  {_fmt(v, 60):>14}  {run:>14}{mark}")
    if copied:
        print()
        print("not recomputable from the recording, as the run reported them:")
        for k in copied:
            print(f"{k:<{width}}  {_fmt(res.summary[k], 60)}")
    recorded = {k: v[2] for k, v in d.metric_series.items() if np.any(np.isfinite(v[2]))}
    if recorded:
        print()
        print("per-step metrics as the run logged them (their extrema cover every step, also "
              "the ones between recorded frames):")
        for k, v in recorded.items():
            f = v[np.isfinite(v)]
            print(f"  {k:<34} min {f.min():.6g}  max {f.max():.6g}")
    print()
    if res.differences:
        print(f"{len(res.differences)} key(s) differ from the run's own summary: "
              + ", ".join(k for k, _, _ in res.differences)
              + (f": extremes over the recorded 1/{every} of the steps only; the per-step series "
                 "above hold every step's extremes" if every > 1 else ""))
    elif stored:
        print("the recomputed summary matches the run's own summary")
    print(f"verdict: {res.verdict.summary_line}")
    for p in res.plots:
        print(f"wrote {p}")


def _cmd_review(args: argparse.Namespace) -> int:
    res = review(args.recording, out_dir=args.out, plots=not args.no_plots)
    if args.json:
        json.dump(res.summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        _print_text(res)
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "review",
        help="summary and plots of a recorded run (.rrd)",
        description="Read a run's rerun recording back, recompute its summary with the "
                    "simulator's metrics, compare it with the run's own summary, and write the "
                    "Fig. 11 safety plot and swarm snapshots next to the recording.",
    )
    p.add_argument("recording", type=Path, metavar="RUN.rrd", help="the recording to review")
    p.add_argument("--json", action="store_true",
                   help="print only the summary JSON (the keys of summary.json) on stdout")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="write the PNGs here (default: next to the recording)")
    p.add_argument("--no-plots", action="store_true", help="do not write PNGs")
    p.set_defaults(func=_cmd_review)
