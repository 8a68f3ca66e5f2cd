"""Worker threads that answer a process's queries: started as needed, kept, and never more than a bound."""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class QueryPool:
    """At most `workers` tasks run at once on threads kept between tasks; `backlog` more may wait for one.

    `submit` never blocks and never starts a thread beyond `workers`: when every worker is busy and
    the backlog is full it returns False, for the caller to answer "busy" at once. A worker starts
    only when a task finds none idle, so a process that serves little holds few threads. Workers
    are daemon threads: a handler waiting an hour for a goal's result does not hold up the exit.
    """

    def __init__(self, name: str, workers: int, backlog: int = 0) -> None:
        if workers < 1 or backlog < 0:
            raise ValueError(f"query pool {name!r} needs workers >= 1 and backlog >= 0, not {workers} and {backlog}")
        self.name = name
        self.workers = workers
        self.backlog = backlog
        self._tasks: collections.deque[Callable[[], None]] = collections.deque()
        self._changed = threading.Condition(threading.Lock())
        self._threads = 0
        self._idle = 0
        self._busy = 0

    def submit(self, task: Callable[[], None]) -> bool:
        """Run `task` on a worker, now or once one is free; False if the pool is full (it will not run)."""
        with self._changed:
            if self._busy + len(self._tasks) >= self.workers + self.backlog:
                return False
            self._tasks.append(task)
            # A worker woken but not yet running still counts as idle here: start one only for the
            # tasks no idle worker is left to take.
            if len(self._tasks) > self._idle and self._threads < self.workers:
                self._threads += 1
                start = True
            else:
                self._changed.notify()
                start = False
        if start:
            threading.Thread(target=self._work, name=f"{self.name}-{self._threads}", daemon=True).start()
        return True

    def load(self) -> str:
        """How full the pool is, for a "busy" reply."""
        with self._changed:
            return f"{self._busy} of {self.workers} workers busy, {len(self._tasks)} of {self.backlog} waiting"

    def _work(self) -> None:
        while True:
            with self._changed:
                self._idle += 1
                while not self._tasks:
                    self._changed.wait()
                self._idle -= 1
                task = self._tasks.popleft()
                self._busy += 1
            try:
                task()
            except Exception:
                log.exception("a task of query pool %s failed", self.name)
            finally:
                with self._changed:
                    self._busy -= 1
