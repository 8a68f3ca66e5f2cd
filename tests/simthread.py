"""The sim thread as a service runs it (services/sim/loop.py SimLoop), without Zenoh, for unit tests
that ask it what sim/move, sim/fault and goals ask it."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from services.sim.loop import SimLoop
from services.sim.simulation import Simulation


@contextmanager
def sim_thread(sim: Simulation, realtime_factor: float) -> Iterator[SimLoop]:
    """`sim` stepped on a thread of its own at `realtime_factor`, obeying nothing; stopped at the end."""
    loop = SimLoop(sim, realtime_factor, lambda: None)
    stop = threading.Event()
    thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield loop
    finally:
        stop.set()
        thread.join(5.0)
