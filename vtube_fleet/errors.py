"""Error types shared by the whole package.

Everything a *user* can cause (a bad config, a tube that violates the paper's assumptions, an
endpoint that does not answer) raises a subclass of :class:`UserError`. The CLI prints such errors
as one line (``error: …``) and exits non-zero, never with a traceback.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["PROBLEMS_SHOWN", "ConfigError", "UserError", "bug_text", "join_problems"]

#: A one-line error shows at most this many per-vehicle problems and counts the rest (at 1,000
#: vehicles a full list was 146 kB on one line); the caller keeps every one elsewhere.
PROBLEMS_SHOWN = 10


class UserError(Exception):
    """An error caused by user input or by the outside world, reported as one line."""

    exit_code: int = 2


class ConfigError(UserError):
    """A configuration file is malformed: unknown key, wrong type, missing key, bad value.

    The message names the file and the key, e.g. ``paper.toml: [robots].r_s: expected a
    number, got 'abc'``.
    """


def bug_text(exc: BaseException) -> str:
    """How an exception nobody expected (a bug of ours, logged with its traceback) is named
    in a reason: ``RuntimeError: … (a bug: the traceback is in the log)``."""
    return f"{type(exc).__name__}: {exc} (a bug: the traceback is in the log)"


def join_problems(problems: Sequence[str], shown: int = PROBLEMS_SHOWN,
                  rest: str = "every one is in the summary's events") -> str:
    """The problems ``"; "``-joined, at most ``shown`` of them, then ``… and N more (rest)``."""
    if len(problems) <= shown:
        return "; ".join(problems)
    return ("; ".join(problems[:shown])
            + f"; … and {len(problems) - shown} more ({rest})")
