"""Races and ordering on the sim's side: goals handed to the sim thread as it shuts down, a cancel that comes
during a step, a grasp repeated on what the hand holds."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import GripperCommandGoal, NavigateToPoseGoal
from schemas.world import World
from services.actionlib import GoalHandle, Outcome
from services.executor.kinematics import ArmKinematics
from services.sim import loop as loop_module
from services.sim.controllers import Controllers
from services.sim.loop import SimLoop
from services.sim.simulation import Simulation
from services.sim.world import Motion
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.unit.test_sim import PREGRASP_HEIGHT, above, approach, drive, gripper, reach
from tests.unit.test_sim import kin as kin  # the fixtures, shared
from tests.unit.test_sim import world as world

WORLD = load_world("household")
FAR = NavigateToPoseGoal(pose=Pose2D(x=10.0, y=1.2, yaw=0.0), max_speed=0.6)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


def handle_for(goal: NavigateToPoseGoal) -> GoalHandle[NavigateToPoseGoal, Any]:
    return GoalHandle(uuid.uuid4().hex, goal, lambda _goal_id, _feedback: None)


def relay_in_thread(loop: SimLoop, handle: GoalHandle[Any, Any]) -> tuple[threading.Thread, list[Outcome[Any]]]:
    outcomes: list[Outcome[Any]] = []

    def run() -> None:
        outcomes.append(loop.relay(lambda controllers: Controllers.navigate(controllers, handle.goal), handle))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, outcomes


def noting_submits(loop: SimLoop) -> threading.Event:
    """An event set whenever something is handed to the sim thread."""
    submitted = threading.Event()
    original = loop.submit

    def submit(command: Callable[[Simulation], None], changes: bool = True) -> bool:
        try:
            return original(command, changes)
        finally:
            submitted.set()

    loop.submit = submit  # type: ignore[method-assign]
    return submitted


def test_a_goal_handed_over_as_the_sim_thread_stops_ends_at_once_and_never_moves(sim: Simulation) -> None:
    loop = SimLoop(sim, 4.0, lambda: None)
    stop = threading.Event()
    submitted = noting_submits(loop)
    handle = handle_for(FAR)
    relays: list[tuple[threading.Thread, list[Outcome[Any]]]] = []

    def last_pass() -> None:
        # After the pass's last drain: the thread is to stop, and a goal's start is handed to it
        # before it gets round to its final drain.
        if relays:
            return
        stop.set()
        relays.append(relay_in_thread(loop, handle))
        assert submitted.wait(5.0), "the goal's start was never handed to the sim thread"

    sim_thread = threading.Thread(target=loop.run, args=(stop, last_pass), daemon=True)
    sim_thread.start()
    sim_thread.join(10.0)
    assert not sim_thread.is_alive()
    relay, outcomes = relays[0]
    relay.join(3.0)
    try:
        assert not relay.is_alive(), "the goal's thread waits for a motion no sim thread will ever step"
        assert outcomes[0].state is GoalState.ABORTED
        assert "shutting down" in outcomes[0].message
        assert sim.controllers.motions == {}
    finally:
        sim.controllers.stop("test over")  # the sim thread is gone: this thread may touch pybullet
        relay.join(5.0)


def test_a_goal_after_the_sim_thread_stopped_is_refused_at_once(
    sim: Simulation, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(loop_module, "START_TIMEOUT", 60.0)
    loop = SimLoop(sim, 4.0, lambda: None)
    stop = threading.Event()
    stop.set()
    loop.run(stop)
    relay, outcomes = relay_in_thread(loop, handle_for(FAR))
    relay.join(5.0)
    try:
        assert not relay.is_alive(), "the goal waited for a sim thread that had stopped"
        assert outcomes[0].state is GoalState.ABORTED
        assert "shutting down" in outcomes[0].message
    finally:
        sim.controllers.stop("test over")
        relay.join(5.0)


def holding_the_cup_above_the_counter(world: World, kin: ArmKinematics) -> Simulation:
    sim = Simulation(world, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    drive(sim, approach(world, "kitchen_counter"))
    cup = sim.scene.object_position("red_cup")
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    reach(sim, kin, cup)
    assert gripper(sim, 0.0).holding == "red_cup"
    return sim


def lifted_and_let_go(sim: Simulation, kin: ArmKinematics, open_to: float) -> None:
    """Lift the hand; once the gripper goal to `open_to` is done, the cup must fall: nothing holds it."""
    cup = sim.scene.object_position("red_cup")
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    held = sim.scene.object_position("red_cup")
    assert gripper(sim, open_to).holding is None
    sim.settle(3.0)
    assert sim.scene.ground_truth().holding is None
    assert sim.scene.object_position("red_cup").z < held.z - 0.05, "let go, the cup still hangs from the hand"


def test_closing_again_on_the_object_held_still_lets_go_of_it_on_open(world: World, kin: ArmKinematics) -> None:
    """A second grasp of what the hand holds must not leave the first grip behind: opening then
    let go of `holding` while a leftover constraint still carried the cup off with the hand."""
    sim = holding_the_cup_above_the_counter(world, kin)
    try:
        assert gripper(sim, 0.0).holding == "red_cup"  # closed again on it: still held, once
        lifted_and_let_go(sim, kin, 0.08)
    finally:
        sim.close()


def test_closing_again_with_a_payload_limit_below_the_held_object_lets_it_slip(
    world: World, kin: ArmKinematics
) -> None:
    sim = holding_the_cup_above_the_counter(world, kin)
    try:
        motion = sim.run(sim.controllers.gripper(GripperCommandGoal(position=0.0, payload_limit=0.1)), timeout=5.0)
        assert "slips out" in motion.message
        assert motion.result is not None and motion.result.holding is None, "it slips out, yet is held"
        cup = sim.scene.object_position("red_cup")
        reach(sim, kin, above(cup, PREGRASP_HEIGHT))
        sim.settle(1.0)
        assert sim.scene.object_position("red_cup").z < cup.z + 0.02, "the hand carried off the cup it let slip"
    finally:
        sim.close()


def test_a_cancel_that_comes_during_a_step_is_carried_out_before_the_next(sim: Simulation) -> None:
    """The sim thread ends a goal asked to stop before its next step, not once the goal's own thread
    next looks (every FEEDBACK_PERIOD: 0.1 s of driving on after the cancel)."""
    loop = SimLoop(sim, 1.0, lambda: None)
    stop = threading.Event()
    handle = handle_for(FAR)
    fed = threading.Event()
    handle._publish_feedback = lambda _goal_id, _feedback: fed.set()  # type: ignore[method-assign]
    ticks_after_cancel: list[float] = []

    def start(controllers: Controllers) -> Motion[Any, Any]:
        motion = Controllers.navigate(controllers, FAR)
        tick = motion.tick  # type: ignore[attr-defined]

        def tick_and_cancel(ctl: Controllers) -> None:
            if handle.should_stop:
                ticks_after_cancel.append(ctl.world.sim_time)
            tick(ctl)
            if fed.is_set():  # the goal's thread has relayed feedback and waits again: the cancel comes
                handle.cancel_requested.set()

        motion.tick = tick_and_cancel  # type: ignore[attr-defined]
        return motion

    outcomes: list[Outcome[Any]] = []
    relay = threading.Thread(target=lambda: outcomes.append(loop.relay(start, handle)), daemon=True)
    sim_thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
    sim_thread.start()
    relay.start()
    relay.join(10.0)
    stop.set()
    sim_thread.join(10.0)
    assert not relay.is_alive() and not sim_thread.is_alive()
    assert outcomes[0].state is GoalState.CANCELED, outcomes[0]
    assert ticks_after_cancel == [], f"the goal drove on for {len(ticks_after_cancel)} steps after its cancel"


def test_a_navigation_checked_from_where_a_still_rolling_base_was_is_refused(sim: Simulation) -> None:
    """A preempting goal starts right after the old one is canceled (the same step, now that the sim
    thread carries out the cancel at once): the base, still braking, is within the 3 cm of where the
    new route was checked from, yet comes to rest several centimetres past it. Refused at once, not
    set off on legs it is already off (then aborted as pushed or blocked)."""
    first = sim.controllers.navigate(FAR)
    for _ in range(round(10.0 * FAST_PHYSICS_HZ)):
        sim.step()
        if sim.controllers.base.actual[0] > 0.45:
            break
    assert sim.controllers.base.actual[0] > 0.45, "the base never got going"
    here = sim.robot.base_pose()  # as safety fills in `start` from odometry
    sim.controllers.cancel(first, GoalState.CANCELED, "preempted")
    second = sim.controllers.navigate(
        NavigateToPoseGoal(pose=Pose2D(x=here.x + 0.5, y=here.y, yaw=here.yaw), max_speed=0.6, start=here)
    )
    assert second.state is GoalState.ABORTED and "checked from" in second.message, second.message
    assert "still moving" in second.message, second.message
    # Once at rest where it stopped, a goal checked from there sets off.
    for _ in range(round(2.0 * FAST_PHYSICS_HZ)):
        sim.step()
    rest = sim.robot.base_pose()
    again = sim.controllers.navigate(
        NavigateToPoseGoal(pose=Pose2D(x=rest.x + 0.5, y=rest.y, yaw=rest.yaw), max_speed=0.6, start=rest)
    )
    assert sim.run(again, timeout=20.0).state is GoalState.SUCCEEDED, again.message
