"""Safety's pure checks: keep-out zones, speed, joints, payload, the e-stop latch."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest

from schemas.common import Pose2D, Vec3
from schemas.plan import Fallback, GripperStep, GroundedPlan, NavigateStep, PickStep, PlaceStep, Plan, SayStep, Step
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, TrajectoryPoint, Twist
from schemas.safety import Rule
from services.robotmodel import ArmModel
from services.safety.errors import Unauthorized, Vetoed
from services.safety.latch import EstopLatch
from services.safety.operator import MAX_TOKEN_BYTES, ensure_token, read_token
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

ARM = [f"panda_joint{i}" for i in range(1, 8)]
HOME = [0.0, -1.2, 0.0, -2.7, 0.0, 1.5, 0.785]


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    world = load_world()
    arm = ArmModel(world.robot.arm_urdf)
    return SafetyPolicy(WorldModel(world), load_policy(None, world.robot, arm, world.keep_out), arm)


def test_goal_in_the_stairs_is_vetoed_naming_the_zone(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match="keep-out zone 'stairs'"):
        policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0)), Pose2D(x=9.0, y=6.0))


def test_a_path_through_the_stairs_is_vetoed(policy: SafetyPolicy) -> None:
    with pytest.raises(
        Vetoed, match=r"^path from \(10\.00, 8\.50\) to .* takes the base's footprint into keep-out zone 'stairs'"
    ):
        policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=11.5, y=6.5)), Pose2D(x=10.0, y=8.5))


def test_a_goal_off_the_map_is_vetoed(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match="outside every room"):
        policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=30.0, y=2.0)), Pose2D(x=6.0, y=1.2))


def test_without_a_known_pose_no_route_is_approved(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match="pose is unknown"):
        policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=2.5, y=1.05)), None)


def test_the_route_checked_is_the_route_driven_including_the_straight_in_leg(policy: SafetyPolicy) -> None:
    # The goal and the direct leg stay clear of the stairs, but the base parks by driving in from
    # 0.4 m behind the goal along its heading, and that point is at the stairs.
    goal = Pose2D(x=9.9, y=8.5, yaw=math.pi)
    with pytest.raises(Vetoed, match="keep-out zone 'stairs'"):
        policy.check_navigation(NavigateToPoseGoal(pose=goal), Pose2D(x=9.0, y=6.0))
    # Facing the other way, the same goal is driven into from the clear side.
    policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=9.9, y=8.5, yaw=0.0)), Pose2D(x=9.0, y=6.0))


def test_the_footprint_not_just_the_centre_stays_out_of_zones(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match="stairs"):
        policy.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=10.3, y=7.5)), Pose2D(x=9.0, y=7.5))


def test_a_clear_goal_passes_but_a_speed_over_the_limit_is_refused_not_clamped(policy: SafetyPolicy) -> None:
    goal = NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.75, yaw=math.pi / 2), max_speed=0.6)  # at the coffee table
    # The turn rate, not asked for, is filled in with the limit: the robot gets numbers safety approved.
    assert policy.check_navigation(goal, Pose2D(x=6.0, y=1.2)).command == msgspec.structs.replace(
        goal, max_turn_rate=1.2, start=Pose2D(x=6.0, y=1.2)
    )
    with pytest.raises(Vetoed, match=r"2 m/s exceeds the base's limit of 0\.6 m/s") as refused:
        policy.check_navigation(NavigateToPoseGoal(pose=goal.pose, max_speed=2.0), Pose2D(x=6.0, y=1.2))
    assert refused.value.rule is Rule.BASE_SPEED
    assert refused.value.values == {"speed_mps": 2.0, "limit_mps": 0.6}


def test_cmd_vel_from_a_program_over_a_limit_is_refused_and_from_a_person_clamped(policy: SafetyPolicy) -> None:
    here = Pose2D(x=6.0, y=1.2)
    with pytest.raises(Vetoed, match="exceeds the limit"):
        policy.check_cmd_vel(Twist(linear_x=5.0), here)
    assert policy.check_cmd_vel(Twist(linear_x=0.2), here).command == Twist(linear_x=0.2)
    running = Twist(linear_x=0.6, angular_z=-1.2)
    clamped = policy.check_teleop(Twist(linear_x=5.0, angular_z=-9.0), here, running, 0.02)
    assert clamped.command == Twist(linear_x=0.6, angular_z=-1.2)
    assert clamped.clamped_by is Rule.BASE_SPEED and "clamped" in clamped.note
    with pytest.raises(Vetoed, match="not finite"):
        policy.check_cmd_vel(Twist(linear_x=float("nan")), here)


def test_cmd_vel_towards_the_stairs_or_blind_is_vetoed_but_stopping_never_is(policy: SafetyPolicy) -> None:
    facing_stairs = Pose2D(x=10.0, y=8.0, yaw=0.0)
    with pytest.raises(Vetoed, match="keep-out zone 'stairs'"):
        policy.check_cmd_vel(Twist(linear_x=0.5), facing_stairs)
    assert policy.check_cmd_vel(Twist(linear_x=-0.3), facing_stairs).command == Twist(linear_x=-0.3)
    with pytest.raises(Vetoed, match="pose is unknown"):
        policy.check_cmd_vel(Twist(linear_x=0.1), None)
    assert policy.check_cmd_vel(Twist(), None).command == Twist()
    assert policy.check_cmd_vel(Twist(angular_z=0.5), None).command == Twist(angular_z=0.5)


def trajectory(*points: tuple[list[float], float]) -> FollowJointTrajectoryGoal:
    return FollowJointTrajectoryGoal(
        joint_names=ARM, points=[TrajectoryPoint(positions=q, time_from_start=t) for q, t in points]
    )


NOW = dict(zip(ARM, HOME, strict=True))
START = Pose2D(x=6.0, y=1.2)


def test_trajectories_within_limits_pass(policy: SafetyPolicy) -> None:
    target = [*HOME[:3], -2.0, *HOME[4:]]
    goal = trajectory((HOME, 0.0), (target, 1.0))
    assert policy.check_trajectory(goal, NOW, START).command == goal


def test_trajectories_past_a_joint_limit_or_too_fast_are_vetoed(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match=r"panda_joint4 = 0\.5000 rad is outside"):
        policy.check_trajectory(trajectory(([*HOME[:3], 0.5, *HOME[4:]], 1.0)), NOW, START)
    with pytest.raises(Vetoed, match="rad/s"):
        policy.check_trajectory(trajectory((HOME, 0.1), ([2.0, *HOME[1:]], 0.2)), NOW, START)


def test_the_first_segment_starts_where_the_arm_is(policy: SafetyPolicy) -> None:
    far = [2.0, *HOME[1:]]
    # One point, reached in 0.1 s from where the arm really is: 20 rad/s.
    with pytest.raises(Vetoed, match="rad/s"):
        policy.check_trajectory(trajectory((far, 0.1)), NOW, START)
    with pytest.raises(Vetoed, match="would jump"):
        policy.check_trajectory(trajectory((far, 0.0), (far, 5.0)), NOW, START)
    with pytest.raises(Vetoed, match="joint positions are unknown"):
        policy.check_trajectory(trajectory((HOME, 1.0)), None, START)


def test_unknown_joints_are_vetoed(policy: SafetyPolicy) -> None:
    with pytest.raises(Vetoed, match="unknown joints"):
        policy.check_trajectory(
            FollowJointTrajectoryGoal(
                joint_names=["elbow"], points=[TrajectoryPoint(positions=[0.0], time_from_start=1.0)]
            ),
            NOW,
            START,
        )


def test_payload_comes_from_the_world_file(policy: SafetyPolicy) -> None:
    assert policy.check_gripper(GripperCommandGoal(position=0.0, object_id="red_cup")).command.object_id == "red_cup"
    with pytest.raises(Vetoed, match=r"weighs 4\.5 kg, over the arm.s payload of 3 kg"):
        policy.check_gripper(GripperCommandGoal(position=0.0, object_id="cast_iron_pan"))
    with pytest.raises(Vetoed, match="unknown object"):
        policy.check_gripper(GripperCommandGoal(position=0.0, object_id="anvil"))


def test_plans_are_checked_step_by_step(policy: SafetyPolicy) -> None:
    source = Plan(steps=[Step(action="pick", target="pan")])  # type: ignore[arg-type]
    pan = PickStep(
        object_id="cast_iron_pan",
        object_name="cast-iron pan",
        position=Vec3(x=3.25, y=0.35, z=0.925),
        mass=0.1,  # a lie in the message: safety reads the mass from its own world file
        support_id="kitchen_counter",
        approach=Pose2D(x=2.5, y=1.05, yaw=-1.57),
    )
    go = NavigateStep(target="kitchen counter", goal=Pose2D(x=2.5, y=1.05, yaw=-1.57))
    assert policy.check_plan(GroundedPlan(steps=[go], source=source), Pose2D(x=6.0, y=1.2))
    with pytest.raises(Vetoed, match=r"step 2 \(pick\).*payload"):
        policy.check_plan(GroundedPlan(steps=[go, pan], source=source), Pose2D(x=6.0, y=1.2))
    stairs = NavigateStep(target="stairs", goal=Pose2D(x=11.2, y=8.0))
    with pytest.raises(Vetoed, match=r"step 1 \(navigate_to\).*'stairs'"):
        policy.check_plan(GroundedPlan(steps=[stairs], source=source), Pose2D(x=6.0, y=1.2))


def test_the_latch_holds_until_the_operator_token_resets_it(tmp_path: Path) -> None:
    token = ensure_token(tmp_path / "token")
    assert (tmp_path / "token").stat().st_mode & 0o777 == 0o600
    latch = EstopLatch(token)
    assert latch.trigger("executor", "test", 100.0)
    assert not latch.trigger("agent", "again", 101.0), "a second trigger does not overwrite the first"
    assert (latch.state.source, latch.state.stamp) == ("executor", 100.0)
    with pytest.raises(Unauthorized):
        latch.reset("agent", "guess", 102.0)
    with pytest.raises(Unauthorized):
        latch.reset("agent", "", 102.0)
    assert latch.state.latched
    latch.reset("operator", token, 103.0)
    assert not latch.state.latched and latch.state.stamp == 103.0


def test_the_latch_survives_a_restart_and_an_unreadable_state_fails_closed(tmp_path: Path) -> None:
    state = tmp_path / "estop.json"
    token = ensure_token(tmp_path / "token", state)  # a fresh install: unlatched
    first = EstopLatch(token, state)
    assert not first.state.latched
    assert first.trigger("watchdog", "lost the arm", 100.0)
    assert not EstopLatch("secret", state).state.latched, "trigger only latches in memory; save writes it"
    first.save()
    again = EstopLatch(token, state)
    assert again.state.latched and again.state.source == "watchdog"
    again.reset("operator", token, 101.0)
    assert EstopLatch(token, state).state.latched, "reset, like trigger, is written by save"
    again.save()
    assert not EstopLatch(token, state).state.latched
    state.write_text("{ not json")
    assert EstopLatch(token, state).state.latched


def test_a_missing_latch_file_starts_latched_except_on_a_fresh_installs_first_start(tmp_path: Path) -> None:
    token_file, state = tmp_path / "cfg" / "operator-token", tmp_path / "state" / "estop-r1.json"
    token = ensure_token(token_file, state)
    assert not EstopLatch(token, state).state.latched, "the first start of a fresh install is usable"
    assert oct(state.stat().st_mode & 0o777) == "0o600" and oct(token_file.stat().st_mode & 0o777) == "0o600"
    state.unlink()  # lost: deleted, or a volume that was not mounted
    assert ensure_token(token_file, state) == token and not state.exists(), "a token that exists makes no latch file"
    lost = EstopLatch(token, state)
    assert lost.state.latched and "missing" in lost.state.reason
    lost.reset("operator", token, 5.0)
    lost.save()
    assert not EstopLatch(token, state).state.latched


# Whole plans with sub-steps, on_failure alternatives and the gripper

SOURCE = Plan(steps=[Step(action="stop")])  # type: ignore[arg-type]
CLEAR = Pose2D(x=9.0, y=6.0)


def nav(pose: Pose2D, name: str = "there") -> NavigateStep:
    return NavigateStep(target=name, goal=pose)


def test_an_unsafe_alternative_refuses_the_plan_naming_it(policy: SafetyPolicy) -> None:
    stairs = Fallback(first=0, last=0, steps=[nav(Pose2D(x=11.2, y=8.0), "stairs")], labels=["1.1 on_failure 1"])
    plan = GroundedPlan(steps=[nav(CLEAR), SayStep(text="hi")], source=SOURCE, labels=["1.1", "1.2"])
    assert policy.check_plan(plan, Pose2D(x=9.0, y=5.5))
    with pytest.raises(Vetoed, match=r"^step 1\.1 on_failure 1 \(navigate_to\).*'stairs'"):
        policy.check_plan(msgspec.structs.replace(plan, fallbacks=[stairs]), Pose2D(x=9.0, y=5.5))


def test_an_alternative_is_checked_from_wherever_the_steps_it_covers_start(policy: SafetyPolicy) -> None:
    # Step 2 can fail with the cup in the hand: an alternative opening the gripper would drop it there.
    cup = pick_red_cup()
    put = PlaceStep(
        surface_id="kitchen_counter", surface_name="kitchen counter", position=cup.position, approach=cup.approach
    )
    release = Fallback(first=0, last=1, steps=[GripperStep(open=True)], labels=["1 on_failure 1"])
    plan = GroundedPlan(steps=[cup, put], source=SOURCE, labels=["1.1", "1.2"], fallbacks=[release])
    with pytest.raises(Vetoed, match=r"^step 1 on_failure 1 \(gripper\): opening the gripper would drop red cup"):
        policy.check_plan(plan, COUNTER_SIDE)
    # Covering only the pick, it starts with the cup in the hand too: a lift or stow that fails
    # after the grasp leaves it there.
    covering_first = msgspec.structs.replace(release, last=0)
    with pytest.raises(Vetoed, match=r"^step 1 on_failure 1 \(gripper\): opening the gripper would drop red cup"):
        policy.check_plan(msgspec.structs.replace(plan, fallbacks=[covering_first]), COUNTER_SIDE)


def test_the_steps_after_an_alternative_are_checked_from_where_it_ends(policy: SafetyPolicy) -> None:
    plan = GroundedPlan(steps=[SayStep(text="hi"), GripperStep(open=True)], source=SOURCE)
    assert policy.check_plan(plan, COUNTER_SIDE)
    # If saying hi fails, the alternative picks the cup: step 2 would then open the hand holding it.
    picking = Fallback(first=0, last=0, steps=[pick_red_cup()])
    with pytest.raises(Vetoed, match=r"^step 2 \(gripper\): opening the gripper would drop red cup"):
        policy.check_plan(msgspec.structs.replace(plan, fallbacks=[picking]), COUNTER_SIDE)


COUNTER = Pose2D(x=2.5, y=1.05, yaw=-1.57)
COUNTER_SIDE = Pose2D(x=2.5, y=2.0)


def pick_red_cup() -> PickStep:
    return PickStep(
        object_id="red_cup",
        object_name="red cup",
        position=Vec3(x=2.2, y=0.55, z=0.95),
        mass=0.25,
        support_id="kitchen_counter",
        approach=COUNTER,
    )


def test_the_gripper_may_not_drop_what_it_holds(policy: SafetyPolicy) -> None:
    cup = pick_red_cup()
    place = PlaceStep(
        surface_id="kitchen_counter", surface_name="kitchen counter", position=cup.position, approach=COUNTER
    )
    start = COUNTER_SIDE
    with pytest.raises(Vetoed, match=r"^step 3 \(gripper\): opening the gripper would drop red cup"):
        policy.check_plan(
            GroundedPlan(steps=[cup, GripperStep(open=False), GripperStep(open=True)], source=SOURCE), start
        )
    checks = policy.check_plan(GroundedPlan(steps=[cup, place, GripperStep(open=True)], source=SOURCE), start)
    assert "step 3: the gripper opens with nothing in it" in checks
    # An alternative that drops it is refused too.
    drop = Fallback(first=1, last=1, steps=[GripperStep(open=True)], labels=["2 on_failure 1"])
    with pytest.raises(Vetoed, match=r"^step 2 on_failure 1 \(gripper\): .*would drop red cup"):
        policy.check_plan(GroundedPlan(steps=[cup, place], source=SOURCE, fallbacks=[drop]), start)


def test_a_malformed_alternative_is_refused(policy: SafetyPolicy) -> None:
    beyond = Fallback(first=0, last=3, steps=[SayStep(text="x")])
    with pytest.raises(Vetoed, match=r"covers steps 1\.\.4 of a plan of 1 steps"):
        policy.check_plan(GroundedPlan(steps=[SayStep(text="hi")], source=SOURCE, fallbacks=[beyond]), CLEAR)


@pytest.mark.parametrize(
    ("content", "complaint"),
    [(b"\xd0\xff binary \x00", "not text"), (b"a" * (MAX_TOKEN_BYTES + 1), "not a token file")],
)
def test_a_token_file_that_is_no_token_is_refused_as_one_that_cannot_be_read(
    tmp_path: Path, content: bytes, complaint: str
) -> None:
    """Every command that reads the token refuses an OSError with its message; a file not UTF-8 raised
    UnicodeDecodeError (a traceback from `tether reset`), and /dev/zero was read without end."""
    token_file = tmp_path / "operator-token"
    token_file.write_bytes(content)
    with pytest.raises(OSError, match=complaint):
        read_token(token_file)
    with pytest.raises(OSError, match="not a token file"):
        read_token(Path("/dev/zero"))
    token_file.write_text("  abc123\n")
    assert read_token(token_file) == "abc123"
