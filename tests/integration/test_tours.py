"""Every graspable object picked and placed on every surface, over real processes, judged by the sim.

Its own module (apart from tests/integration/test_executor.py) so that its fast sim lives only while
the tours run, and a parallel worker can take it while another runs the executor's other tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from schemas.executor import PlanStatus
from schemas.world import WorldObject
from tests.integration.conftest import FAST, FAST_SIM, Stack, start_stack, stop_stack
from tests.integration.test_executor import GRASPABLE, WITHOUT_RECORDER, WORLD, chain, execute, plan, truth


@pytest.fixture(scope="module")
def tour_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """One stack for the objects' tours of the surfaces: each tour leaves the world as it found it."""
    s = start_stack(
        tmp_path_factory.mktemp("tours"), realtime_factor=FAST, services=WITHOUT_RECORDER, sim_options=FAST_SIM
    )
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.mark.parametrize("obj", GRASPABLE, ids=[o.id for o in GRASPABLE])
def test_every_graspable_object_is_picked_and_placed_on_every_surface(tour_stack: Stack, obj: WorldObject) -> None:
    stack = tour_stack
    for surface in chain(obj.support):
        name = WORLD.furniture[surface].name
        result = execute(stack, plan({"action": "pick", "target": obj.name}, {"action": "place", "target": name}))
        # Judged by the simulator, not by what the executor says.
        now = truth(stack)
        placed = next(o for o in now.objects if o.id == obj.id)
        where = f"the sim has it on {placed.on} at {placed.position}, held: {now.holding}"
        assert result.status is PlanStatus.SUCCEEDED, f"{obj.name} onto the {name}: {result.reason}; {where}"
        assert now.holding is None
        assert placed.on == surface, f"{obj.name} is on {placed.on}, not on the {name}"
        resting = WORLD.furniture[surface].size.z + obj.size.z / 2
        assert placed.position.z == pytest.approx(resting, abs=0.01), f"{obj.name} on the {name} is not upright"
