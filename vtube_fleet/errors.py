"""Error types shared by the whole package.

Everything a *user* can cause (a bad config, a tube that violates the paper's assumptions, an
endpoint that does not answer) raises a subclass of :class:`UserError`. The CLI prints such errors
as one line (``error: …``) and exits non-zero, never with a traceback.
"""

from __future__ import annotations

__all__ = ["UserError", "ConfigError"]


class UserError(Exception):
    """An error caused by user input or by the outside world, reported as one line."""

    exit_code: int = 2


class ConfigError(UserError):
    """A configuration file is malformed: unknown key, wrong type, missing key, bad value.

    The message names the file and the key, e.g. ``paper.toml: [robots].r_s: expected a
    number, got 'abc'``.
    """
