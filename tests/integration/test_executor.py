"""The executor over real processes: cancel, re-detection of a moved object, planning failures,
preemption, a delivery and putting it back, each judged by the sim (navigation through every
doorway, pick and place everywhere: tests/integration/test_tours.py)."""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from shapely.geometry import Point

from schemas import keys
from schemas.actions import GoalState
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, FailureKind, PlanStatus
from schemas.robot import JointState
from schemas.world import Empty, GroundTruth, Moved, MoveEntity
from services.errors import GoalRejected
from services.runtime import SERVICES
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.watch import Watch
from tether.client import PlanSender

WORLD = WorldModel(load_world())
ROBOT = WORLD.world.robot
PLAN_TIMEOUT = 600.0
# Graspable: everything within the arm's payload (the cast-iron pan is not).
GRASPABLE = [o for o in WORLD.world.objects if o.mass <= ROBOT.payload]
# The shortest tour of every surface (planned routes, from counter round to counter): kitchen,
# living room, office, bedroom.
SURFACES = ["kitchen_counter", "kitchen_table", "coffee_table", "chair", "shelf", "bed"]


# Every service but the recorder (its tests are elsewhere).
WITHOUT_RECORDER = tuple(s for s in SERVICES if s not in ("recorder", "planner"))


# Ten times real time here, not conftest's FAST (twenty): putting an object back where the camera saw
# it checks the spot to 5 cm, and at twenty times it once landed 14 cm off on a loaded run (issue 21).
PRECISE = 10.0


@pytest.fixture
def fast_stack(tmp_path: Path) -> Iterator[Stack]:
    s = start_stack(tmp_path, realtime_factor=PRECISE, services=WITHOUT_RECORDER, sim_options=FAST_SIM)
    try:
        yield s
    finally:
        stop_stack(s)


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def plan(*steps: dict[str, str]) -> str:
    return json.dumps({"plan": list(steps)})


def execute(stack: Stack, text: str, feedback: list[ExecutePlanFeedback] | None = None) -> ExecutePlanResult:
    run = PlanSender(stack.node, feedback.append if feedback is not None else None).run(
        ExecutePlanGoal(text=text), PLAN_TIMEOUT
    )
    assert run.result is not None
    return run.result


def chain(start: str) -> list[str]:
    """Every surface once, along the tour, starting after `start` and ending on it."""
    k = SURFACES.index(start)
    return SURFACES[k + 1 :] + SURFACES[: k + 1]


def arm_speed(state: JointState) -> float:
    return max(abs(v) for v in state.velocity[:7])


def test_cancel_during_an_arm_motion_stops_the_arm(fast_stack: Stack) -> None:
    stack = fast_stack
    joints = Watch(stack.node, keys.JOINT_STATES)
    trajectories = Watch(stack.node, keys.ROBOT_TRAJECTORY.status)
    sender = PlanSender(stack.node)
    handle = sender.send(ExecutePlanGoal(text=plan({"action": "pick", "target": "blue book"})))
    moving = joints.wait_for(lambda j: arm_speed(j) > 0.3, 120.0)
    assert moving is not None, "the arm never moved"
    reply = handle.cancel()
    assert reply.accepted, reply
    run = sender.wait(handle, 60.0)
    assert run.result is not None and run.result.status is PlanStatus.CANCELED, run.result
    assert run.result.steps[0].failure is FailureKind.CANCELED
    # The trajectory running then was canceled on the robot, not left to finish.
    assert trajectories.wait_for(lambda s: s.state is GoalState.CANCELED, 10.0) is not None
    # Stopped, and it stays stopped: no later motion of the plan.
    after = len(joints)
    assert joints.wait_for(lambda j: arm_speed(j) < 0.01, 5.0, after=after) is not None, "the arm did not stop"
    settled = joints.latest(5.0)
    assert settled is not None
    later = joints.wait_for(lambda j: j.stamp > settled.stamp + 0.5, 5.0, after=len(joints))
    assert later is not None
    drift = max(abs(a - b) for a, b in zip(later.position[:7], settled.position[:7], strict=True))
    assert drift < 0.01, f"the arm moved {drift:.3f} rad after the cancel"


def test_an_object_moved_out_of_sight_is_found_again_and_picked(fast_stack: Stack) -> None:
    stack = fast_stack
    # Out of the robot's sight (it starts in the living room): the world file still has it on the counter.
    moved = stack.node.call(keys.SIM_MOVE, MoveEntity(id="red_cup", x=2.9, y=3.65), timeout=10.0)
    assert isinstance(moved, Moved) and WORLD.support_under(moved.position, 0.05) == "kitchen_table"
    feedback: list[ExecutePlanFeedback] = []
    result = execute(stack, plan({"action": "pick", "target": "red cup"}), feedback)
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert truth(stack).holding == "red_cup"
    notes = [f.message for f in feedback if f.message]
    assert any("red cup is not where it was expected (kitchen counter)" in n for n in notes), notes


def test_an_object_out_of_the_arms_reach_fails_with_a_planning_reason(fast_stack: Stack) -> None:
    stack = fast_stack
    # On the bed, 1.1 m in front of where the base stands to use it: inside safety's workspace box,
    # beyond what the arm reaches.
    bed = WORLD.furniture["bed"]
    moved = stack.node.call(keys.SIM_MOVE, MoveEntity(id="apple", x=bed.approach.x - 1.1, y=7.5), timeout=10.0)
    assert isinstance(moved, Moved)
    seen = execute(stack, plan({"action": "navigate_to", "target": "bed"}))
    assert seen.status is PlanStatus.SUCCEEDED, seen.reason
    result = execute(stack, plan({"action": "pick", "target": "apple"}))
    assert (result.status, result.stage, result.failure) == (PlanStatus.FAILED, "execute", FailureKind.PLANNING)
    assert "no grasp of apple works" in result.reason and "out of reach" in result.reason, result.reason
    assert result.steps[0].attempts == 3, "retried, re-detecting it each time"
    assert truth(stack).holding is None


def test_a_plan_sent_while_another_runs_is_rejected_or_preempts_it(fast_stack: Stack) -> None:
    stack = fast_stack
    sender = PlanSender(stack.node)
    started = threading.Event()
    first_sender = PlanSender(stack.node, lambda fb: started.set() if fb.stage == "execute" else None)
    first = first_sender.send(ExecutePlanGoal(text=plan({"action": "navigate_to", "target": "bedroom"})))
    assert started.wait(60.0)
    with pytest.raises(GoalRejected, match="busy"):
        sender.send(ExecutePlanGoal(text=plan({"action": "navigate_to", "target": "coffee table"})))
    second = sender.send(ExecutePlanGoal(text=plan({"action": "navigate_to", "target": "coffee table"}), preempt=True))
    ended = first_sender.wait(first, 60.0)
    assert ended.result is not None and ended.result.status is PlanStatus.CANCELED
    assert ended.result.reason.startswith(f"preempted by goal {second.goal_id}"), ended.result.reason
    done = sender.wait(second, PLAN_TIMEOUT)
    assert done.result is not None and done.result.status is PlanStatus.SUCCEEDED, done.result
    here = truth(stack).robot
    goal = WORLD.furniture["coffee_table"].approach
    assert math.hypot(here.x - goal.x, here.y - goal.y) < 0.05


def test_an_agent_starts_follows_and_cancels_a_plan_in_three_calls(fast_stack: Stack) -> None:
    stack = fast_stack
    odom = Watch(stack.node, keys.ODOM)
    # Three drives: still under way however quickly the sim drives while the CLI calls start.
    rooms = ("bedroom", "kitchen", "hallway")
    started = tether_cli(stack, "send", plan(*({"action": "navigate_to", "target": r} for r in rooms)), "--json")
    assert started.returncode == 0, started.stdout + started.stderr
    goal_id = json.loads(started.stdout)["goal_id"]
    assert odom.wait_for(lambda o: abs(o.linear_x) > 0.1, 60.0), "the base never moved"
    status = tether_cli(stack, "goal", goal_id, "--json")
    assert status.returncode == 0, status.stdout + status.stderr
    progress = json.loads(status.stdout)
    assert progress["state"] == "executing" and progress["feedback"]["action"] == "navigate_to", progress
    statuses = Watch(stack.node, keys.EXECUTE_PLAN.status)
    canceled = tether_cli(stack, "cancel", goal_id)
    assert canceled.returncode == 0, canceled.stdout
    assert statuses.wait_for(lambda s: s.goal_id == goal_id and s.state.terminal, 60.0), "the plan never ended"
    ended = tether_cli(stack, "goal", goal_id, "--json")
    final = json.loads(ended.stdout)
    assert (ended.returncode, final["state"], final["result"]["status"]) == (1, "canceled", "canceled"), final
    stopped = odom.wait_for(lambda o: abs(o.linear_x) < 0.01 and abs(o.angular_z) < 0.01, 10.0, after=len(odom))
    assert stopped is not None
    unknown = tether_cli(stack, "goal", "nosuchgoal", "--json")
    assert unknown.returncode == 2 and json.loads(unknown.stdout)["state"] == "unknown"


def test_an_object_brought_to_me_ends_on_the_top_nearest_me_and_goes_back_where_it_was(fast_stack: Stack) -> None:
    stack = fast_stack
    operator = WORLD.world.humans[0].pose
    here = Point(operator.x, operator.y)
    nearest = min(WORLD.world.furniture, key=lambda f: WORLD.footprint(f).distance(here))
    bring = plan(
        {"action": "pick", "target": "red cup"}, {"action": "place", "target": "red cup", "target_location": "me"}
    )
    result = execute(stack, bring)
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert any("the free surface nearest them" in w for w in result.warnings), result.warnings
    now = truth(stack)
    cup = next(o for o in now.objects if o.id == "red_cup")
    assert now.holding is None and cup.on == nearest.id, (now.holding, cup)  # on a top, not the floor or held
    assert 0.4 <= math.dist((cup.position.x, cup.position.y), (operator.x, operator.y)) <= 2.0, cup.position
    delivered = cup.position

    # Carried off in one plan, put back by the next: the resolver remembers where the camera saw it.
    result = execute(stack, plan({"action": "pick", "target": "red cup"}, {"action": "navigate_to", "target": "chair"}))
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert truth(stack).holding == "red_cup"
    result = execute(stack, plan({"action": "place", "target": "red cup", "target_location": "where it was found"}))
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert any("where the camera last saw it before it was in the gripper" in w for w in result.warnings)
    now = truth(stack)
    cup = next(o for o in now.objects if o.id == "red_cup")
    assert now.holding is None and cup.on == nearest.id, (now.holding, cup)
    assert math.dist((cup.position.x, cup.position.y), (delivered.x, delivered.y)) < 0.05, (cup.position, delivered)


# Searches bounded below the defaults: the room the robot is in, two places at most.
NARROW_SEARCH = '[executor.search]\nscope = "room"\nmax_places = 2\n'


def test_an_object_out_of_view_is_searched_for_and_one_nowhere_fails_naming_where_it_looked(tmp_path: Path) -> None:
    stack = start_stack(
        tmp_path, realtime_factor=PRECISE, services=WITHOUT_RECORDER, sim_options=FAST_SIM, extra_config=NARROW_SEARCH
    )
    try:
        # Along the kitchen table, beside the camera's left edge as the base stands at the kitchen's
        # pose facing east (and 0.3 m back from it).
        moved = stack.node.call(keys.SIM_MOVE, MoveEntity(id="blue_cup", x=2.5, y=3.75), timeout=10.0)
        assert isinstance(moved, Moved) and WORLD.support_under(moved.position, 0.05) == "kitchen_table"
        feedback: list[ExecutePlanFeedback] = []
        steps = [{"action": "navigate_to", "target": "kitchen"}, {"action": "detect", "target": "blue cup"}]
        result = execute(stack, plan(*steps, {"action": "pick", "target": "blue cup"}), feedback)
        assert result.status is PlanStatus.SUCCEEDED, result.reason
        assert truth(stack).holding == "blue_cup"
        detect = result.steps[1]
        assert detect.searched == ["around in the kitchen"], detect
        assert detect.search_s > 0, detect  # the executor timed its search
        assert detect.message.endswith("after looking around in the kitchen"), detect.message
        notes = [f.message for f in feedback if f.step == 1]
        assert "blue cup is not in view from here; looking for it" in notes, notes
        assert "looking for blue cup around in the kitchen" in notes, notes
        # In the office, out of the search's scope: the step fails naming the places it looked,
        # as `tether send` shows it.
        moved = stack.node.call(keys.SIM_MOVE, MoveEntity(id="apple", x=6.2, y=8.7), timeout=10.0)
        assert isinstance(moved, Moved) and WORLD.support_under(moved.position, 0.0375) == "shelf"
        sent = tether_cli(stack, "send", "--wait", plan({"action": "detect", "target": "apple"}))
        shown = " ".join(sent.stderr.split())
        assert sent.returncode == 1, sent.stdout + sent.stderr
        looked = "around in the kitchen, on the kitchen table"
        assert f"apple not found: looked {looked}; 1 more place(s) not visited" in shown, shown
        assert "other rooms not searched (search scope room)" in shown, shown
        assert f"(searched: {looked})" in shown, shown
        assert truth(stack).holding == "blue_cup"
    finally:
        stop_stack(stack)
