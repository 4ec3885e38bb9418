"""How a run ends: its outcome word and the process exit code, defined once.

Every command (``run``, ``mock-fleet``, ``mission``, ``agent``, ``sim``) ends with one of the
outcomes below, printed on its last line and written to ``summary.json`` as ``outcome``; the exit
code follows from the outcome through :func:`exit_code`.

==============  ====  ==========================================================================
outcome         code  meaning
==============  ====  ==========================================================================
``completed``   0     every vehicle exited the tube (and landed), no safety limit broken
``incomplete``  3     some vehicle did not exit or did not land in time
``aborted``     3     the run stopped in flight (take-off failure, no valid partition, timeout)
``failed``      2     the run could not start or a user error stopped it (nothing flown unsafe)
``unsafe``      4     a safety limit was broken (judged from the truth when it is known)
``interrupted`` 130   SIGINT / SIGTERM / SIGHUP: held, then landed
==============  ====  ==========================================================================

A :class:`~vtube_fleet.errors.UserError` carries its own code (2 by default) for ``failed``.
The offline simulator (``vtube-fleet sim``) has no vehicles to land and keeps its own code for
a run that ended with robots left in the tube or with a violation: :data:`EXIT_SIM_UNFINISHED`
(1; the README lists it with the others).
"""

from __future__ import annotations

__all__ = [
    "EXIT_ERROR",
    "EXIT_INCOMPLETE",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_SIM_UNFINISHED",
    "EXIT_UNSAFE",
    "OUTCOMES",
    "exit_code",
]

#: The run completed.
EXIT_OK = 0
#: A user error (bad config, infeasible tube, unreachable endpoint): nothing was flown unsafe.
EXIT_ERROR = 2
#: Not every vehicle exited / landed, or the mission was aborted in flight.
EXIT_INCOMPLETE = 3
#: A safety limit was broken.
EXIT_UNSAFE = 4
#: ``vtube-fleet sim``: robots remained in the tube or a safety condition was violated.
EXIT_SIM_UNFINISHED = 1
#: Interrupted by SIGINT / SIGTERM / SIGHUP (128 + 2, as a shell reports it).
EXIT_INTERRUPTED = 130

#: Outcome word → exit code.
OUTCOMES: dict[str, int] = {
    "completed": EXIT_OK,
    "incomplete": EXIT_INCOMPLETE,
    "aborted": EXIT_INCOMPLETE,
    "failed": EXIT_ERROR,
    "unsafe": EXIT_UNSAFE,
    "interrupted": EXIT_INTERRUPTED,
}


def exit_code(outcome: str) -> int:
    """The exit code of ``outcome`` (:data:`OUTCOMES`); an unknown word counts as incomplete."""
    return OUTCOMES.get(outcome, EXIT_INCOMPLETE)
