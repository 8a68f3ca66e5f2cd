"""The search for an object not in view: the order of places (pure), and the Manipulator carrying it
out against a scripted robot port: bounds, cancel, veto and e-stop end it where they happen."""

from __future__ import annotations

import functools
import itertools
import math
import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest

from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, Pose2D, Vec3
from schemas.plan import DetectStep, PickStep
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Twist
from schemas.world import PerceivedObject
from services.errors import GoalRejected
from services.executor.armplanning import ArmPlanner
from services.executor.config import ExecutorConfig, SearchConfig
from services.executor.errors import Canceled, CommandVetoed, Interrupted, PostconditionFailed, PreconditionFailed
from services.executor.manipulation import Manipulator
from services.executor.navigation import BasePlanner
from services.executor.search import narrowest, not_found, plan_search, step_scope, surface_poses
from services.worldmodel import WorldModel, approach_axes, load_world

WORLD = WorldModel(load_world())
KITCHEN = WORLD.room_pose("kitchen")
COUNTER = WORLD.furniture["kitchen_counter"]
TABLE = WORLD.furniture["kitchen_table"]
HOME = list(WORLD.world.robot.home_joints)
CUP_ON_THE_TABLE = PerceivedObject(
    id="blue_cup", name="blue cup", cls="cup", color="blue", position=Vec3(x=2.5, y=3.7, z=0.8), on="kitchen_table"
)


def room(furniture_id: str) -> str | None:
    return WORLD.room_of(*WORLD.furniture[furniture_id].center)


def plan(here: Pose2D = KITCHEN, **bounds: Any) -> Any:
    args: dict[str, Any] = {"scope": "flat", "max_places": 20, "headings": 4} | bounds
    return plan_search(WORLD, here, **args)


# The order of places


def test_it_looks_around_first_then_the_rooms_surfaces_nearest_first_then_room_by_room() -> None:
    search = plan()
    around, *surfaces = search.looks
    assert around.place == "around in the kitchen" and around.surface is None
    # Three more headings from where it stands, a quarter turn apart: its own heading it saw already.
    assert [(p.x, p.y) for p in around.poses] == [(KITCHEN.x, KITCHEN.y)] * 3
    yaws = [KITCHEN.yaw] + [p.yaw for p in around.poses]
    for a, b in itertools.pairwise(yaws):
        assert math.remainder(b - a, math.tau) == pytest.approx(math.pi / 2, abs=1e-3)
    # The table's approach is nearer the room's centre than the counter's.
    assert [s.surface for s in surfaces[:2]] == ["kitchen_table", "kitchen_counter"]
    assert [s.place for s in surfaces[:2]] == ["on the kitchen table", "on the kitchen counter"]
    assert {s.surface for s in surfaces} == set(WORLD.furniture)
    # Each room's surfaces in one go: a room is never left and come back to.
    rooms = [room(s.surface) for s in surfaces]
    changes = [r for before, r in itertools.pairwise(rooms) if r != before]
    assert len(changes) == len(set(rooms)) - 1, rooms
    # A top is looked at from its approach pose first; a long one then from along its edge.
    assert all(s.poses[0] == WORLD.furniture[s.surface].approach for s in surfaces if s.surface)
    assert (search.left_out, search.out_of_scope) == (0, 0)


def test_where_memory_last_saw_it_comes_first_among_the_rooms_surfaces() -> None:
    surfaces = [s.surface for s in plan(remembered_on="kitchen_counter").looks[1:3]]
    assert surfaces == ["kitchen_counter", "kitchen_table"]
    # Remembered in another room: first once the search leaves the kitchen.
    other = [s.surface for s in plan(remembered_on="shelf").looks[1:]]
    assert other[:3] == ["kitchen_table", "kitchen_counter", "shelf"]


def test_scope_room_stays_in_the_room_and_none_looks_nowhere() -> None:
    search = plan(scope="room")
    places = [s.place for s in search.looks]
    assert places == ["around in the kitchen", "on the kitchen table", "on the kitchen counter"]
    assert search.out_of_scope == len(WORLD.furniture) - 2
    assert "other rooms not searched" in not_found("blue cup", [s.place for s in search.looks], search)
    nothing = plan(scope="none")
    assert nothing.looks == []
    assert not_found("blue cup", [], nothing) == "blue cup not found: looked nowhere; no search (search scope none)"


def test_the_places_are_bounded_and_say_how_many_were_left_out() -> None:
    search = plan(max_places=2)
    assert len(search.looks) == 2
    assert search.left_out == 1 + len(WORLD.furniture) - 2
    reason = not_found("apple", [s.place for s in search.looks], search)
    assert reason == (
        "apple not found: looked around in the kitchen, on the kitchen table; "
        f"{search.left_out} more place(s) not visited (the search visits at most 2)"
    )


def test_where_the_base_cannot_turn_it_looks_around_from_the_rooms_pose() -> None:
    # At the counter the base stands too close to it to turn round.
    search = plan(COUNTER.approach, skip={"kitchen_counter"})
    around = search.looks[0]
    assert around.place == "around in the kitchen"
    assert [(p.x, p.y) for p in around.poses] == [(KITCHEN.x, KITCHEN.y)] * 4
    assert around.poses[0].yaw == pytest.approx(KITCHEN.yaw, abs=1e-3)
    # The counter was looked at from its approach pose already: only from along it, towards its ends.
    along = next(s for s in search.looks if s.surface == "kitchen_counter")
    assert along.place == "along the kitchen counter" and COUNTER.approach not in along.poses
    short = plan(WORLD.furniture["chair"].approach, skip={"chair"})
    assert "chair" not in {s.surface for s in short.looks}


@pytest.mark.parametrize("furniture", ["kitchen_counter", "kitchen_table", "bed", "shelf", "coffee_table", "chair"])
def test_a_long_top_is_looked_at_from_along_its_edge_so_its_ends_are_in_view(furniture: str) -> None:
    item = WORLD.furniture[furniture]
    poses = surface_poses(WORLD, item, 1.2)
    _, along = approach_axes(item)
    length = (item.size.x, item.size.y)[along]
    assert poses[0] == item.approach
    if length <= 1.2:
        assert poses == (item.approach,)
        return
    # Two more, facing the top as the approach pose does, at the same distance from its edge, each
    # moved towards one end so that the 1.2 m it takes in reaches that end.
    assert len(poses) == 3
    centre = item.center[along]
    ends = sorted((p.x, p.y)[along] for p in poses[1:])
    assert ends == pytest.approx([centre - (length - 1.2) / 2, centre + (length - 1.2) / 2], abs=1e-3)
    for pose in poses[1:]:
        assert pose.yaw == item.approach.yaw
        assert (pose.x, pose.y)[1 - along] == pytest.approx((item.approach.x, item.approach.y)[1 - along])


def test_a_step_narrows_the_configured_scope_never_widens_it() -> None:
    assert narrowest("flat", "room") == "room"
    assert narrowest("room", "flat") == "room"
    assert narrowest("room", None) == "room"
    assert narrowest("flat", "none") == "none"
    assert step_scope(SimpleNamespace(search="room")) == "room"
    assert step_scope(SimpleNamespace(search="everywhere")) is None
    assert step_scope(DetectStep(object_id="blue_cup", object_name="blue cup")) is None


# The search carried out


class SearchRobot:
    """Drives to each goal pose at once; perception reports the object while `sees(pose)` holds.
    `on_goal(n, goal)` may answer the n-th goal (from 0) instead: a ResultResponse, or raise."""

    def __init__(
        self,
        sees: Callable[[Pose2D], bool],
        start: Pose2D = KITCHEN,
        on_goal: Callable[[int, NavigateToPoseGoal], ResultResponse[Any] | None] | None = None,
        remembered_on: str | None = None,
    ) -> None:
        self.sees = sees
        self.pose = start
        self.on_goal = on_goal
        self.remembered_on = remembered_on
        self.goals: list[NavigateToPoseGoal] = []
        self.stop: str | None = None

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        n = len(self.goals)
        self.goals.append(goal)
        answer = self.on_goal(n, goal) if self.on_goal is not None else None
        if answer is not None:
            return answer
        self.pose = goal.pose
        return ResultResponse(goal_id="g", state=GoalState.SUCCEEDED)

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        raise AssertionError("a search moves no arm")

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        raise AssertionError("a search moves no gripper")

    def cmd_vel(self, twist: Twist) -> None:
        pass

    def base_pose(self) -> Pose2D | None:
        return self.pose

    def arm_positions(self) -> list[float] | None:
        return HOME

    def held_object(self) -> str | None:
        return None

    def look(self, timeout: float, *, new: bool = False) -> list[PerceivedObject] | None:
        if not self.sees(self.pose):
            return []
        return [CUP_ON_THE_TABLE]

    def safety_stop(self) -> str | None:
        return self.stop

    def speed_scale(self) -> float:
        return 1.0

    def people(self) -> list[Pose2D]:
        return []

    def remembered(self, object_id: str) -> PerceivedObject | None:
        if self.remembered_on is None:
            return None
        x, y = WORLD.furniture[self.remembered_on].center
        where = Vec3(x=x, y=y, z=0.8)
        return PerceivedObject(id=object_id, name="", cls="", color="", position=where, on=self.remembered_on)


@functools.cache
def planners() -> tuple[ArmPlanner, BasePlanner]:
    return ArmPlanner(WORLD), BasePlanner(WORLD)


def manipulator(robot: SearchRobot, **search: Any) -> Manipulator:
    arm, base = planners()
    return Manipulator(robot, arm, base, WORLD, ExecutorConfig(search=SearchConfig(**search)))


DETECT = DetectStep(object_id="blue_cup", object_name="blue cup")


def facing_north(pose: Pose2D) -> bool:
    return abs(math.remainder(pose.yaw - math.pi / 2, math.tau)) < 0.1


def at(target: Pose2D) -> Callable[[Pose2D], bool]:
    return lambda pose: math.dist((pose.x, pose.y), (target.x, target.y)) < 0.05


def never(pose: Pose2D) -> bool:
    return False


def test_detect_turns_round_and_finds_what_is_behind_it() -> None:
    robot = SearchRobot(facing_north)
    notes: list[str] = []
    searched: list[str] = []
    message = manipulator(robot).detect(DETECT, threading.Event(), note=notes.append, searched=searched)
    assert searched == ["around in the kitchen"]
    assert message.endswith("after looking around in the kitchen") and "on the kitchen table" in message
    assert "blue cup is not in view from here; looking for it" in notes
    # Backed off to look again (0.3 m), then turned in place: never left the spot it backed to.
    turns = robot.goals[1:]
    assert turns and all(math.dist((g.pose.x, g.pose.y), (KITCHEN.x - 0.3, KITCHEN.y)) < 1e-6 for g in turns)


def test_nowhere_to_be_found_fails_naming_every_place_looked_in_order() -> None:
    robot = SearchRobot(never)
    searched: list[str] = []
    with pytest.raises(PreconditionFailed) as failed:
        manipulator(robot, scope="room").detect(DETECT, threading.Event(), searched=searched)
    assert searched == ["around in the kitchen", "on the kitchen table", "on the kitchen counter"]
    assert str(failed.value) == (
        "blue cup not found: looked around in the kitchen, on the kitchen table, on the kitchen counter; "
        "other rooms not searched (search scope room)"
    )
    # Nothing outside the kitchen was driven to.
    assert {WORLD.room_of(g.pose.x, g.pose.y) for g in robot.goals} == {"kitchen"}


def test_the_search_stops_at_its_place_bound() -> None:
    robot = SearchRobot(never)
    with pytest.raises(PreconditionFailed, match=r"looked around in the kitchen; \d+ more place\(s\) not visited"):
        manipulator(robot, max_places=1).detect(DETECT, threading.Event())
    assert all(WORLD.room_of(g.pose.x, g.pose.y) == "kitchen" for g in robot.goals)


def test_the_search_stops_at_its_time_bound() -> None:
    robot = SearchRobot(never)
    m = manipulator(robot, max_time=100.0)
    ticks = iter(range(0, 10_000, 60))  # each reading of the clock a minute later
    m.clock = lambda: float(next(ticks))
    with pytest.raises(PreconditionFailed, match="the search stopped after its 100 s") as failed:
        m.detect(DETECT, threading.Event())
    assert "looked around in the kitchen" in str(failed.value)
    assert "on the kitchen counter" not in str(failed.value)


def test_a_step_scope_none_does_not_search() -> None:
    robot = SearchRobot(never)
    m = manipulator(robot)
    with pytest.raises(PreconditionFailed, match=r"^blue cup not found: looked nowhere; no search"):
        m.search("blue_cup", "blue cup", threading.Event(), lambda _: None, [], scope="none")
    assert robot.goals == []
    with pytest.raises(PostconditionFailed, match=r"not in view from here \(search scope none\)"):
        manipulator(robot, scope="none").detect(DETECT, threading.Event())


def test_a_cancel_stops_the_search_where_it_is() -> None:
    cancel = threading.Event()

    def cancel_on_third(n: int, goal: NavigateToPoseGoal) -> ResultResponse[Any] | None:
        if n == 2:
            cancel.set()
            return ResultResponse(goal_id="g", state=GoalState.CANCELED)
        return None

    robot = SearchRobot(never, on_goal=cancel_on_third)
    with pytest.raises(Canceled, match=r"^searching for blue cup canceled$"):
        manipulator(robot).detect(DETECT, cancel)
    assert len(robot.goals) == 3, "no goal after the cancel"


def test_a_veto_ends_the_search_with_its_reason() -> None:
    def veto_the_table(n: int, goal: NavigateToPoseGoal) -> ResultResponse[Any] | None:
        if goal.pose == TABLE.approach:
            raise GoalRejected("a person is within 0.5 m of the path", ErrorKind.VETOED)
        return None

    robot = SearchRobot(never, on_goal=veto_the_table)
    with pytest.raises(CommandVetoed) as vetoed:
        manipulator(robot).detect(DETECT, threading.Event())
    assert str(vetoed.value) == (
        "navigation: a person is within 0.5 m of the path (searching for blue cup after looking around in the kitchen)"
    )
    assert robot.goals[-1].pose == TABLE.approach, "nothing sent after the veto"


def test_an_estop_during_a_motion_or_between_places_ends_the_search() -> None:
    robot: SearchRobot

    def estop_on_second(n: int, goal: NavigateToPoseGoal) -> ResultResponse[Any] | None:
        if n == 1:
            robot.stop = "e-stop latched by operator: test"
            return ResultResponse(goal_id="g", state=GoalState.CANCELED, message="e-stop")
        return None

    robot = SearchRobot(never, on_goal=estop_on_second)
    with pytest.raises(Interrupted, match="canceled by the robot side: e-stop"):
        manipulator(robot).detect(DETECT, threading.Event())
    assert len(robot.goals) == 2

    # Latched while the base stood still between two places: not one more goal.
    def estop_after_turning(n: int, goal: NavigateToPoseGoal) -> ResultResponse[Any] | None:
        if n == 3:
            robot.stop = "e-stop latched by operator: test"
        return None

    robot = SearchRobot(never, on_goal=estop_after_turning)
    with pytest.raises(Interrupted, match="stopped after looking around in the kitchen: e-stop latched"):
        manipulator(robot).detect(DETECT, threading.Event())
    assert len(robot.goals) == 4  # the back-off, three turns


PICK_FROM_THE_COUNTER = PickStep(
    object_id="blue_cup",
    object_name="blue cup",
    position=Vec3(x=2.5, y=0.5, z=0.95),
    mass=0.25,
    support_id="kitchen_counter",
    approach=COUNTER.approach,
)


def test_a_pick_searches_the_same_way_from_where_it_expected_the_object() -> None:
    robot = SearchRobot(at(TABLE.approach), start=COUNTER.approach)
    searched: list[str] = []
    notes: list[str] = []
    found = manipulator(robot).locate(PICK_FROM_THE_COUNTER, threading.Event(), notes.append, searched=searched)
    assert found.on == "kitchen_table"
    # Around (from the room's pose: no room to turn at the counter), then the room's tops nearest
    # first: the counter again from along its edge, then the table.
    assert searched == [
        "on the kitchen counter",
        "around in the kitchen",
        "along the kitchen counter",
        "on the kitchen table",
    ]
    assert "blue cup is not where it was expected (kitchen counter); looking for it" in notes
    assert robot.pose == TABLE.approach


def test_a_pick_goes_first_where_memory_saw_the_object_since_the_plan_was_grounded() -> None:
    # A detect before the pick saw it on the table: the pick goes there, no search.
    robot = SearchRobot(at(TABLE.approach), start=COUNTER.approach, remembered_on="kitchen_table")
    searched: list[str] = []
    found = manipulator(robot).locate(PICK_FROM_THE_COUNTER, threading.Event(), lambda _: None, searched=searched)
    assert found.on == "kitchen_table" and searched == []
    assert [g.pose for g in robot.goals] == [TABLE.approach]
