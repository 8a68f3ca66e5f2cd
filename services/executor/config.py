"""Executor configuration: timeouts per stage and how the arm moves."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

Timeout = Annotated[float, Meta(gt=0.0, le=3600.0)]


class ExecutorConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    world: str = "household"
    parse_timeout: Timeout = 5.0
    resolve_timeout: Timeout = 5.0
    check_timeout: Timeout = 5.0
    # Wall-clock bound on one motion (a navigation leg, an arm move, a gripper command).
    motion_timeout: Timeout = 120.0
    # Below the safety limit, so planned trajectories pass its check with margin.
    max_joint_speed: Annotated[float, Meta(gt=0.0, le=3.0)] = 1.0
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
