"""The sim's transport with two real Zenoh sessions in one process: fail closed, goals, ground truth, sim/move."""

from __future__ import annotations

import logging
import os
import secrets
import signal
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.robot import NavigateToPoseGoal
from schemas.safety import EstopState, SafetyStatus
from schemas.world import Empty, Moved, MoveEntity
from services.actionlib import ActionClient, GoalHandle, Outcome
from services.errors import CallError, GoalRejected
from services.robotlink import BAD_MAC, NOT_SIGNED, Signer
from services.robotrules import PREEMPT_TIMEOUT, RESET_GRACE
from services.runtime import Node, NodeSettings
from services.safety.config import SafetyConfig
from services.sim import loop as sim_loop_module
from services.sim.config import SimConfig
from services.sim.controllers import STALL_TIME, Controllers
from services.sim.node import SimNode
from services.sim.simulation import Simulation
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.procs import wait_until
from tests.sessions import LOADED_HEARTBEAT_MAX_AGE, LOADED_HEARTBEAT_TIMEOUT, free_port
from tests.watch import Watch


@dataclass
class Rig:
    client: Node
    sim_node: SimNode
    latched: threading.Event
    beating: threading.Event
    speed_scale: float = 1.0  # what the heartbeat carries


@pytest.fixture
def rig() -> Iterator[Rig]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    # The heartbeat's bounds for a loaded machine (tests/sessions.py): `make test` runs these tests at
    # the lowest priority beside others (tests/suite.py), and this process, held off the CPU for 0.5 s,
    # once lost its own heartbeat mid-drive. The bounds are the robot contract's to test, at their defaults.
    config = SimConfig(
        realtime_factor=4.0,
        first_heartbeat_wait=0.5,
        physics_hz=FAST_PHYSICS_HZ,
        heartbeat_timeout=LOADED_HEARTBEAT_TIMEOUT,
        heartbeat_max_age=LOADED_HEARTBEAT_MAX_AGE,
    )
    sim = Simulation(load_world(config.world), physics_hz=config.physics_hz, visuals=False)
    stop, beating, latched = threading.Event(), threading.Event(), threading.Event()
    key = secrets.token_bytes(32)
    with Node("sim", settings) as sim_session, Node("test", settings) as client:
        # The test plays safety: it holds the robot key and signs what it sends to the robot.
        client.signer = Signer(key)
        sim_node = SimNode(sim_session, sim, config, robot_key=key)
        sim_session.declare_alive()
        runner = threading.Thread(target=sim_node.run, args=(stop,), daemon=True)
        runner.start()
        rig = Rig(client, sim_node, latched, beating)

        def heartbeat() -> None:
            seq = 0
            while not stop.wait(0.05):
                if beating.is_set():
                    seq += 1
                    estop = EstopState(latched=latched.is_set(), source="operator", reason="test")
                    status = SafetyStatus(
                        seq=seq, stamp=time.time(), estop=estop, speed_scale=rig.speed_scale, speed_reason="test"
                    )
                    client.publish(keys.HEARTBEAT, status)

        beater = threading.Thread(target=heartbeat, daemon=True)
        beater.start()
        assert not client.wait_alive(["sim"], timeout=10.0)
        try:
            yield rig
        finally:
            stop.set()
            runner.join(5.0)
            beater.join(5.0)
            sim_node.close()
    sim.close()


FAR = NavigateToPoseGoal(pose=Pose2D(x=10.0, y=1.2, yaw=0.0), max_speed=0.6)


def test_goals_are_rejected_until_a_heartbeat_arrives(rig: Rig) -> None:
    navigate = ActionClient(rig.client, keys.ROBOT_NAVIGATE)
    with pytest.raises(GoalRejected, match="no safety heartbeat"):
        navigate.send(FAR)


def wait_for_heartbeat(rig: Rig) -> None:
    rig.beating.set()
    deadline = time.monotonic() + 5.0
    while rig.sim_node.safety_block() is not None and time.monotonic() < deadline:
        time.sleep(0.02)  # polling the heartbeat's arrival with a deadline, not standing in for work
    assert rig.sim_node.safety_block() is None


def test_speed_scale_zero_pauses_navigation_without_aborting_it(rig: Rig) -> None:
    navigate = ActionClient(rig.client, keys.ROBOT_NAVIGATE)
    wait_for_heartbeat(rig)
    odom = Watch(rig.client, keys.ODOM)
    goal = navigate.send(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2, yaw=0.0), max_speed=0.6))
    result = goal.result_future(timeout=30.0)
    assert odom.wait_for(lambda o: o.linear_x > 0.3, timeout=10.0), "the base never got going"
    rig.speed_scale = 0.0
    still = odom.wait_for(lambda o: abs(o.linear_x) < 0.001, timeout=5.0, after=len(odom))
    assert still is not None, "the base did not come to rest"
    # Paused well past the stall time (sim seconds): the goal is neither aborted nor moving.
    paused = len(odom)
    assert odom.wait_for(lambda o: o.sim_time > still.sim_time + STALL_TIME + 1.0, timeout=10.0, after=paused)
    assert not result.done()
    assert max(abs(o.linear_x) for o in odom.messages[paused:]) < 0.001
    assert abs(odom.messages[-1].pose.x - still.pose.x) < 0.005
    rig.speed_scale = 1.0
    outcome = result.result(timeout=30.0)
    assert outcome.state is GoalState.SUCCEEDED, outcome.message
    assert outcome.result is not None and outcome.result.pose.x == pytest.approx(8.0, abs=0.05)


def test_losing_the_heartbeat_stops_the_base_and_aborts_the_goal(rig: Rig) -> None:
    navigate = ActionClient(rig.client, keys.ROBOT_NAVIGATE)
    wait_for_heartbeat(rig)
    odom = Watch(rig.client, keys.ODOM)
    goal = navigate.send(FAR)
    assert odom.wait_for(lambda o: o.linear_x > 0.3, timeout=10.0), "the base never got going"
    rig.beating.clear()
    result = goal.result(timeout=5.0)
    assert result.state is GoalState.ABORTED
    assert "no safety heartbeat for" in result.message
    # The abort is immediate; physics then needs a few steps to bring the base to rest.
    aborted = rig.client.call(keys.GROUND_TRUTH, Empty())
    truth = aborted
    deadline = time.monotonic() + 2.0
    while truth.linear_speed >= 0.01 and time.monotonic() < deadline:
        truth = rig.client.call(keys.GROUND_TRUTH, Empty())
    assert truth.linear_speed < 0.01
    assert truth.sim_time - aborted.sim_time <= 0.1


def test_send_goal_answers_well_within_safetys_forward_timeout(rig: Rig) -> None:
    # Else safety may report a forward failed that the sim then runs (docs/robot.md, Timing).
    forward_timeout = SafetyConfig().forward_timeout
    assert all(server._preempt_timeout == PREEMPT_TIMEOUT for server in rig.sim_node.servers)
    assert 0.5 * forward_timeout > PREEMPT_TIMEOUT + 2 * RESET_GRACE
    assert SimConfig().first_heartbeat_wait + RESET_GRACE < forward_timeout


def hold_the_sim_thread(rig: Rig) -> threading.Event:
    """Keep the sim thread busy until the returned event is set (as a long stall would)."""
    release = threading.Event()
    rig.sim_node.submit(lambda _sim: release.wait(10.0) and None)
    return release


def running_motions(rig: Rig) -> list[str]:
    kinds = rig.sim_node.loop.ask(lambda sim: list(sim.controllers.motions), 5.0)
    assert kinds is not None, "the sim thread did not answer"
    return kinds


def handle_for(goal: NavigateToPoseGoal) -> GoalHandle[NavigateToPoseGoal, object]:
    return GoalHandle(uuid.uuid4().hex, goal, lambda _goal_id, _feedback: None)


def test_a_goal_the_sim_did_not_start_in_time_never_starts_later(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    wait_for_heartbeat(rig)
    monkeypatch.setattr(sim_loop_module, "START_TIMEOUT", 0.2)
    release = hold_the_sim_thread(rig)
    outcome = rig.sim_node._run_goal(Controllers.navigate)(handle_for(FAR))
    assert outcome.state is GoalState.ABORTED and "did not start" in outcome.message
    release.set()
    assert running_motions(rig) == [], "the abandoned goal started, out of reach of any cancel"


def test_a_goal_canceled_before_the_sim_starts_it_never_moves(rig: Rig) -> None:
    wait_for_heartbeat(rig)
    release = hold_the_sim_thread(rig)
    handle = handle_for(FAR)
    outcomes: list[Outcome[Any]] = []
    runner = threading.Thread(target=lambda: outcomes.append(rig.sim_node._run_goal(Controllers.navigate)(handle)))
    runner.start()
    handle.cancel_requested.set()
    release.set()
    runner.join(10.0)
    assert outcomes and outcomes[0].state is GoalState.CANCELED, outcomes
    assert outcomes[0].message == "canceled before it started"
    assert running_motions(rig) == []


def test_a_latched_estop_rejects_goals_naming_who_and_why(rig: Rig) -> None:
    rig.latched.set()
    rig.beating.set()
    navigate = ActionClient(rig.client, keys.ROBOT_NAVIGATE)
    deadline = time.monotonic() + 5.0
    while "e-stop" not in (rig.sim_node.safety_block() or "") and time.monotonic() < deadline:
        time.sleep(0.02)
    with pytest.raises(GoalRejected, match="e-stop latched by operator: test"):
        navigate.send(FAR)


def test_sim_move_replies_where_the_object_came_to_rest_or_why_not_even_without_safety(rig: Rig) -> None:
    # Moving things in the simulated world is not the robot acting: no heartbeat is needed.
    moved = rig.client.call(keys.SIM_MOVE, MoveEntity(id="blue_book", x=7.8, y=2.5), timeout=10.0)
    assert isinstance(moved, Moved), moved
    assert (moved.position.x, moved.position.y, moved.position.z) == pytest.approx((7.8, 2.5, 0.465), abs=0.005)
    truth = rig.client.call(keys.GROUND_TRUTH, Empty())
    book = next(o for o in truth.objects if o.id == "blue_book")
    assert book.on == "coffee_table"
    assert (book.position.x, book.position.y) == pytest.approx((moved.position.x, moved.position.y), abs=0.001)
    refused = rig.client.call(keys.SIM_MOVE, MoveEntity(id="blue_book", x=50.0, y=2.5))
    assert isinstance(refused, ServiceError) and refused.kind is ErrorKind.INVALID_REQUEST, refused
    assert "outside every room" in refused.message


def test_commands_and_heartbeats_without_safetys_mac_are_dropped_and_reported(rig: Rig) -> None:
    rig.latched.set()
    rig.beating.set()
    deadline = time.monotonic() + 5.0
    while "e-stop" not in (rig.sim_node.safety_block() or "") and time.monotonic() < deadline:
        time.sleep(0.02)  # polling the heartbeat's arrival with a deadline
    assert "e-stop" in (rig.sim_node.safety_block() or "")
    settings = rig.client.settings
    with Node("attacker", settings) as attacker, Node("forger", settings) as forger:
        # No key at all: the goal is answered unauthorized, never reaching the action server.
        with pytest.raises(CallError, match="not signed by safety") as refused:
            ActionClient(attacker, keys.ROBOT_NAVIGATE).send(FAR)
        assert refused.value.error.kind is ErrorKind.UNAUTHORIZED
        # Signed, but with another key: an unlatched heartbeat is no heartbeat.
        forger.signer = Signer(secrets.token_bytes(32))
        unlatched = SafetyStatus(seq=1, stamp=time.time(), estop=EstopState(latched=False), speed_scale=1.0)
        deadline = time.monotonic() + 5.0
        while not any(BAD_MAC in text for text, _ in rig.sim_node.link.problems(60.0)):
            assert time.monotonic() < deadline, "the forged heartbeat was never refused"
            forger.publish(keys.HEARTBEAT, unlatched)
            attacker.publish(keys.HEARTBEAT, unlatched)
            assert "e-stop" in (rig.sim_node.safety_block() or ""), "a forged heartbeat unlatched the robot"
            time.sleep(0.01)  # pacing the forgeries
    diagnostics = rig.client.call(keys.ROBOT_DIAGNOSTICS, Empty())
    texts = " | ".join(p.text for p in diagnostics.problems)
    assert "robot/navigate_to_pose/_action/send_goal" in texts and NOT_SIGNED in texts, texts
    assert f"safety/heartbeat: {BAD_MAC}" in texts, texts


def test_a_dead_camera_renderer_stops_detections_and_pictures_but_not_the_robot(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    renderer = rig.sim_node.renderer
    objects = Watch(rig.client, keys.OBJECTS)
    assert objects.wait_for(lambda m: True, timeout=30.0), "no detections from the renderer"
    with caplog.at_level(logging.ERROR, logger="services.sim.renderer"):
        os.kill(renderer.pid, signal.SIGKILL)
        assert wait_until(lambda: renderer.failure is not None, 10.0), "the sim never noticed"
        # Logged once the failure is set, on the thread that noticed it: waited for too.
        logged = wait_until(lambda: any(str(renderer.pid) in r.getMessage() for r in caplog.records), 10.0)
    assert logged, "not logged"
    with pytest.raises(CallError) as refused:
        rig.client.call(keys.CAMERA_IMAGE, Empty(), timeout=5.0)
    assert refused.value.error.kind is ErrorKind.UNAVAILABLE
    assert f"pid {renderer.pid}" in refused.value.error.message
    # The robot is still controlled and reports its state; no detections come any more.
    seen = len(objects)
    navigate = ActionClient(rig.client, keys.ROBOT_NAVIGATE)
    wait_for_heartbeat(rig)
    odom = Watch(rig.client, keys.ODOM)
    goal = navigate.send(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2, yaw=0.0), max_speed=0.6))
    assert odom.wait_for(lambda o: o.linear_x > 0.3, timeout=10.0), "the base never got going"
    goal.cancel()
    assert len(objects) == seen
