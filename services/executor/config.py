"""Executor configuration: timeouts and retries per step, how busy goals are handled, how the arm moves."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec
from msgspec import Meta

Timeout = Annotated[float, Meta(gt=0.0, le=3600.0)]
Retries = Annotated[int, Meta(ge=0, le=10)]


class _Table(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class StepTimeouts(_Table):
    """`[executor.timeouts]`: seconds one step may take, counted in motion time: while safety
    pauses the robot for a person nearby the clock stands still, and while it slows the robot the
    clock runs as much slower. A step over its time is canceled and fails (execution)."""

    navigate_to: Timeout = 300.0
    pick: Timeout = 240.0
    place: Timeout = 240.0
    detect: Timeout = 60.0
    gripper: Timeout = 30.0
    say: Timeout = 10.0
    wait: Timeout = 120.0  # a wait step itself lasts at most 60 s
    stop: Timeout = 10.0


class StepRetries(_Table):
    """`[executor.retries]`: how often a step is tried again after a planning, execution or
    postcondition failure, each time after re-detecting what it acts on and planning anew. Never
    after a cancel, a veto or an e-stop."""

    navigate_to: Retries = 2
    pick: Retries = 2
    place: Retries = 2
    detect: Retries = 1
    gripper: Retries = 0
    say: Retries = 0
    wait: Retries = 0
    stop: Retries = 0


class ExecutorConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    world: str = "household"
    parse_timeout: Timeout = 5.0
    resolve_timeout: Timeout = 5.0
    check_timeout: Timeout = 5.0
    timeouts: StepTimeouts = StepTimeouts()
    retries: StepRetries = StepRetries()
    # A plan sent while another runs: rejected, or the running one canceled first (a goal's own
    # `preempt` asks for that too; `tether send --preempt`).
    when_busy: Literal["reject", "preempt"] = "reject"
    # Below the safety limit, so planned trajectories pass its check with margin.
    max_joint_speed: Annotated[float, Meta(gt=0.0, le=3.0)] = 1.0
    max_joint_acceleration: Annotated[float, Meta(gt=0.0, le=20.0)] = 3.0
    # Seconds one planning query (a base path, an arm path) may search before it gives up.
    planning_time: Annotated[float, Meta(gt=0.0, le=30.0)] = 1.0
    # How far the base's footprint keeps from walls and furniture on planned paths (metres): more
    # than the robot's tracking tolerance (services/footprint.py, 3 cm), which safety demands.
    base_clearance: Annotated[float, Meta(ge=0.0, le=0.5)] = 0.04
    # The base counts as at an approach pose within these.
    approach_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.15
    approach_yaw_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.2
    # Heights above the grasp point: where the hand waits before descending, and lifts to after.
    pregrasp_height: Annotated[float, Meta(ge=0.0, le=0.5)] = 0.15
    place_clearance: Annotated[float, Meta(ge=0.0, le=0.2)] = 0.02
    # How far below an object's top the fingertips close at most; objects up to twice this tall
    # are held at their centre. The palm sits about 4 cm above the fingertips: grasping a 10 cm
    # cup at its centre pressed the palm onto its rim and tipped it over between the fingers.
    grasp_depth: Annotated[float, Meta(gt=0.0, le=0.2)] = 0.03
