"""Safety's configuration: which policy it enforces, where its state lives, how often it proves it is alive.

The rules themselves (limits, zones, separation, rates) are in the policy file, not here.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta


class SafetyConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    world: str = "household"
    # The policy file (TOML or YAML); None: the default, services/safety/policy.toml.
    policy: Annotated[str, Meta(min_length=1, max_length=4096)] | None = None
    # The design card requires at least 20 Hz; the sim stops after 200 ms without one.
    heartbeat_hz: Annotated[float, Meta(ge=20.0, le=1000.0)] = 50.0
    # Where the operator's reset token lives; None: $TETHER_OPERATOR_TOKEN_FILE or ~/.config/tether.
    operator_token_file: str | None = None
    forward_timeout: Annotated[float, Meta(gt=0.0, le=60.0)] = 5.0
    # Where the latch survives a restart; None: estop-<robot>.json beside the operator token.
    estop_state_file: str | None = None
    # Where the control mode survives a restart; None: mode-<robot>.json beside the operator token.
    mode_state_file: str | None = None
    # Safety's memory of incidents (SQLite, services/safety/incidents.py); None: incidents-<robot>.sqlite
    # beside the e-stop state file. A file that cannot be used is reported, never fatal.
    incident_store: str | None = None
    # The key safety signs robot commands and heartbeats with, shared only with the robot backend
    # (hex, 32 bytes, mode 0600; made on first start). None: $TETHER_ROBOT_KEY_FILE, else
    # robot-<robot>.key beside the operator token.
    robot_key_file: str | None = None
    # Reset attempts per identity (operator name) a minute, at most; more are refused with when to retry.
    max_resets_per_minute: Annotated[int, Meta(ge=1, le=600)] = 5
