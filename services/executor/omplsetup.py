"""OMPL's process-wide state, shared by the base planner (navigation.py) and the arm planner (armplanning.py).

OMPL keeps one random seed and one log level for the whole process, and logs to stdout. Every solve
runs inside `solving(seed)`: one solve at a time in the process, OMPL silent meanwhile (the
planners report failures themselves, in words), its random numbers seeded for that solve so the
same request gives the same answer, and the log level as it was afterwards. Nothing is set at
import time.

OMPL calls the planners' checks from C++. An exception raised there would travel back through
OMPL with a traceback holding OMPL's objects, which then outlive the solve (nanobind reports them
"leaked" at exit): `Guard` turns it into a failed check and keeps it as text, to raise afterwards.
"""

from __future__ import annotations

import contextlib
import threading
import traceback
from collections.abc import Callable, Iterator

from ompl import util as ou

# One OMPL solve at a time in the process: the seed and the log level are global.
_LOCK = threading.Lock()


@contextlib.contextmanager
def solving(seed: int) -> Iterator[None]:
    """Hold for one whole solve, from building OMPL's objects to freeing them: the process's only
    OMPL solve meanwhile, OMPL's log off, its random numbers seeded with `seed` (positive: OMPL
    takes 0 as "pick one at random"). The log level is restored on the way out."""
    if seed <= 0:
        raise ValueError(f"an OMPL seed must be positive (0 makes OMPL pick one at random), got {seed}")
    with _LOCK:
        level = ou.getLogLevel()
        ou.setLogLevel(ou.LogLevel.LOG_NONE)
        try:
            # Reseeding after the first solve in the process makes OMPL log an error (silenced
            # here), yet it reseeds all the same: the same seed gives the same solve.
            ou.RNG.setSeed(seed)
            yield
        finally:
            ou.setLogLevel(level)


class Guard:
    """Runs checks called from OMPL: one that raises fails, and the error is kept as text in
    `failure`; every later check fails at once, so the solve ends soon."""

    def __init__(self) -> None:
        self.failure = ""

    def check(self, test: Callable[..., bool], *args: object) -> bool:
        if self.failure:
            return False
        try:
            return bool(test(*args))
        except Exception:
            self.failure = traceback.format_exc()
            return False

    def raise_failure(self, what: str) -> None:
        """Raise the kept error, if any, as a RuntimeError naming `what` failed."""
        if self.failure:
            raise RuntimeError(f"{what} failed inside OMPL:\n{self.failure}")
