"""Faults injected into the simulated world over real processes (sim/fault, `tether world fault`): a
slip during a carry, an object hidden and put back, a doorway blocked; and the incidents the sim
reports (dropped, collision). One stack for the module; the tests run in order, each going on from
where the robot stands after the one before."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.executor import ExecutePlanGoal, ExecutePlanResult, FailureKind, PlanStatus
from schemas.incidents import IncidentKind, IncidentReport
from schemas.world import Empty, FaultInjected, FaultKind, GroundTruth, InjectFault, PerceivedObjects
from services.runtime import SERVICES
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.watch import Watch
from tether.client import PlanSender

SERVICES_USED = tuple(s for s in SERVICES if s not in ("recorder", "planner"))
PLAN_TIMEOUT = 300.0


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    tmp: Path = tmp_path_factory.mktemp("faults")
    s = start_stack(tmp, realtime_factor=10.0, services=SERVICES_USED, sim_options=FAST_SIM)
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.fixture(scope="module")
def incidents(stack: Stack) -> Watch[IncidentReport]:
    return Watch(stack.node, keys.INCIDENT_REPORT)


def execute(stack: Stack, *steps: dict[str, str]) -> ExecutePlanResult:
    run = PlanSender(stack.node).run(ExecutePlanGoal(text=json.dumps({"plan": list(steps)})), PLAN_TIMEOUT)
    assert run.result is not None
    return run.result


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def fault(stack: Stack, kind: FaultKind, target: str = "") -> FaultInjected:
    reply = stack.node.call(keys.SIM_FAULT, InjectFault(kind=kind, target=target), timeout=10.0)
    assert isinstance(reply, FaultInjected), reply
    return reply


def test_the_cup_slips_during_the_carry_and_lands_where_the_arm_reaches_it(
    stack: Stack, incidents: Watch[IncidentReport]
) -> None:
    armed = tether_cli(stack, "world", "fault", "slip", "--json")
    assert armed.returncode == 0, armed.stderr
    assert json.loads(armed.stdout)["status"] == "injected"
    result = execute(
        stack,
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "kitchen table"},
        {"action": "place", "target": "kitchen table"},
    )
    # Picked, carried (the drive itself goes on), and the place finds the hand empty.
    assert result.status is PlanStatus.FAILED, result.reason
    assert [s.status for s in result.steps] == ["succeeded", "succeeded", "failed"], result.steps
    assert result.steps[2].failure is FailureKind.PRECONDITION and "holds nothing" in result.steps[2].message
    world = truth(stack)
    cup = next(o for o in world.objects if o.id == "red_cup")
    # Slipped just after setting off from the counter: it fell onto the counter, where it can be picked again.
    assert world.holding is None and (cup.on, cup.room) == ("kitchen_counter", "kitchen"), cup
    dropped = incidents.wait_for(lambda r: r.kind is IncidentKind.DROPPED, 10.0)
    assert dropped is not None, "no dropped incident reported"
    assert dropped.objects == ["red cup"] and "slipped" in dropped.reason
    assert dropped.x is not None and dropped.y is not None
    assert math.dist((dropped.x, dropped.y), (cup.position.x, cup.position.y)) < 0.02
    collisions = [r for r in incidents.messages if r.kind is IncidentKind.COLLISION]
    assert not collisions, f"a pick and a drive touched nothing, yet: {collisions}"


def test_a_hidden_object_is_out_of_sight_until_cleared(stack: Stack) -> None:
    there = execute(stack, {"action": "navigate_to", "target": "kitchen table"})
    assert there.status is PlanStatus.SUCCEEDED, there.reason
    objects = Watch(stack.node, keys.OBJECTS)

    def seen(object_id: str, after: float) -> PerceivedObjects | None:
        return objects.wait_for(lambda m: m.stamp > after and any(o.id == object_id for o in m.objects), 10.0)

    assert seen("blue_cup", 0.0) is not None, "the camera does not see the blue cup on the kitchen table"
    hidden = fault(stack, FaultKind.HIDE, "blue_cup")
    hidden_at = time.time()
    assert "outside the house" in hidden.message
    cup = next(o for o in truth(stack).objects if o.id == "blue_cup")
    assert cup.room is None, cup
    # Frames after the hide still show the apple beside where the cup stood, and not the cup.
    later = objects.wait_for(lambda m: m.stamp > hidden_at + 0.2 and any(o.id == "apple" for o in m.objects), 10.0)
    assert later is not None and not any(o.id == "blue_cup" for o in later.objects)
    # Bad targets: refused with what is known, and the sim keeps serving.
    attic = tether_cli(stack, "world", "fault", "block", "attic")
    assert attic.returncode == 2 and "attic" in attic.stderr and "kitchen-living_room" in attic.stderr
    unicorn = tether_cli(stack, "world", "fault", "hide", "unicorn", "--json")
    assert unicorn.returncode == 2
    refusal = json.loads(unicorn.stdout)
    assert refusal["status"] == "refused" and "red_cup" in refusal["error"]["candidates"]
    cleared = tether_cli(stack, "world", "fault", "clear", "--json")
    assert cleared.returncode == 0, cleared.stderr
    assert "blue cup" in json.loads(cleared.stdout)["message"]
    back = seen("blue_cup", time.time())
    assert back is not None, "the cup never came back into view"
    assert next(o for o in back.objects if o.id == "blue_cup").on == "kitchen_table"


def test_a_blocked_doorway_stops_the_drive_and_the_touch_is_reported(
    stack: Stack, incidents: Watch[IncidentReport]
) -> None:
    blocked = tether_cli(stack, "world", "fault", "block", "kitchen-living_room", "--json")
    assert blocked.returncode == 0, blocked.stderr
    box = json.loads(blocked.stdout)
    assert (box["position"]["x"], box["position"]["y"]) == (5.0, 2.1)
    before = len(incidents)
    try:
        result = execute(stack, {"action": "navigate_to", "target": "living room"})
        assert result.status is PlanStatus.FAILED, result.reason
        assert "blocked" in result.reason or "stalled" in result.reason, result.reason
        robot = truth(stack).robot
        assert robot.x < 5.0, f"the base got through, to ({robot.x:.2f}, {robot.y:.2f})"
        touched = incidents.wait_for(lambda r: r.kind is IncidentKind.COLLISION, 10.0, after=before)
        assert touched is not None, "no collision reported"
        assert any("doorway between the kitchen and the living room" in o for o in touched.objects), touched
    finally:
        fault(stack, FaultKind.CLEAR)
