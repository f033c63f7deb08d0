"""How a search ended: one enum for the optimizer's rounds and runs (after optimistix's
`RESULTS`: a name, and a message in words).

A `Status` is a `str`, so it compares equal to its value ("converged" == Status.CONVERGED),
and JSON files carry the value.
"""

from __future__ import annotations

import enum


class Status(str, enum.Enum):
    """The end of a round (`vdo.optimize`) or of a whole search."""

    CONVERGED = "converged"
    MAX_STEPS = "max_steps"
    FEASIBLE = "feasible"
    TIME_LIMIT = "time_limit"
    INTERRUPTED = "interrupted"
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value

    @property
    def message(self) -> str:
        """The status in words, for logs and reports."""
        return _MESSAGES[self]

    @property
    def stopped(self) -> bool:
        """True when the search was stopped from outside (time limit or a signal), not by its
        own rule."""
        return self in (Status.TIME_LIMIT, Status.INTERRUPTED)


_MESSAGES = {
    Status.CONVERGED: "the solver's tolerance was met (or nothing was left to gain)",
    Status.MAX_STEPS: "every round ran all its steps",
    Status.FEASIBLE: "a feasibility round met every constraint",
    Status.TIME_LIMIT: "the time limit ended the search; the best layout so far was kept",
    Status.INTERRUPTED: "a signal (Ctrl-C, SIGTERM) ended the search; the best layout so far was kept",
    Status.FAILED: "the solver failed (a non-finite value or an optimistix error)",
}
