"""The simulator's frozen config: which world, how fast, and how often it reports."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

Hz = Annotated[float, Meta(gt=0.0, le=1000.0)]
WallSeconds = Annotated[float, Meta(gt=0.0, le=60.0)]


class SimConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[sim]` in the config file. Timeouts are wall-clock seconds; rates are per wall second."""

    world: Annotated[str, Meta(min_length=1, max_length=1000)] = "household"
    # Sim seconds per wall second; tests run the sim a few times faster than real time.
    realtime_factor: Annotated[float, Meta(ge=0.1, le=20.0)] = 1.0
    physics_hz: Annotated[float, Meta(ge=60.0, le=2000.0)] = 240.0
    heartbeat_timeout: WallSeconds = 0.2
    # A goal that arrives before safety's first heartbeat (right after start-up, while the peers are
    # still connecting) waits this long for it before it is refused.
    first_heartbeat_wait: WallSeconds = 3.0
    cmd_vel_timeout: WallSeconds = 0.5
    joint_states_hz: Hz = 50.0
    odom_hz: Hz = 50.0
    objects_hz: Hz = 5.0
    humans_hz: Hz = 5.0
