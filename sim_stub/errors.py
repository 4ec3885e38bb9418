"""Error type of :mod:`sim_stub` (independent of ``vtube_fleet``).

Everything a *user* of the mock can get wrong (a malformed ``--home``, a port scheme that cannot
hold the requested number of vehicles, an unreadable homes file, an invalid fault spec) raises
:class:`SimStubError` with a one-line message naming the cause and the numbers. The CLI prints it
as ``error: <message>`` and exits with status 2.
"""

from __future__ import annotations

__all__ = ["SimStubError"]


class SimStubError(ValueError):
    """A user error in the mock's configuration, reported as one line."""

    exit_code: int = 2
