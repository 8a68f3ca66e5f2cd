"""The sim without Zenoh for unit tests: its thread as a service runs it (services/sim/loop.py SimLoop),
asked what sim/move, sim/fault and goals ask it; a move done in the Simulation itself."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from schemas.world import Moved, MoveEntity
from services.sim.loop import SimLoop
from services.sim.simulation import Simulation
from services.sim.world import Drop


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


def moved(sim: Simulation, request: MoveEntity) -> Moved:
    """`request` done (it must be taken) and the object let settle, stepped here: what sim/move replies."""
    drop = sim.scene.move(request)
    assert isinstance(drop, Drop), drop
    sim.run(drop, timeout=5.0)
    assert drop.result is not None
    return drop.result
