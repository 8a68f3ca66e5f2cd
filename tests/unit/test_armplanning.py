"""Collision-checked arm motions with real pinocchio, coal and OMPL in the default world: the
collision model, allowed contacts, planning around obstacles, straight moves, timing, and a
planned side grasp followed by the pybullet sim."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

from schemas.common import Pose2D, Vec3
from schemas.robot import (
    ARM_JOINTS,
    MAX_TRAJECTORY_POINTS,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    NavigateToPoseGoal,
    TrajectoryPoint,
)
from schemas.world import Extent, WorldObject
from services.executor import armplanning
from services.executor.armplanning import (
    GRIPPER,
    ArmPlanner,
    ArmPlannerConfig,
    ArmScene,
    HeldObject,
    SceneObject,
    interpolate,
    plan_pick,
    time_parameterize,
)
from services.executor.errors import IKFailed, PlanningFailed
from services.executor.grasps import Grasp, grasps
from services.executor.kinematics import top_down_rotation
from services.executor.navigation import BasePlanner
from services.robotmodel import ArmModel, arm_to_world
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.sim.simulation import Simulation
from services.sim.world import FINGER_LINKS
from services.worldmodel import WorldModel, load_world

WORLD = WorldModel(load_world())
ROBOT = WORLD.world.robot
MOUNT = ROBOT.arm_mount
COUNTER = WORLD.furniture["kitchen_counter"]
CUP = WORLD.objects["red_cup"]
# The living room, nothing but two walls within reach.
OPEN = ROBOT.start
SPEED, ACCELERATION = 1.0, 2.0
# Pairs the model may skip: one rigid body (hand, fingers, link7) or next to each other in the URDF.
ADJACENT = {
    *(("panda_link" + str(i), "panda_link" + str(i + 1)) for i in range(7)),
    ("panda_link7", "panda_hand"),
    ("panda_link7", "panda_leftfinger"),
    ("panda_link7", "panda_rightfinger"),
    ("panda_hand", "panda_leftfinger"),
    ("panda_hand", "panda_rightfinger"),
    ("panda_leftfinger", "panda_rightfinger"),
}


# A search that runs out of its time fails (the arm) or tries the next seed (the base), so plans
# compared with each other are planned unhurried. `make test` runs the unit tests at the lowest
# priority beside stacks, where a solve of 20 ms of CPU can take more than the default 1 s: a CI run
# saw the arm's plans fail in threads. With this long a limit every search ends by finding its path.
UNHURRIED = 30.0


@pytest.fixture(scope="module")
def planner() -> ArmPlanner:
    return ArmPlanner(WORLD, ArmPlannerConfig(planning_time=UNHURRIED))


def scene_objects(*skip: str) -> list[SceneObject]:
    return [SceneObject(o, WORLD.initial_position(o)) for o in WORLD.world.objects if o.id not in skip]


@pytest.fixture(scope="module")
def counter(planner: ArmPlanner) -> ArmScene:
    return planner.scene(COUNTER.approach, scene_objects())


def top_down(planner: ArmPlanner, target: Sequence[float]) -> np.ndarray:
    """Joints with the hand pointing down at `target` (panda_link0), whatever they hit."""
    return planner.kin.solve(pin.SE3(top_down_rotation(0.0), np.array(target, dtype=float)), planner.home)


def box(name: str, x: float, y: float, z: float) -> WorldObject:
    return WorldObject(
        id=name, name=name, cls=name, color="grey", shape="box", size=Extent(x=x, y=y, z=z), mass=0.5, support="shelf"
    )


def cup_grasp(scene: ArmScene, kind: str = "top") -> Grasp:
    return next(g for g in grasps(CUP, WORLD.initial_position(CUP), 0.0, scene.base, MOUNT) if g.kind == kind)


def sampled(points: list[TrajectoryPoint]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interval velocities, and accelerations at each sample (at rest before and after), from the samples."""
    t = np.array([p.time_from_start for p in points])
    q = np.array([p.positions for p in points])
    dt = np.diff(t)
    velocity = np.diff(q, axis=0) / dt[:, None]
    padded = np.vstack([np.zeros(q.shape[1]), velocity, np.zeros(q.shape[1])])
    spans = np.concatenate([[dt[0] / 2], (dt[:-1] + dt[1:]) / 2, [dt[-1] / 2]])
    return dt, velocity, np.diff(padded, axis=0) / spans[:, None]


# The collision model


def test_only_adjacent_links_are_never_checked_so_the_hand_meets_link0_and_the_base(
    planner: ArmPlanner, counter: ArmScene
) -> None:
    excluded = set(planner.robot.excluded_names())
    assert excluded <= ADJACENT
    checked = {(counter.names[a], counter.names[b]) for a, b in counter.pairs}
    for pair in [
        ("panda_link0", "panda_hand"),
        ("panda_link0", "panda_link7"),
        ("panda_link1", "panda_hand"),
        ("panda_link5", "panda_hand"),
        ("panda_hand", "robot_base"),
        ("panda_leftfinger", "robot_base"),
        ("panda_hand", "kitchen_counter"),
        ("panda_link4", "red_cup"),
    ]:
        assert pair in checked, pair


def test_the_hand_folded_onto_link0_collides(planner: ArmPlanner) -> None:
    scene = planner.scene(OPEN)
    q = top_down(planner, (-0.05, 0.13, 0.08))
    assert ("panda_link0", "panda_hand") in scene.collisions(q)
    assert not scene.is_free(q)


@pytest.mark.parametrize(("height", "free"), [(0.02, True), (0.013, False), (-0.01, False)])
def test_fingers_over_the_base_keep_the_padding(planner: ArmPlanner, height: float, free: bool) -> None:
    # The fingertips reach 7 mm beyond the grasp frame: 13 mm, 6 mm and 17 mm into the base's top.
    scene = planner.scene(OPEN)
    q = top_down(planner, (-0.25, 0.18, height))
    assert scene.is_free(q) is free
    if not free:
        assert ("panda_leftfinger", "robot_base") in scene.collisions(q)


def test_the_counter_collides_and_the_stowed_arm_is_free(planner: ArmPlanner, counter: ArmScene) -> None:
    assert counter.collisions(planner.home) == []
    inside = top_down(planner, (0.45, -0.1, COUNTER.size.z - MOUNT.z - 0.03))
    hits = counter.collisions(inside)
    assert any(b == "kitchen_counter" for _, b in hits), hits


def test_a_held_object_collides_with_the_scene_but_not_with_the_hand(planner: ArmPlanner, counter: ArmScene) -> None:
    grasp = cup_grasp(counter)
    q_lift = counter.ik(grasp.lift, planner.home)
    # A 30 cm stick held where the cup would be reaches from the lifted hand through the cup into
    # the counter; the hand holding it is not a collision.
    stick = box("stick", 0.04, 0.04, 0.3)
    in_grasp = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.15]))
    holding = counter.holding(HeldObject(stick, in_grasp))
    assert counter.is_free(q_lift)
    assert holding.collisions(q_lift) == [("kitchen_counter", "stick"), ("red_cup", "stick")]
    # The cup held as grasped sits between the open fingers: that is not a collision.
    with_cup = counter.holding(HeldObject(CUP, grasp.object_in_grasp))
    assert with_cup.collisions(q_lift) == []
    assert "red_cup" not in with_cup.names[: len(planner.robot.names)]


def test_allowed_contacts_hold_for_one_call_only(planner: ArmPlanner, counter: ArmScene) -> None:
    grasp = cup_grasp(counter)
    q_pre = counter.ik(grasp.pregrasp, planner.home)
    q_grasp = counter.cartesian(q_pre, grasp.pose.translation, allowed=[("red_cup", GRIPPER)])[-1]
    hits = counter.collisions(q_grasp)
    assert hits and all(b == "red_cup" and a.startswith("panda_") for a, b in hits), hits
    assert counter.is_free(q_grasp, allowed=[("red_cup", GRIPPER)])
    assert not counter.is_free(q_grasp)
    # Holding it, it rests on the counter: allowed while it leaves the counter.
    holding = counter.holding(HeldObject(CUP, grasp.object_in_grasp))
    assert ("kitchen_counter", "red_cup") in holding.collisions(q_grasp)
    assert holding.is_free(q_grasp, allowed=[("red_cup", "kitchen_counter")])


# Motions


def board_scene(planner: ArmPlanner) -> tuple[ArmScene, np.ndarray, np.ndarray]:
    """A board upright ahead of the arm, and the hand down either side of it."""
    board = box("board", 0.4, 0.04, 0.5)
    centre = arm_to_world(OPEN, MOUNT, [0.55, 0.0, -0.1])
    scene = planner.scene(OPEN, [SceneObject(board, centre)])
    left = scene.ik(pin.SE3(top_down_rotation(0.0), np.array([0.5, 0.3, 0.05])), planner.home)
    right = scene.ik(pin.SE3(top_down_rotation(0.0), np.array([0.5, -0.3, 0.05])), planner.home)
    return scene, left, right


def test_plans_around_a_board_between_start_and_goal(planner: ArmPlanner) -> None:
    scene, left, right = board_scene(planner)
    assert not scene.path_free([left, right])
    path = scene.plan(left, right)
    assert len(path) > 2
    assert np.array_equal(path[0], left) and np.array_equal(path[-1], right)
    assert scene.path_free(path, step=0.005)
    assert all(np.all(q >= planner.kin.lower) and np.all(q <= planner.kin.upper) for q in path)
    again = scene.plan(left, right)
    assert len(again) == len(path) and all(np.array_equal(a, b) for a, b in zip(again, path, strict=True))


# Searches of a millisecond of wall time, at most, until one gets the CPU long enough to try a configuration.
SEARCHES = 50


def test_a_path_not_found_in_time_is_refused_naming_what_blocks() -> None:
    # A millisecond: RRTConnect gets no further than its first few configurations. `make test` runs
    # the unit tests at the lowest priority (tests/suite.py), where the millisecond can pass with the
    # process off the CPU and nothing tried (CI saw it once): such a refusal names the direct motion's
    # contact only, and the search is run again.
    scene, left, right = board_scene(ArmPlanner(WORLD, ArmPlannerConfig(planning_time=0.001)))
    messages = []
    for _ in range(SEARCHES):
        with pytest.raises(PlanningFailed) as failed:
            scene.plan(left, right, what="moving the hand across")
        message = str(failed.value)
        assert message.startswith("moving the hand across: no collision-free path found in 0.001 s: ")
        assert re.search(r"the direct motion is blocked where panda_\w+ touches board", message), message
        messages.append(message)
        if "configurations it tried" in message:
            break
    assert re.search(
        r"configurations it tried and rejected, the commonest contacts were panda_\w+ touches board \(\d+%\)", message
    ), messages


def test_ik_whose_solutions_all_collide_names_what_they_collide_with(planner: ArmPlanner, counter: ArmScene) -> None:
    inside = pin.SE3(top_down_rotation(0.0), np.array([0.45, -0.1, COUNTER.size.z - MOUNT.z - 0.03]))
    with pytest.raises(IKFailed, match=r"all \d+ solutions found collide: panda_\w+ touches kitchen_counter"):
        counter.ik(inside, planner.home)


def test_a_free_straight_line_is_the_plan(planner: ArmPlanner, counter: ArmScene) -> None:
    q_pre = counter.ik(cup_grasp(counter).pregrasp, planner.home)
    path = counter.plan(planner.home, q_pre)
    assert len(path) == 2


def test_a_start_in_collision_is_refused_naming_the_contact(planner: ArmPlanner, counter: ArmScene) -> None:
    inside = top_down(planner, (0.45, -0.1, COUNTER.size.z - MOUNT.z - 0.03))
    with pytest.raises(PlanningFailed, match=r"start configuration collides: panda_\w+ touches kitchen_counter"):
        counter.plan(inside, planner.home)


def test_a_start_within_the_padding_can_still_leave(planner: ArmPlanner, counter: ArmScene) -> None:
    # Fingertips 5 mm above the counter: inside the 1 cm padding, not touching.
    grasp_height = COUNTER.size.z - MOUNT.z + 0.005 + 0.0072
    close = top_down(planner, (0.45, -0.1, grasp_height))
    assert not counter.is_free(close)
    path = counter.plan(close, planner.home)
    assert np.array_equal(path[-1], planner.home)
    up = counter.cartesian(close, [0.45, -0.1, grasp_height + 0.1])
    assert counter.is_free(up[-1])


def test_a_straight_move_keeps_the_grasp_frame_on_the_line(planner: ArmPlanner, counter: ArmScene) -> None:
    grasp = cup_grasp(counter)
    q_pre = counter.ik(grasp.pregrasp, planner.home)
    path = counter.cartesian(q_pre, grasp.pose.translation, allowed=[("red_cup", GRIPPER)])
    start, end = grasp.pregrasp.translation, grasp.pose.translation
    for q in interpolate(path, 0.005):
        pose = planner.kin.forward(q)
        off_line = np.linalg.norm(np.cross(pose.translation - start, end - start)) / np.linalg.norm(end - start)
        assert off_line < 1.5e-3
        assert np.linalg.norm(pin.log3(pose.rotation.T @ grasp.pose.rotation)) < 0.02
    with pytest.raises(PlanningFailed, match="kitchen_counter"):
        counter.cartesian(q_pre, grasp.pose.translation - np.array([0.0, 0.0, 0.065]), allowed=[("red_cup", GRIPPER)])


def test_unreachable_targets_fail_with_a_reason(planner: ArmPlanner, counter: ArmScene) -> None:
    with pytest.raises(IKFailed, match=r"\(1\.500, 0\.000, 0\.300\) m in panda_link0: .*residual"):
        counter.ik(pin.SE3(top_down_rotation(0.0), np.array([1.5, 0.0, 0.3])), planner.home)
    far = Vec3(x=COUNTER.center[0] + 0.9, y=COUNTER.center[1] - 0.2, z=COUNTER.size.z + CUP.size.z / 2)
    scene = planner.scene(COUNTER.approach, [*scene_objects("red_cup"), SceneObject(CUP, far)])
    candidates = grasps(CUP, far, 0.0, COUNTER.approach, MOUNT)
    with pytest.raises(PlanningFailed, match=r"no grasp of red cup works .*out of reach"):
        plan_pick(scene, planner.home, candidates, CUP, COUNTER.id)


# Timing


def test_timing_keeps_every_joint_within_its_velocity_and_acceleration(planner: ArmPlanner) -> None:
    rng = np.random.default_rng(3)
    corners = [planner.home + rng.uniform(-0.8, 0.8, 7) for _ in range(4)]
    curve = [
        planner.home + np.array([0.3 * math.sin(2 * s), 0.2 * s, 0.1 * s * s, -0.3 * s, 0.0, 0.1, 0.0])
        for s in np.linspace(0, 1, 16)
    ]
    limits = np.array([1.0, 1.0, 0.8, 1.0, 1.2, 1.2, 1.5])
    for path, acceleration in ((corners, 2.0), (curve, 2.0), (corners, limits * 3)):
        points = time_parameterize(path, limits, acceleration)
        dt, velocity, accel = sampled(points)
        assert points[0].time_from_start == 0.0 and np.array_equal(points[0].positions, path[0])
        assert np.allclose(points[-1].positions, path[-1])
        assert np.all(dt > 0) and np.all(dt <= 0.04 + 1e-9)
        assert np.all(np.abs(velocity) <= limits)
        assert np.all(np.abs(accel) <= acceleration)
        assert len(points) <= MAX_TRAJECTORY_POINTS
        # Every waypoint is a sample: the samples trace the path that was checked.
        samples = [np.array(p.positions) for p in points]
        for waypoint in path:
            assert min(float(np.max(np.abs(s - waypoint))) for s in samples) < 1e-9
    still = time_parameterize([planner.home], SPEED, ACCELERATION)
    assert [p.time_from_start for p in still] == [0.0, 0.04]


def test_a_path_that_cannot_be_timed_names_the_joint_and_the_limit(
    planner: ArmPlanner, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Its first guess at the corner speeds takes joint 1 over its acceleration limit; with no
    # rounds left to slow them down, timing gives up and says where.
    monkeypatch.setattr(armplanning, "TIMING_ROUNDS", 1)
    curve = [planner.home + np.array([0.3 * math.sin(2 * s), 0.2 * s, 0, 0, 0, 0, 0]) for s in np.linspace(0, 1, 16)]
    with pytest.raises(
        PlanningFailed,
        match=r"could not time a path of 16 waypoints within the joint limits: panda_joint1 would still reach "
        r"[\d.]+ rad/s² at [\d.]+ s, over its acceleration limit of 2\.00 rad/s²",
    ):
        time_parameterize(curve, SPEED, 2.0)


def test_a_timed_pick_passes_the_safety_check(planner: ArmPlanner, counter: ArmScene) -> None:
    arm = ArmModel(ROBOT.arm_urdf)
    policy = SafetyPolicy(WORLD, load_policy(None, ROBOT, arm, WORLD.world.keep_out), arm)
    candidates = grasps(CUP, WORLD.initial_position(CUP), 0.0, COUNTER.approach, MOUNT)
    pick = plan_pick(counter, planner.home, candidates, CUP, COUNTER.id, q_stow=planner.home)
    assert pick.to_stow is not None
    for path in (pick.to_pregrasp, pick.approach, pick.lift, pick.to_stow):
        points = time_parameterize(path, SPEED, ACCELERATION)
        goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points)
        now = dict(zip(ARM_JOINTS, path[0].tolist(), strict=True))
        verdict = policy.check_trajectory(goal, now, COUNTER.approach)
        assert verdict.values["fastest_rps"] <= SPEED + 1e-9


# The sim


def test_the_sim_follows_a_planned_side_grasp_of_the_red_cup(planner: ArmPlanner) -> None:
    sim = Simulation(WORLD.world)
    try:
        route = [Pose2D(x=5.7, y=2.1), Pose2D(x=4.3, y=2.1)]
        assert (
            sim.run(sim.controllers.navigate(NavigateToPoseGoal(pose=COUNTER.approach, path=route)), 60.0).state
            == "succeeded"
        )
        base = sim.robot.base_pose()
        objects = [SceneObject(o, sim.scene.object_position(o.id)) for o in WORLD.world.objects]
        scene = planner.scene(base, objects)
        side = [g for g in grasps(CUP, sim.scene.object_position(CUP.id), 0.0, base, MOUNT) if g.kind == "side"]
        pick = plan_pick(scene, np.array(sim.robot.arm_positions()), side, CUP, COUNTER.id)

        def follow(path: list[np.ndarray]) -> float:
            goal = FollowJointTrajectoryGoal(
                joint_names=list(ARM_JOINTS), points=time_parameterize(path, SPEED, ACCELERATION)
            )
            motion = sim.controllers.follow_trajectory(goal)
            worst = 0.0
            while motion.running:
                sim.step()
                if motion.feedback is not None:
                    worst = max(
                        worst, float(np.max(np.abs(np.subtract(motion.feedback.desired, motion.feedback.actual))))
                    )
            assert motion.state == "succeeded", motion.message
            return worst

        assert follow(pick.to_pregrasp) < 0.02
        assert follow(pick.approach) < 0.02
        closed = sim.run(sim.controllers.gripper(GripperCommandGoal(position=0.0, object_id=CUP.id)), 5.0)
        assert closed.result is not None and closed.result.holding == CUP.id
        body = sim.scene.object_bodies[CUP.id]
        fingers = [sim.robot.link_index[name] for name in FINGER_LINKS]
        assert all(sim.scene.bullet.getContactPoints(sim.robot.id, body, link, -1) for link in fingers)
        assert follow(pick.lift) < 0.02
        assert sim.scene.object_position(CUP.id).z > COUNTER.size.z + CUP.size.z / 2 + 0.1
    finally:
        sim.close()


def test_base_and_arm_plans_in_threads_are_the_plans_made_alone(planner: ArmPlanner) -> None:
    # OMPL's seed is the process's: one solve at a time (omplsetup.solving), each reseeded.
    base = BasePlanner(WORLD, time_limit=UNHURRIED)
    scene, left, right = board_scene(planner)
    goal = WORLD.room_pose("kitchen")
    alone_base, alone_arm = base.plan(OPEN, goal), scene.plan(left, right)
    found: dict[str, list] = {}
    failed: dict[str, BaseException] = {}

    def plans(name: str, plan: Callable[[], Any]) -> None:
        # Kept, not raised on the thread: a CI run saw the arm's plans missing and no reason why.
        try:
            found[name] = [plan() for _ in range(3)]
        except Exception as exc:
            failed[name] = exc

    threads = [
        threading.Thread(target=plans, args=("base", lambda: base.plan(OPEN, goal))),
        threading.Thread(target=plans, args=("arm", lambda: scene.plan(left, right))),
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not failed, {name: f"{type(exc).__name__}: {exc}" for name, exc in failed.items()}
    assert found["base"] == [alone_base] * 3
    for path in found["arm"]:
        assert len(path) == len(alone_arm) and all(np.array_equal(a, b) for a, b in zip(path, alone_arm, strict=True))


def test_planning_leaves_ompl_silent_as_it_was_and_no_objects_alive_at_exit() -> None:
    # OMPL's nanobind bindings print "leaked" warnings when its objects outlive the interpreter;
    # OMPL logs to stdout, and would log an error reseeding after its first solve.
    script = """
from ompl import util as ou
from services.executor.armplanning import ArmPlanner, ArmPlannerConfig
from services.executor.errors import PlanningFailed
from services.executor.navigation import BasePlanner
from services.worldmodel import WorldModel, load_world
from tests.unit.test_armplanning import board_scene
ou.setLogLevel(ou.LogLevel.LOG_INFO)
world = WorldModel(load_world())
base = BasePlanner(world)
start, goal = world.world.robot.start, world.room_pose("kitchen")
print(len(base.plan(start, goal)), len(base.plan(start, goal, seed=2)))
scene, left, right = board_scene(ArmPlanner(world))
print(len(scene.plan(left, right)))
hurried, left, right = board_scene(ArmPlanner(world, ArmPlannerConfig(planning_time=0.001)))
try:
    hurried.plan(left, right)
except PlanningFailed as exc:
    failed = exc  # kept to the end: its traceback must hold no OMPL object
print(ou.getLogLevel() == ou.LogLevel.LOG_INFO)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    *_, paths, arm, level = done.stdout.strip().splitlines()
    assert all(int(n) > 0 for n in paths.split()) and int(arm) > 2 and level == "True", done.stdout
    output = done.stdout + done.stderr
    assert not re.search(r"^(Debug|Info|Warning|Error):", output, re.MULTILINE), output
    assert "leaked" not in done.stderr, done.stderr
