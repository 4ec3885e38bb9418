"""``vtube-fleet review``: recompute a recorded run's summary and compare."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from vtube_fleet.recording.review import (
    ReviewResult,
    compare_summaries,
    recorded_every,
    review,
)

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
    if res.per_step_keys or res.run_keys:
        print()
        print("review = the best the recording knows: "
              + "; ".join(part for part in (
                  f"{len(res.per_step_keys)} extreme(s) from the per-step series the run logged "
                  "(every step, also between the recorded frames)" if res.per_step_keys else "",
                  f"{', '.join(res.run_keys)} as the run counted them (confirmed by those "
                  "series)" if res.run_keys else "") if part))
    frame_diffs = [k for k, v in res.from_frames.items()
                   if compare_summaries({k: v}, {k: res.summary.get(k)})]
    if frame_diffs:
        print()
        unit = "tick" if d.kind == "fleet" else "step"
        print(f"from the {len(d.t_s)} recorded frames alone (one every {every} "
              f"{unit}{'s' if every > 1 else ''}; `steps` = frames judged), --json key "
              "from_frames:")
        for k in frame_diffs:
            print(f"{k:<{width}}  {_fmt(res.from_frames[k], 60):>14}")
    print()
    if res.differences:
        print(f"{len(res.differences)} key(s) differ from the run's own summary: "
              + ", ".join(k for k, _, _ in res.differences))
    elif stored:
        print("the recomputed summary matches the run's own summary")
    print(f"verdict: {res.verdict.summary_line}")
    for p in res.plots:
        print(f"wrote {p}")


def _print_no_flight(res: ReviewResult) -> None:
    d = res.data
    print(f"recording  {d.path}")
    print(f"run        {d.kind}, {len(d.events)} events, no scene recorded")
    print(f"no flight: {res.no_flight}")


def _cmd_review(args: argparse.Namespace) -> int:
    res = review(args.recording, out_dir=args.out, plots=not args.no_plots)
    if args.json and res.no_flight is not None:
        json.dump({**res.summary, "no_flight": res.no_flight}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    elif res.no_flight is not None:
        _print_no_flight(res)
    elif args.json:
        json.dump({**res.summary, "from_frames": res.from_frames}, sys.stdout, indent=2)
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
                   help="print only the summary JSON on stdout: the keys of summary.json with "
                   "the best figures the recording holds (extremes over every step from its "
                   "per-step series), and under from_frames the figures recomputed from the "
                   "recorded frames alone")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="write the PNGs here (default: next to the recording)")
    p.add_argument("--no-plots", action="store_true", help="do not write PNGs")
    p.set_defaults(func=_cmd_review)
