"""The stand-in robot's frozen config: where its ROS 2 side listens, its domain and key style, cmd_vel, camera, stop."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

import msgspec
from msgspec import Meta

from services.ros2.wire import Style
from services.runtime import ConfigError
from services.sim.config import CmdVelSeconds, Hz

DomainId = Annotated[int, Meta(ge=0, le=232)]
DOMAIN_ENV = "ROS_DOMAIN_ID"


class Ros2SimConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[ros2sim]` in the config file. The world, realtime_factor and report rates are `[sim]`'s
    (SimConfig), so one file drives the sim and its stand-in alike."""

    # A Zenoh endpoint of the robot's own ROS 2 network, apart from tether's: where rmw_zenoh's
    # router listens on a real robot, and where the ros2 backend connects.
    listen: Annotated[str, Meta(pattern=r"^[a-z][a-z0-9-]*/\S+$", max_length=300)] = "tcp/127.0.0.1:7447"
    # ROS_DOMAIN_ID in the environment wins over this, as the contract says (domain_id() below); 0 without either.
    domain_id: DomainId | None = None
    style: Style = Style.RMW_ZENOH
    # cmd_vel as geometry_msgs/TwistStamped rather than Twist (what the backend sends).
    stamped_cmd_vel: bool = False
    # Wall seconds a cmd_vel holds; as the sim's, counted in sim time x [sim] realtime_factor, and bounded alike.
    cmd_vel_timeout: CmdVelSeconds = 0.5
    # Each picture renders a frame (about 20 ms) in the sim's renderer process, off the sim thread.
    camera_hz: Hz = 1.0
    # emergency_stop is also a dead-man signal (a twist_mux lock's timeout): the robot stops as on
    # data=true once none has arrived for this long, and before the first; until data=false comes.
    # Wall seconds; 0 turns it off. The backend sends emergency_stop at 20 Hz.
    stop_timeout: Annotated[float, Meta(ge=0.0, le=60.0)] = 0.5


def domain_id(config: Ros2SimConfig, environ: Mapping[str, str]) -> int:
    """The ROS domain: ROS_DOMAIN_ID when set (as every ROS 2 node reads it), else the config's, else 0."""
    raw = environ.get(DOMAIN_ENV, "").strip()
    if not raw:
        return config.domain_id if config.domain_id is not None else 0
    try:
        return msgspec.convert(int(raw), DomainId)
    except (ValueError, msgspec.ValidationError):
        raise ConfigError(f"{DOMAIN_ENV}={raw!r} is not a ROS domain id (an integer from 0 to 232)") from None
