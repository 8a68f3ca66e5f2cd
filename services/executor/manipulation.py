"""The motions that make up the steps: planned base routes, picks and places, searching for objects.

Every motion goes to the robot through safety (the Robot port) and every outcome is checked, the
last ones through perception: after a pick the object must be seen in the gripper, after a place
on the surface. Pure logic: the planners (navigation.py, armplanning.py) and the port, no Zenoh.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Collection, Sequence
from typing import Any, assert_never

import numpy as np
import pinocchio as pin

from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, Pose2D, Vec3, fmt_pose
from schemas.plan import (
    DetectStep,
    GripperStep,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    SayStep,
    StopStep,
    WaitStep,
)
from schemas.robot import (
    ARM_JOINTS,
    GRIPPER_MAX_GAP,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    NavigateToPoseGoal,
    Twist,
)
from schemas.world import PerceivedObject, WorldObject
from services.errors import GoalRejected
from services.executor.armplanning import (
    GRIPPER,
    ArmPlanner,
    ArmScene,
    HeldObject,
    SceneObject,
    plan_pick,
    plan_place,
    time_parameterize,
)
from services.executor.config import ExecutorConfig, SearchScope
from services.executor.errors import (
    Canceled,
    CommandVetoed,
    ExecutionError,
    GraspFailed,
    Interrupted,
    PlanningFailed,
    PostconditionFailed,
    PreconditionFailed,
)
from services.executor.grasps import GraspConfig, fits, grasps, narrowest_width, object_pose, placements
from services.executor.navigation import BasePlanner
from services.executor.ports import Robot
from services.executor.search import Look, SearchPlan, narrowest, not_found, plan_search, step_scope
from services.robotmodel import arm_to_world, map_to_base
from services.worldmodel import WorldModel

log = logging.getLogger(__name__)

GRIPPER_OPEN = GRIPPER_MAX_GAP
GRIPPER_CLOSED = 0.0
# Perception publishes a few times a second; wait at most this for its next report.
PERCEPTION_TIMEOUT = 2.0
# The stowed arm counts as stowed within this (rad, every joint).
STOWED = 0.05
# After a failed try the hand backs off this far up before the arm is stowed.
BACK_OFF = 0.1
# An object not in view from where the base stands may be cut off by the image's edge: the base
# backs off this far (straight back, metres) and looks again.
LOOK_BACK = 0.3
# A planned motion starts from the arm's measured position when that is this close (rad, every
# joint) to where it was planned from: the previous motion ended within its goal tolerance.
REPLAN_ABOVE = 0.1

Note = Callable[[str], None]


# An object the resolver's memory has this far from where its pick step was grounded has been seen
# elsewhere since (metres): the pick goes there first.
MOVED_SINCE_GROUNDED = 0.1
# An object seen this far (metres, across the floor) from where its grasp was planned, once the hand
# is above it, has moved meanwhile: reaching in, the fingers would push it or come down on it. Well
# above perception's error (under 1 cm): an object the hand partly hides is not reported at all, as
# the part left would put its centre off (up to 8 cm for the blue book; services/sim/detection.py).
MOVED_BEFORE_GRASP = 0.03
# A placed object whose centre perception sees this much (metres) lower than standing upright puts
# it has fallen over: on its side a cup's centre is its height less its width lower (4 cm).
FALLEN_OVER = 0.015


def _quiet(_: str) -> None:
    pass


def check_outcome(what: str, result: ResultResponse[Any], cancel: threading.Event) -> Any:
    if result.state is GoalState.SUCCEEDED:
        return result.result
    if result.state is GoalState.CANCELED:
        if cancel.is_set():
            raise Canceled(f"{what} canceled")
        # Not canceled here: safety cancels every goal it forwarded when the e-stop latches.
        raise Interrupted(f"{what} canceled by the robot side: {result.message or 'no reason given'}")
    message = result.message or "no reason given"
    # The robot's own words start with what it was doing ("navigation to (2.50, 1.05) aborted ...").
    raise ExecutionError(message if message.startswith(what) else f"{what} {result.state}: {message}")


def refused(what: str, exc: GoalRejected) -> ExecutionError:
    """A goal the robot side would not take: safety's veto (or its e-stop) is final; a robot that
    was busy or unreachable may be asked again."""
    if exc.kind in (ErrorKind.VETOED, ErrorKind.ESTOP):
        return CommandVetoed(f"{what}: {exc.reason}")
    return ExecutionError(f"{what}: the robot did not take it: {exc.reason}")


def _so_far(searched: list[str]) -> str:
    return f" after looking {', '.join(searched)}" if searched else ""


def _pose_error(here: Pose2D, goal: Pose2D) -> tuple[float, float]:
    """How far `here` is from `goal`: metres, and radians of heading either way."""
    return math.hypot(here.x - goal.x, here.y - goal.y), abs(math.remainder(here.yaw - goal.yaw, math.tau))


def _cm(metres: float) -> str:
    return f"{abs(metres) * 100:.0f} cm"


def offset_words(expected: Vec3, seen: Vec3, base: Pose2D) -> str:
    """Where `seen` is from `expected`, in the robot's words: '4 cm left of', '3 cm beyond'."""
    ahead, left = map_to_base(base, seen.x, seen.y)
    ahead0, left0 = map_to_base(base, expected.x, expected.y)
    parts = []
    if abs(left - left0) >= 0.01:
        parts.append(f"{_cm(left - left0)} {'left of' if left > left0 else 'right of'}")
    if abs(ahead - ahead0) >= 0.01:
        parts.append(f"{_cm(ahead - ahead0)} {'beyond' if ahead > ahead0 else 'short of'}")
    if abs(seen.z - expected.z) >= 0.01:
        parts.append(f"{_cm(seen.z - expected.z)} {'above' if seen.z > expected.z else 'below'}")
    return " and ".join(parts) or "right at"


def grasp_config(config: ExecutorConfig) -> GraspConfig:
    """The executor's distances as the grasp and placement candidates take them."""
    return GraspConfig(
        pregrasp_distance=config.pregrasp_height,
        lift_height=config.pregrasp_height,
        grasp_depth=config.grasp_depth,
        place_clearance=config.place_clearance,
    )


class Manipulator:
    """Turns grounded steps into goals for the robot (through safety) and checks each outcome.

    The base drives routes the base planner found; the arm follows paths the arm planner found
    around the furniture, the objects perception sees and what the hand holds, timed within the
    configured joint speed and acceleration. What the hand holds is read from perception, never
    from bookkeeping a failed step could have left stale; how it is held (the grasp) is remembered
    from the pick, so the place can put it down upright.
    """

    def __init__(
        self, robot: Robot, arm: ArmPlanner, base: BasePlanner, world: WorldModel, config: ExecutorConfig
    ) -> None:
        self.robot = robot
        self.arm = arm
        self.base = base
        self.world = world
        self.config = config
        self.grasp_config = grasp_config(config)
        self.home = np.array(world.world.robot.home_joints, dtype=float)
        self.mount = world.world.robot.arm_mount
        # The grasp that holds what the hand holds, from the pick that took it.
        self._held: HeldObject | None = None
        # What a place step let go of (the object's id, the step itself), while its motions after
        # letting go are under way or failed: its retry or resume finds the hand empty and checks the
        # object is where it was put. Another step, of this plan or a later one, is not that step.
        self._let_go: tuple[str, PlaceStep] | None = None
        # Grasps and placements tried and failed, per object, so a retry comes in another way.
        self._failed: dict[str, set[str]] = {}
        # What a search's time limit is measured by (tests step it by hand).
        self.clock: Callable[[], float] = time.monotonic
        # Seconds spent searching since start, by that clock (a step's result reports its share).
        self.search_time = 0.0

    # Base

    def drive_to(self, pose: Pose2D, cancel: threading.Event, max_speed: float | None = None, attempt: int = 1) -> None:
        """Plan a route to `pose` around walls, furniture and people and drive it. A retry plans
        anew (another seed, people where they stand now)."""
        self._stow_if_out(cancel)
        start = self._base()
        people = [(p.x, p.y) for p in self.robot.people()]
        path = self.base.plan(start, pose, people, seed=attempt)
        goal = NavigateToPoseGoal(pose=pose, path=path, max_speed=max_speed)
        try:
            result = self.robot.navigate(goal, cancel)
        except GoalRejected as exc:
            raise refused("navigation", exc) from None
        check_outcome("navigation", result, cancel)
        self._check_arrived(pose)

    def _check_arrived(self, goal: Pose2D) -> None:
        """Done means odometry has the base at the goal, not that the robot said so: after a success
        reported short of it (by a faulty robot, or whoever answers on its keys) the next step would
        plan from where the base is not. The pose is one that arrived after the navigation ended
        (NodeRobot.base_pose), none if none came."""
        here = self.robot.base_pose()
        if here is None:
            raise PostconditionFailed(
                f"the robot reported reaching {fmt_pose(goal)}, but no odometry came after the navigation "
                "ended: where the base stopped is unknown"
            )
        if not self._at(here, goal):
            distance, turn = _pose_error(here, goal)
            raise PostconditionFailed(
                f"the robot reported reaching {fmt_pose(goal)}, but odometry has the base stopped at "
                f"{fmt_pose(here)}: {distance:.2f} m and {math.degrees(turn):.0f}° off (arrived means within "
                f"{self.config.approach_tolerance:g} m and {math.degrees(self.config.approach_yaw_tolerance):.0f}°)"
            )

    def ensure_at(self, approach: Pose2D, cancel: threading.Event, attempt: int = 1) -> None:
        """Drive to `approach` unless the base already stands there."""
        here = self.robot.base_pose()
        if here is not None and self._at(here, approach):
            return
        self.drive_to(approach, cancel, attempt=attempt)

    def _at(self, here: Pose2D, pose: Pose2D) -> bool:
        distance, turn = _pose_error(here, pose)
        return distance <= self.config.approach_tolerance and turn <= self.config.approach_yaw_tolerance

    # State

    def _base(self) -> Pose2D:
        base = self.robot.base_pose()
        if base is None:
            raise PreconditionFailed("no odometry from the robot: its pose is unknown")
        return base

    def _arm_now(self) -> np.ndarray:
        q = self.robot.arm_positions()
        if q is None:
            raise PreconditionFailed("no joint states from the robot")
        # The robot's word, unchecked by the schema: a NaN would reach the planners and crash them.
        if len(q) != len(self.home) or not all(math.isfinite(v) for v in q):
            raise PreconditionFailed(f"the robot's joint states are not {len(self.home)} finite positions: {list(q)}")
        return np.array(q, dtype=float)

    def _look(self, new: bool = False) -> list[PerceivedObject]:
        """What perception reports after the last motion ended (with `new`, in its next report from
        now on): the objects in view and held."""
        seen = self.robot.look(PERCEPTION_TIMEOUT, new=new)
        if seen is None:
            raise PreconditionFailed(f"no report from perception within {PERCEPTION_TIMEOUT:g} s")
        return seen

    def _scene(self, base: Pose2D, seen: Sequence[PerceivedObject], held: HeldObject | None = None) -> ArmScene:
        objects = [
            SceneObject(self.world.objects[o.id], o.position, o.yaw or 0.0)
            for o in seen
            if o.id in self.world.objects and o.on != "gripper"
        ]
        return self.arm.scene(base, objects, held)

    # Arm and gripper

    def _follow(self, path: list[np.ndarray], what: str, cancel: threading.Event) -> None:
        """Run a planned path from where the arm is now: a motion ends within its tolerance of its
        last point, so the next, planned from there, starts from the measured position instead
        (safety wants the first point where the arm is); further off, the plan no longer holds."""
        here = self._arm_now()
        off = float(np.max(np.abs(here - path[0])))
        if off > REPLAN_ABOVE:
            raise ExecutionError(f"{what}: the arm is {off:.2f} rad from where the motion was planned to start")
        path = [here, *path[1:]]
        points = time_parameterize(path, self.config.max_joint_speed, self.config.max_joint_acceleration)
        goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points)
        try:
            result = self.robot.trajectory(goal, cancel)
        except GoalRejected as exc:
            raise refused(what, exc) from None
        check_outcome(what, result, cancel)

    def gripper(self, position: float, cancel: threading.Event, object_id: str | None = None) -> Any:
        try:
            result = self.robot.gripper(GripperCommandGoal(position=position, object_id=object_id), cancel)
        except GoalRejected as exc:
            raise refused("gripper", exc) from None
        return check_outcome("gripper", result, cancel)

    def operate_gripper(self, open_: bool, cancel: threading.Event) -> str:
        """open_gripper / close_gripper on their own. Opening never drops what the hand holds (that
        is place's job); closing on what it already holds leaves it as it is."""
        held_id = self.robot.held_object()
        held = self.world.objects.get(held_id) if held_id else None
        held_name = held.name if held else held_id
        if open_:
            if held_name is not None:
                raise PreconditionFailed(f"opening the gripper would drop {held_name}; use place to put it down")
            self.gripper(GRIPPER_OPEN, cancel)
            return "gripper open"
        if held_name is not None:
            return f"gripper already closed on {held_name}"
        result = self.gripper(GRIPPER_CLOSED, cancel)
        holding = None if result is None else result.holding
        return f"gripper closed on {holding}" if holding else "gripper closed, holding nothing"

    def _stowed(self) -> bool:
        return bool(np.max(np.abs(self._arm_now() - self.home)) <= STOWED)

    def _stow_if_out(self, cancel: threading.Event) -> None:
        """The arm over the base before the base moves: the routes are planned for the base alone."""
        if not self._stowed():
            self.stow(cancel)

    def stow(self, cancel: threading.Event) -> None:
        """Back to the stowed pose around what is near, holding what the hand holds; first straight
        up a little when the hand is down among things (after a failed grasp, say)."""
        base, q = self._base(), self._arm_now()
        held_id = self.robot.held_object()
        held = self._held if self._held is not None and held_id == self._held.obj.id else None
        seen = self._look()
        scene = self._scene(base, seen, held)
        near = [(o.id, GRIPPER) for o in seen if o.id in self.world.objects and o.on != "gripper"]
        try:
            path = scene.plan(q, self.home, what="stowing the arm")
        except PlanningFailed:
            up = self.arm.kin.forward(q).translation + np.array([0.0, 0.0, BACK_OFF])
            lift = scene.cartesian(q, up, allowed=near, what="backing the hand off")
            self._follow(lift, "backing the hand off", cancel)
            path = scene.plan(lift[-1], self.home, what="stowing the arm")
        self._follow(path, "stowing the arm", cancel)

    # Finding the object

    def _within_reach(self, base: Pose2D, position: Vec3) -> bool:
        return math.hypot(position.x - base.x, position.y - base.y) <= self.world.world.robot.reach

    def locate(
        self, step: PickStep, cancel: threading.Event, note: Note, attempt: int = 1, searched: list[str] | None = None
    ) -> PerceivedObject:
        """Stand where the object can be picked and see it there: at the step's approach pose, or,
        when perception has it elsewhere, found by a search (`search`), then approached. Raises
        PreconditionFailed saying where it looked; `searched` gets each place looked at."""
        searched = [] if searched is None else searched
        # Seen somewhere else since the plan was grounded (a detect before this pick found it): there.
        remembered = self.robot.remembered(step.object_id)
        moved = (
            remembered is not None
            and remembered.on in self.world.furniture
            and math.dist((remembered.position.x, remembered.position.y), (step.position.x, step.position.y))
            > MOVED_SINCE_GROUNDED
        )
        support = step.support_id
        if remembered is not None and moved:
            support = str(remembered.on)
            self.drive_to(self.approach_near(remembered), cancel, attempt=attempt)
        else:
            self.ensure_at(step.approach, cancel, attempt)
        found = self._find_in_view(step.object_id, cancel)
        if found is not None and self._within_reach(self._base(), found.position):
            return found
        if found is None:
            expected = self._surface_name(support)
            searched.append(f"on the {expected}")
            note(f"{step.object_name} is not where it was expected ({expected}); looking for it")
            found = self.search(
                step.object_id, step.object_name, cancel, note, searched, step_scope(step), attempt, {support}
            )
        if not self._within_reach(self._base(), found.position):
            note(f"{step.object_name} is on the {self._surface_name(found.on)}, out of reach: moving closer")
            self.drive_to(self.approach_near(found), cancel, attempt=attempt)
            found = self._seen(step.object_id)
            if found is None:
                raise PreconditionFailed(f"{step.object_name} went out of view moving closer to it")
        return found

    def search(
        self,
        object_id: str,
        name: str,
        cancel: threading.Event,
        note: Note,
        searched: list[str],
        scope: SearchScope | None = None,
        attempt: int = 1,
        skip: Collection[str] = (),
    ) -> PerceivedObject:
        """Look for an object that is not in view, place by place as search.plan_search orders them
        within `[executor.search]` (`scope`, the step's, narrows it), each place appended to
        `searched` once looked at. Every motion is a base goal through safety; the search stops at
        once on cancel or while safety holds the robot still, and a veto or a motion ended by the
        robot side ends it with that reason. Not found: PreconditionFailed naming every place looked
        (those in `searched` already, then the search's), and the bound that stopped it."""
        bounds = self.config.search
        remembered = self.robot.remembered(object_id)
        plan = plan_search(
            self.world,
            self._base(),
            scope=narrowest(bounds.scope, scope),
            max_places=bounds.max_places,
            headings=bounds.headings,
            remembered_on=remembered.on if remembered is not None else None,
            skip=skip,
            clearance=self.config.base_clearance,
            surface_view=bounds.surface_view,
        )
        started = self.clock()
        try:
            return self._search(plan, object_id, name, cancel, note, searched, attempt, started)
        finally:
            self.search_time += self.clock() - started

    def _search(
        self,
        plan: SearchPlan,
        object_id: str,
        name: str,
        cancel: threading.Event,
        note: Note,
        searched: list[str],
        attempt: int,
        started: float,
    ) -> PerceivedObject:
        bounds = self.config.search
        for look in plan.looks:
            self._may_search_on(name, searched, cancel)
            if self.clock() - started > bounds.max_time:
                raise PreconditionFailed(not_found(name, searched, plan, bounds.max_time))
            note(f"looking for {name} {look.place}")
            try:
                found = self._look_from(look, object_id, cancel, attempt)
            except PlanningFailed as exc:
                note(f"not looking {look.place}: {exc}")  # planned, not driven: nothing moved
                continue
            except Canceled:
                raise Canceled(f"searching for {name}{_so_far(searched)} canceled") from None
            except ExecutionError as exc:
                # A veto, an e-stop, a motion ended or aborted: never on to the next place.
                raise type(exc)(f"{exc} (searching for {name}{_so_far(searched)})") from None
            searched.append(look.place)
            if found is not None:
                note(f"found {name} {look.place}")
                return found
        raise PreconditionFailed(not_found(name, searched, plan))

    def _may_search_on(self, name: str, searched: list[str], cancel: threading.Event) -> None:
        if cancel.is_set():
            raise Canceled(f"searching for {name}{_so_far(searched)} canceled")
        stop = self.robot.safety_stop()
        if stop is not None:
            raise Interrupted(f"searching for {name} stopped{_so_far(searched)}: {stop}")

    def _look_from(self, look: Look, object_id: str, cancel: threading.Event, attempt: int) -> PerceivedObject | None:
        """Go where `look` says and look: at each heading of a look around (one the base cannot turn
        to is left out), or at a furniture top (from a little further back too)."""
        unplanned: PlanningFailed | None = None
        if look.surface is not None:
            reached = False
            for pose in look.poses:  # the approach pose, then along the edge of a long top
                try:
                    self.drive_to(pose, cancel, attempt=attempt)
                except PlanningFailed as exc:
                    unplanned = exc
                    continue
                reached = True
                found = self._find_in_view(object_id, cancel)
                if found is not None:
                    return found
            if not reached and unplanned is not None:
                raise unplanned
            return None
        turned = False
        for pose in look.poses:
            if cancel.is_set():
                raise Canceled("looking around canceled")
            try:
                self.drive_to(pose, cancel, attempt=attempt)
            except PlanningFailed as exc:
                unplanned = exc
                continue
            turned = True
            found = self._seen_twice(object_id)
            if found is not None:
                return found
        if not turned and unplanned is not None:
            raise unplanned
        return None

    def _seen(self, object_id: str, new: bool = False) -> PerceivedObject | None:
        return next((o for o in self._look(new) if o.id == object_id), None)

    def _seen_twice(self, object_id: str) -> PerceivedObject | None:
        """The object in the first report after the last motion, or else in the one after: a report
        can be under way while a motion ends (the arm still over the object, say)."""
        return self._seen(object_id) or self._seen(object_id, new=True)

    def _find_in_view(self, object_id: str, cancel: threading.Event) -> PerceivedObject | None:
        """The object as perception sees it from here, or else from LOOK_BACK further back: close to
        the edge of a surface, part of it may lie outside the image, and a part is not reported."""
        found = self._seen_twice(object_id)
        if found is not None:
            return found
        here = self._base()
        back = Pose2D(
            x=here.x - LOOK_BACK * math.cos(here.yaw), y=here.y - LOOK_BACK * math.sin(here.yaw), yaw=here.yaw
        )
        try:
            self.drive_to(back, cancel)
        except PlanningFailed:
            return None  # no room to back off: it is not in view
        return self._seen_twice(object_id)

    def _surface_name(self, surface: str | None) -> str:
        item = self.world.furniture.get(surface or "")
        return item.name if item else "floor"

    def approach_near(self, seen: PerceivedObject) -> Pose2D:
        """The approach pose of the furniture under `seen`, moved along its edge to face it."""
        support = self.world.furniture.get(seen.on or "")
        if support is None:
            raise PreconditionFailed(f"{seen.name} is on the floor, where the arm cannot reach it")
        return self.world.approach_near(support.id, seen.position.x, seen.position.y)

    # Steps

    def pick(
        self,
        step: PickStep,
        cancel: threading.Event,
        attempt: int = 1,
        note: Note = _quiet,
        searched: list[str] | None = None,
    ) -> str:
        if (held_now := self.robot.held_object()) == step.object_id:
            # A try that grasped it and then failed (its lift aborted) left it in the hand: done,
            # once the arm is stowed.
            self._stow_if_out(cancel)
            self._failed.pop(step.object_id, None)
            return f"holding {step.object_name} (in the gripper already)"
        if held_now is not None:
            held = self.world.objects.get(held_now)
            raise PreconditionFailed(f"the gripper already holds {held.name if held else held_now}")
        obj = self.world.objects.get(step.object_id)
        if obj is None:
            # Grounded against another world file (the resolver's config), or by a hostile peer.
            raise PreconditionFailed(
                f"{step.object_name} ({step.object_id}) is not in the executor's world file "
                f"({self.config.world}): it has no shape to plan a grasp of"
            )
        width = narrowest_width(obj)
        if not fits(width, self.grasp_config):
            # Known before anything moves, and no retry makes it fit.
            raise PreconditionFailed(
                f"{step.object_name} is too big for the gripper: {width * 100:.0f} cm across at its narrowest, "
                f"the fingers open to {GRIPPER_MAX_GAP * 100:.0f} cm"
            )
        target = self.locate(step, cancel, note, attempt, searched)
        base, q = self._base(), self._arm_now()
        seen = self._look()
        scene = self._scene(base, seen)
        yaw = target.yaw or 0.0
        failed = self._failed.setdefault(step.object_id, set())
        candidates = grasps(obj, target.position, yaw, base, self.mount, self.grasp_config)
        fresh = [g for g in candidates if g.description not in failed] or candidates
        plan = plan_pick(scene, q, fresh, obj, target.on, q_stow=self.home, cancel=cancel)
        grasp = plan.grasp
        self.gripper(GRIPPER_OPEN, cancel)
        self._follow(plan.to_pregrasp, f"moving above {step.object_name}", cancel)
        self._check_not_moved(step, target, base)
        self._follow(plan.approach, f"reaching {step.object_name}", cancel)
        result = self.gripper(GRIPPER_CLOSED, cancel, object_id=step.object_id)
        holding = None if result is None else result.holding
        in_hand = self._seen(step.object_id)
        if in_hand is None or in_hand.on != "gripper":
            in_hand = self._seen(step.object_id, new=True)  # a report may be under way as the gripper closes
        if holding != step.object_id or in_hand is None or in_hand.on != "gripper":
            failed.add(grasp.description)
            self.gripper(GRIPPER_OPEN, cancel)
            expected = self._map_point(base, (grasp.pose * grasp.object_in_grasp).translation)
            where = (
                "no longer in view"
                if in_hand is None
                else (f"seen {offset_words(expected, in_hand.position, base)} the expected grasp point")
            )
            raise GraspFailed(
                f"{step.object_name} was not in the gripper after closing ({grasp.kind} grasp); it was {where}",
                step.object_name,
            )
        self._held = HeldObject(obj, grasp.object_in_grasp)
        self._follow(plan.lift, f"lifting {step.object_name}", cancel)
        assert plan.to_stow is not None
        self._follow(plan.to_stow, f"stowing {step.object_name}", cancel)
        failed.clear()
        return f"holding {step.object_name} ({grasp.kind} grasp)"

    def _check_not_moved(self, step: PickStep, target: PerceivedObject, base: Pose2D) -> None:
        """The object still where its grasp was planned, as perception sees it with the hand above:
        moved meanwhile (pushed, taken and put back), it is not reached for where it was; a retry
        sees it anew. Hidden under the hand, it is taken as still there (closing checks it)."""
        now = self._seen(step.object_id)
        if now is None or now.on == "gripper":
            return
        moved = math.hypot(now.position.x - target.position.x, now.position.y - target.position.y)
        if moved > MOVED_BEFORE_GRASP:
            raise ExecutionError(
                f"{step.object_name} moved while the arm moved above it: seen "
                f"{offset_words(target.position, now.position, base)} where its grasp was planned; "
                "not reaching for where it was"
            )

    def _map_point(self, base: Pose2D, point: np.ndarray) -> Vec3:
        return arm_to_world(base, self.mount, point)

    def _held_now(self, held_id: str, base: Pose2D, q: np.ndarray) -> HeldObject:
        """How the hand holds `held_id` now: the grasp's orientation remembered from the pick, the
        offset from where perception sees the object (it may have slipped). Perception always reports
        what the hand holds (docs/robot.md): not in the gripper now, it fell out on the way here."""
        obj = self.world.objects[held_id]
        grasp_pose = self.arm.kin.forward(q)
        seen = self._seen_twice(held_id)
        remembered = self._held if self._held is not None and self._held.obj.id == held_id else None
        if seen is None or seen.on != "gripper":
            where = "nowhere in view" if seen is None else f"on the {self._surface_name(seen.on)}"
            raise PreconditionFailed(
                f"{obj.name} is no longer in the gripper: it was as the step began, perception has it {where} now"
            )
        # Upright: the pick kept it so; without a remembered grasp, its heading along the hand's.
        yaw = seen.yaw
        if yaw is None:
            in_arm = grasp_pose * remembered.in_grasp if remembered else grasp_pose
            arm_yaw = math.atan2(float(in_arm.rotation[1, 0]), float(in_arm.rotation[0, 0]))
            yaw = arm_yaw + base.yaw
        centre = object_pose(seen.position, yaw, base, self.mount)
        in_grasp = grasp_pose.inverse() * centre
        if remembered is not None:
            in_grasp = pin.SE3(remembered.in_grasp.rotation, in_grasp.translation)
        return HeldObject(obj, in_grasp)

    def place(self, step: PlaceStep, cancel: threading.Event, attempt: int = 1, note: Note = _quiet) -> str:
        held_id = self.robot.held_object()
        if held_id is None:
            let_go, self._let_go = self._let_go, None
            if let_go is not None and let_go[1] is step and let_go[0] in self.world.objects:
                # A try that let go of it and then failed (its retreat aborted): the hand is empty
                # because it was put down, so whether it was is what perception says.
                self._stow_if_out(cancel)
                return self._check_placed(self.world.objects[let_go[0]], step, cancel)
            raise PreconditionFailed("the gripper holds nothing to place")
        self._let_go = None
        obj = self.world.objects.get(held_id)
        if obj is None:
            raise PreconditionFailed(f"the gripper holds {held_id}, which the world file does not know")
        self.ensure_at(step.approach, cancel, attempt)
        base, q = self._base(), self._arm_now()
        held = self._held_now(held_id, base, q)
        scene = self._scene(base, self._look(), held)
        failed = self._failed.setdefault(held_id, set())
        candidates = placements(obj, held.in_grasp, step.position, base, self.mount, self.grasp_config)
        fresh = [p for p in candidates if p.description not in failed] or candidates
        plan = plan_place(scene, q, fresh, step.surface_name, q_stow=self.home, cancel=cancel)
        self._follow(plan.to_preplace, f"moving {obj.name} above the {step.surface_name}", cancel)
        self._follow(plan.lower, f"lowering {obj.name} onto the {step.surface_name}", cancel)
        self.gripper(GRIPPER_OPEN, cancel)
        self._held = None
        self._let_go = (held_id, step)
        self._follow(plan.retreat, "lifting the hand", cancel)
        assert plan.to_stow is not None
        self._follow(plan.to_stow, "stowing the arm", cancel)
        self._let_go = None
        try:
            return self._check_placed(obj, step, cancel)
        except PostconditionFailed:
            failed.add(plan.placement.description)
            raise

    def _check_placed(self, obj: WorldObject, step: PlaceStep, cancel: threading.Event) -> str:
        """Done means perception sees it on the surface, not that the motions went through."""
        seen = self._find_in_view(obj.id, cancel)
        if seen is None or seen.on != step.surface_id:
            where = "nowhere in view" if seen is None else f"on the {self._surface_name(seen.on)}"
            raise PostconditionFailed(
                f"after placing, perception has {obj.name} {where}, not on the {step.surface_name}"
            )
        # On its side it is still on the surface: only its height tells.
        lower = step.position.z + obj.size.z / 2 - seen.position.z
        if lower > FALLEN_OVER:
            raise PostconditionFailed(
                f"after placing, perception has {obj.name} on the {step.surface_name} but not upright: its "
                f"centre {_cm(lower)} lower than standing, it has fallen over"
            )
        self._failed.pop(obj.id, None)
        return f"placed {obj.name} on the {step.surface_name}"

    def detect(
        self,
        step: DetectStep,
        cancel: threading.Event,
        attempt: int = 1,
        note: Note = _quiet,
        searched: list[str] | None = None,
    ) -> str:
        """Succeeds when perception reports the object: looking now (from a little further back
        too), or else found by a search (`search`; a person is not searched for). A retry looks
        again."""
        searched = [] if searched is None else searched
        seen = self._find_in_view(step.object_id, cancel)
        if seen is None:
            scope = narrowest(self.config.search.scope, step_scope(step))
            if scope == "none" or step.object_id not in self.world.objects:
                unsearched = " (search scope none)" if scope == "none" else ""
                raise PostconditionFailed(f"{step.object_name} is not in view from here{unsearched}")
            note(f"{step.object_name} is not in view from here; looking for it")
            seen = self.search(step.object_id, step.object_name, cancel, note, searched, scope, attempt)
        p = seen.position
        where = f"on the {self._surface_name(seen.on)}" if seen.on != "gripper" else "in the gripper"
        after = f" after looking {', '.join(searched)}" if searched else ""
        return f"{step.object_name} seen {where} at ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}){after}"

    def run(
        self, step: GroundedStep, cancel: threading.Event, attempt: int, note: Note, searched: list[str] | None = None
    ) -> str:
        """One try at a step; what it did, in a few words. A detect or a pick that searches for its
        object appends each place it looked at to `searched`."""
        match step:
            case NavigateStep():
                self.drive_to(step.goal, cancel, step.max_speed, attempt=attempt)
                return f"reached {step.target}"
            case GripperStep():
                return self.operate_gripper(step.open, cancel)
            case PickStep():
                return self.pick(step, cancel, attempt, note, searched)
            case PlaceStep():
                return self.place(step, cancel, attempt, note)
            case DetectStep():
                return self.detect(step, cancel, attempt, note, searched)
            case SayStep():
                # This robot has no speaker; the text is carried in feedback and the recording.
                log.info("say: %s", step.text)
                return f"said: {step.text}"
            case WaitStep():
                if cancel.wait(step.duration):
                    raise Canceled("waiting canceled")  # "WHAT canceled": a timeout says "during WHAT"
                return f"waited {step.duration:g} s"
            case StopStep():
                self.robot.cmd_vel(Twist())
                return "base stopped"
            case _:
                assert_never(step)

    def recover(self, step: GroundedStep, cancel: threading.Event) -> None:
        """Before a retry: the hand open for a pick (unless it holds something) and the arm stowed,
        so the next try starts as a first one would."""
        match step:
            case PickStep():
                if self.robot.held_object() is None:
                    self.gripper(GRIPPER_OPEN, cancel)
            case NavigateStep() | PlaceStep() | DetectStep() | GripperStep() | SayStep() | WaitStep() | StopStep():
                pass
            case _:
                assert_never(step)
        self._stow_if_out(cancel)
