"""The control modes on the real stack, judged by the sim: direct refuses plans while teleop drives;
in supervised mode nothing moves before an operator approves (not even a goal sent to safety past the
executor), the approved plan succeeds, a denied one never moves, a running one paused by the operator
stops and waits while teleop drives, and resumed it finishes; only the operator's token sets the mode
or decides, and deciding on an unknown or finished goal is a clear error."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.executor import ExecutePlanGoal, PlanStatus, StepStatus
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import ApprovalAction, ApprovalDecision, ApprovalReply, ControlMode, Decision, ModeRequest
from schemas.world import Empty, GroundTruth
from services.actionlib import ActionClient
from services.errors import GoalRejected
from services.footprint import footprint
from services.runtime import SERVICES
from services.safety.operator import read_token
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli, wait_for_odometry
from tests.watch import Watch
from tether.client import PlanSender

WORLD = WorldModel(load_world())
PLAN_TIMEOUT = 300.0
SERVICES_HERE = tuple(s for s in SERVICES if s not in ("recorder", "planner"))
DIRECT_REASON = "mode direct: only the operator drives (teleop); plans are refused"


@pytest.fixture(scope="module")
def modes_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    s = start_stack(
        tmp_path_factory.mktemp("modes"), realtime_factor=10.0, services=SERVICES_HERE, sim_options=FAST_SIM
    )
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.fixture
def stack(modes_stack: Stack) -> Iterator[Stack]:
    """The shared stack, put back in autonomous mode after each test."""
    yield modes_stack
    token = read_token(modes_stack.token_file)
    request = ModeRequest(operator="test", token=token, mode=ControlMode.AUTONOMOUS)
    assert modes_stack.node.call(keys.SET_MODE, request, timeout=5.0).ok


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def plan(target: str) -> str:
    return json.dumps({"plan": [{"action": "navigate_to", "target": target}]})


def cli_json(stack: Stack, *args: str) -> tuple[int, dict[str, object]]:
    done = tether_cli(stack, *args, "--json")
    try:
        return done.returncode, json.loads(done.stdout)
    except json.JSONDecodeError:
        raise AssertionError(f"not one JSON object: {done.stdout!r} {done.stderr!r}") from None


def set_mode(stack: Stack, mode: str) -> None:
    code, reply = cli_json(stack, "mode", mode, "--token-file", str(stack.token_file))
    assert (code, reply["ok"], reply["mode"]) == (0, True, mode), reply


def still(before: GroundTruth, after: GroundTruth) -> bool:
    assert after.sim_time > before.sim_time
    moved = math.hypot(after.robot.x - before.robot.x, after.robot.y - before.robot.y)
    return moved < 0.005 and abs(after.robot.yaw - before.robot.yaw) < 0.005


def test_only_the_operators_token_sets_the_mode_and_status_and_the_events_show_it(stack: Stack, tmp_path: Path) -> None:
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    wrong = tmp_path / "wrong-token"
    wrong.write_text("0" * 48 + "\n")
    code, refused = cli_json(stack, "mode", "direct", "--token-file", str(wrong))
    assert code == 2 and not refused["ok"] and "not the operator's token" in str(refused["message"]), refused
    assert cli_json(stack, "mode")[1]["mode"] == "autonomous"
    code, bad = cli_json(stack, "mode", "manual", "--token-file", str(stack.token_file))
    assert code == 2 and "unknown mode 'manual'" in str(bad["error"]), bad
    set_mode(stack, "supervised")
    assert cli_json(stack, "mode") == (0, {"ok": True, "mode": "supervised"})
    code, status = cli_json(stack, "status")
    assert code == 0 and status["mode"] == "supervised", status
    changed = events.wait_for(lambda e: e.decision is Decision.MODE, 5.0)
    assert changed is not None and "autonomous -> supervised by operator" in changed.reason
    assert stack.token_file.read_text().strip() not in repr(events.messages)


def test_direct_refuses_a_plan_with_the_reason_while_teleop_drives(stack: Stack) -> None:
    set_mode(stack, "direct")
    before = truth(stack)
    run = PlanSender(stack.node).run(ExecutePlanGoal(text=plan("coffee table")), PLAN_TIMEOUT)
    assert run.result is not None
    assert (run.result.status, run.result.stage, run.result.reason) == (PlanStatus.REJECTED, "safety", DIRECT_REASON)
    assert still(before, truth(stack))
    # A person turns the robot on the spot (clear of everything wherever it stands).
    odom = Watch(stack.node, keys.ODOM)
    deadline = time.monotonic() + 30.0
    turned = None
    while turned is None and time.monotonic() < deadline:
        stack.node.publish(keys.TELEOP_CMD_VEL, Twist(angular_z=0.5))
        turned = odom.wait_for(lambda o: o.angular_z > 0.1, 0.05, after=max(0, len(odom) - 5))
    stack.node.publish(keys.TELEOP_CMD_VEL, Twist())
    assert turned is not None, "teleop did not turn the robot in direct mode"


def test_supervised_nothing_moves_before_approval_then_the_approved_plan_succeeds(stack: Stack) -> None:
    set_mode(stack, "supervised")
    statuses = Watch(stack.node, keys.EXECUTE_PLAN.status)
    before = truth(stack)
    code, sent = cli_json(stack, "send", plan("coffee table"))
    assert code == 0 and sent["status"] == StepStatus.AWAITING_APPROVAL, sent
    goal_id = str(sent["goal_id"])
    assert f"tether approve {goal_id}" in str(sent["reason"]) and "safety's dry run" in str(sent["reason"]), sent
    code, waiting = cli_json(stack, "pending")
    (listed,) = waiting["plans"]  # type: ignore[misc]
    assert listed["goal_id"] == goal_id and "navigate_to coffee table" in listed["steps"][0], listed
    # Past the executor, straight to safety's door: refused, as no approved plan runs.
    navigate = ActionClient(stack.node, keys.CMD_NAVIGATE)
    with pytest.raises(GoalRejected, match="mode supervised: no plan an operator approved is running"):
        navigate.send(NavigateToPoseGoal(pose=Pose2D(x=before.robot.x + 0.3, y=before.robot.y)))
    assert still(before, truth(stack)), "the robot moved before an operator approved"
    code, approved = cli_json(stack, "approve", goal_id, "--token-file", str(stack.token_file))
    assert (code, approved["ok"], approved["state"]) == (0, True, "approved"), approved
    ended = statuses.wait_for(lambda s: s.goal_id == goal_id and s.state.terminal, PLAN_TIMEOUT)
    assert ended is not None and ended.state is GoalState.SUCCEEDED, ended
    here, goal = truth(stack).robot, WORLD.furniture["coffee_table"].approach
    assert math.hypot(here.x - goal.x, here.y - goal.y) < 0.05
    code, again = cli_json(stack, "approve", goal_id, "--token-file", str(stack.token_file))
    assert code == 2 and "does not wait for approval: it is finished" in str(again["message"]), again
    code, unknown = cli_json(stack, "approve", "no-such-goal", "--token-file", str(stack.token_file))
    assert code == 2 and "no plan with goal id no-such-goal waits for approval" in str(unknown["message"]), unknown


def test_supervised_a_denied_plan_never_moves_and_a_wrong_token_decides_nothing(stack: Stack, tmp_path: Path) -> None:
    set_mode(stack, "supervised")
    before = truth(stack)
    sender = PlanSender(stack.node)
    handle = sender.send(ExecutePlanGoal(text=plan("bedroom")))
    waiting = sender.wait(handle, 60.0, until_started=True)
    assert waiting.awaiting_approval is not None, waiting
    wrong = tmp_path / "wrong-token"
    wrong.write_text("0" * 48 + "\n")
    code, refused = cli_json(stack, "approve", handle.goal_id, "--token-file", str(wrong))
    assert code == 2 and "not the operator's token" in str(refused["message"]), refused
    code, denied = cli_json(stack, "deny", handle.goal_id, "--reason", "not now", "--token-file", str(stack.token_file))
    assert (code, denied["state"]) == (0, "denied"), denied
    result = sender.wait(handle, 60.0).result
    assert result is not None and (result.status, result.stage) == (PlanStatus.REJECTED, "safety"), result
    assert result.reason.startswith("denied by operator") and result.reason.endswith(": not now"), result.reason
    assert still(before, truth(stack)), "a denied plan moved the robot"


def wall_gap(robot: Pose2D) -> float:
    """How far the base's footprint is from the nearest wall or piece of furniture (ground truth)."""
    size = WORLD.world.robot.base_size
    body = footprint(robot.x, robot.y, robot.yaw, size.x, size.y)
    return min(body.distance(o.shape) for o in WORLD.obstacles)


def drive_until_settled(stack: Stack, twist: Twist, limit: float = 30.0) -> list[GroundTruth]:
    """Stream `twist` on teleop (50 Hz) until the base, having moved, stands still under it; the
    ground truth sampled on the way (every 0.3 s), the last one where it settled."""
    start = time.monotonic()
    seen = [truth(stack)]
    try:
        while time.monotonic() - start < limit:
            for _ in range(15):
                stack.node.publish(keys.TELEOP_CMD_VEL, twist)
                time.sleep(0.02)  # the stream's pace, not a wait for a condition
            seen.append(truth(stack))
            first, last, now = seen[0].robot, seen[-2], seen[-1]
            if math.hypot(now.robot.x - first.x, now.robot.y - first.y) > 0.05 and still(last, now):
                return seen
    finally:
        stack.node.publish(keys.TELEOP_CMD_VEL, Twist())
    raise AssertionError(f"the base did not settle within {limit:g} s streaming {twist}: at {seen[-1].robot}")


def set_mode_with_token(stack: Stack, mode: ControlMode) -> None:
    request = ModeRequest(operator="test", token=read_token(stack.token_file), mode=mode)
    assert stack.node.call(keys.SET_MODE, request, timeout=5.0).ok


def test_shared_stops_short_of_a_wall_driving_at_it_and_slides_along_it_at_an_angle(stack: Stack) -> None:
    """Ground truth: told 0.3 m/s straight at the south wall, the base stops a few centimetres short
    (direct mode lets the same command through unchanged: test_shared_filter's gate test); told the
    same at 45 degrees to it, it turns along the wall and drives on, never touching it."""
    navigate = ActionClient(stack.node, keys.CMD_NAVIGATE)
    # Autonomous: put the base facing the living room's south wall, its front 0.5 m from it.
    facing = Pose2D(x=6.5, y=0.05 + 0.3 + 0.5, yaw=-math.pi / 2)
    done = navigate.run(NavigateToPoseGoal(pose=facing), timeout=60.0)
    assert done.state is GoalState.SUCCEEDED, done
    set_mode_with_token(stack, ControlMode.SHARED)
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    seen = drive_until_settled(stack, Twist(linear_x=0.3))
    start, end = seen[0].robot, seen[-1].robot
    gaps = [wall_gap(t.robot) for t in seen]
    assert gaps[0] > 0.45 and 0.01 < gaps[-1] < 0.1, gaps
    assert min(gaps) > 0.0 and abs(end.x - start.x) < 0.02, (gaps, end)
    held = events.wait_for(lambda e: e.values.get("shared") == 1.0 and e.values["speed_mps"] < 0.02, 5.0)
    assert held is not None and held.values["requested_mps"] == 0.3 and "shared:" in held.reason, held

    # Autonomous again: back off and face the wall at 45 degrees, then the same command in shared mode.
    set_mode_with_token(stack, ControlMode.AUTONOMOUS)
    backed = Pose2D(x=end.x, y=end.y + 0.3, yaw=end.yaw)  # backwards first: too close to turn there
    angled = Pose2D(x=end.x, y=0.05 + 0.8, yaw=-math.pi / 4)
    for pose in (backed, angled):
        # From where the base stands still, as safety hears it: a goal sent as the last one's motion
        # dies out was checked from odometry 3 cm behind the base and refused by the robot ("the route
        # was checked from (6.50, 0.66, -1.57 rad) but the base stands at (6.50, 0.69, ...)", a CI run).
        assert settle(stack, 10.0) is not None, "the base did not come to rest"
        assert wait_for_odometry(stack.node, 3, 5.0), "no odometry since the base came to rest"
        done = navigate.run(NavigateToPoseGoal(pose=pose), timeout=60.0)
        assert done.state is GoalState.SUCCEEDED, done
    set_mode_with_token(stack, ControlMode.SHARED)
    seen = drive_until_settled(stack, Twist(linear_x=0.3))
    start, end = seen[0].robot, seen[-1].robot
    gaps = [wall_gap(t.robot) for t in seen]
    # Along the wall to the east wall's corner (the east wall at x 11.95), not stopped where it met the wall.
    assert end.x - start.x > 3.0 and min(gaps) > 0.01, (end, gaps)
    assert any(abs(t.robot.yaw) < 0.1 and t.robot.y < 0.7 for t in seen), "it never drove along the wall"
    deflected = events.wait_for(lambda e: e.values.get("shared_steer_rps", 0.0) > 0.0, 5.0)
    assert deflected is not None and "slide along" in deflected.reason, deflected


def settle(stack: Stack, limit: float) -> Pose2D | None:
    """Where the base stands still (ground truth unchanged over 0.2 s of sim time), waiting up to
    `limit` seconds; None if it keeps moving."""
    deadline = time.monotonic() + limit
    last = truth(stack)
    while time.monotonic() < deadline:
        now = truth(stack)
        if now.sim_time - last.sim_time < 0.2:
            continue
        if still(last, now):
            return now.robot
        last = now
    return None


def test_supervised_a_running_plan_paused_stops_and_waits_teleop_drives_and_resumed_it_finishes(
    stack: Stack,
) -> None:
    """Pause mid-drive: the base stops (odometry, ground truth) and the plan waits (not failed); a
    person turns the robot with teleop; `tether resume` hands back and the plan drives on from there
    to its goal (ground truth). An agent's request with a made-up token cannot pause."""
    here = truth(stack).robot
    # Whichever of two tables is farther: a drive of at least 2.8 m, across rooms.
    target = max(
        ("kitchen_table", "coffee_table"),
        key=lambda t: math.dist((here.x, here.y), (WORLD.furniture[t].approach.x, WORLD.furniture[t].approach.y)),
    )
    goal = WORLD.furniture[target].approach
    set_mode(stack, "supervised")
    statuses = Watch(stack.node, keys.EXECUTE_PLAN.status)
    steps = Watch(stack.node, keys.EXECUTE_PLAN.feedback)
    odometry = Watch(stack.node, keys.ODOM)
    sender = PlanSender(stack.node)
    handle = sender.send(ExecutePlanGoal(text=plan(target.replace("_", " "))))
    goal_id = handle.goal_id
    assert sender.wait(handle, 60.0, until_started=True).awaiting_approval is not None
    token = read_token(stack.token_file)

    def decide(action: ApprovalAction, operator: str = "test", secret: str = token) -> ApprovalReply:
        request = ApprovalDecision(operator=operator, token=secret, goal_id=goal_id, action=action)
        reply: ApprovalReply = stack.node.call(keys.APPROVAL_DECIDE, request, timeout=5.0)
        return reply

    assert decide(ApprovalAction.APPROVE).ok
    agent = decide(ApprovalAction.PAUSE, operator="agent", secret="0" * 48)
    assert not agent.ok and "not the operator's token" in agent.message, agent
    moving = odometry.wait_for(lambda o: abs(o.linear_x) > 0.1, 60.0)
    assert moving is not None, "the approved plan never drove"
    paused = decide(ApprovalAction.PAUSE)
    assert paused.ok and paused.approval is not None and paused.approval.state == "paused", paused
    at_pause = truth(stack).robot
    # The base stops within a braking distance and stays still; the plan waits on its step.
    stopped = odometry.wait_for(
        lambda o: abs(o.linear_x) < 0.01 and abs(o.angular_z) < 0.01, 5.0, after=max(0, len(odometry) - 1)
    )
    assert stopped is not None, "the base did not stop when paused"
    settled = settle(stack, 5.0)
    assert settled is not None, "the base keeps moving while paused"
    # The cancel reaches the sim within a few of its (10x) seconds at the plan's speed (0.24 m/s).
    assert math.dist((settled.x, settled.y), (at_pause.x, at_pause.y)) < 1.0, (at_pause, settled)
    waiting = steps.wait_for(
        lambda f: f.goal_id == goal_id and f.feedback.status is StepStatus.AWAITING_APPROVAL and f.feedback.step == 0,
        10.0,
    )
    assert waiting is not None and f"tether resume {goal_id}" in waiting.feedback.message, waiting
    assert not any(s.goal_id == goal_id and s.state.terminal for s in statuses.messages), "the pause ended the plan"
    code, listed = cli_json(stack, "pending")
    assert code == 0 and [p["goal_id"] for p in listed["paused"]] == [goal_id], listed  # type: ignore[attr-defined]
    navigate = ActionClient(stack.node, keys.CMD_NAVIGATE)
    with pytest.raises(GoalRejected, match="paused by operator test"):
        navigate.send(NavigateToPoseGoal(pose=goal))
    # The person takes over: a turn on the spot with teleop, until it turned 0.1 rad (ground truth).
    before = truth(stack).robot

    def turned() -> float:
        return abs(math.remainder(truth(stack).robot.yaw - before.yaw, math.tau))

    deadline = time.monotonic() + 30.0
    try:
        while turned() < 0.1 and time.monotonic() < deadline:
            stack.node.publish(keys.TELEOP_CMD_VEL, Twist(angular_z=0.5))
            odometry.wait_for(lambda o: o.angular_z > 0.1, 0.02, after=max(0, len(odometry) - 1))
    finally:
        stack.node.publish(keys.TELEOP_CMD_VEL, Twist())
    assert turned() >= 0.1, "teleop did not turn the robot while the plan was paused"
    # Handed back: the step drives again from where the person left the robot, to the plan's goal.
    code, resumed = cli_json(stack, "resume", goal_id, "--token-file", str(stack.token_file))
    assert (code, resumed["ok"], resumed["state"]) == (0, True, "approved"), resumed
    ended = statuses.wait_for(lambda s: s.goal_id == goal_id and s.state.terminal, PLAN_TIMEOUT)
    assert ended is not None and ended.state is GoalState.SUCCEEDED, ended
    there = truth(stack).robot
    assert math.hypot(there.x - goal.x, there.y - goal.y) < 0.05, (there, goal)
    code, late = cli_json(stack, "pause", goal_id, "--token-file", str(stack.token_file))
    assert code == 2 and "it is finished" in str(late["message"]), late
