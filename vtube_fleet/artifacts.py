"""Writing run outputs atomically.

Every ``summary.json`` (and the simulator's files) goes through one atomic writer, so an
interrupted run never leaves a half-written file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = [
    "write_summary",
]

# ----------------------------------------------------------------------------------------------
# the commands
# ----------------------------------------------------------------------------------------------
def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(path)
    return path
