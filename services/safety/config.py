"""Safety's configuration: limits it enforces and how often it proves it is alive."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta


class SafetyConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    world: str = "household"
    # The design card requires at least 20 Hz; the sim stops after 200 ms without one.
    heartbeat_hz: Annotated[float, Meta(ge=20.0, le=1000.0)] = 50.0
    # Limits may only be tighter than the robot's own (world file); None means the robot's.
    max_linear_speed: Annotated[float, Meta(gt=0.0, le=3.0)] | None = None
    max_angular_speed: Annotated[float, Meta(gt=0.0, le=6.0)] | None = None
    max_joint_speed: Annotated[float, Meta(gt=0.0, le=3.0)] = 1.5
    # Where the operator's reset token lives; None: $TETHER_OPERATOR_TOKEN_FILE or ~/.config/tether.
    operator_token_file: str | None = None
    forward_timeout: Annotated[float, Meta(gt=0.0, le=60.0)] = 5.0
    # cmd_vel is refused if holding it this long would reach a keep-out zone or leave the map.
    cmd_vel_horizon: Annotated[float, Meta(gt=0.0, le=10.0)] = 1.0
    # Older odometry or joint states count as unknown: commands needing them are refused.
    state_max_age: Annotated[float, Meta(gt=0.0, le=10.0)] = 0.5
    # Where the latch survives a restart; None: estop-<robot>.json beside the operator token.
    estop_state_file: str | None = None
