"""The recorder's frozen config: where recordings go, how they are named, chunked and flushed, and the
ROS 2 network it also records, if any."""

from __future__ import annotations

import datetime as dt
import os
import string
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from services.ros2.wire import Style, qualify

# Fields a file name pattern may use; both must appear so two robots or two runs never collide.
PATTERN_FIELDS = frozenset({"robot", "stamp"})
STAMP_FORMAT = "%Y%m%dT%H%M%SZ"
# Where rmw_zenoh's router listens on a ROS 2 robot.
ROS2_DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ROS_DOMAIN_ENV = "ROS_DOMAIN_ID"
MAX_DOMAIN_ID = 232

RosTypeName = Annotated[str, Meta(pattern=r"^[A-Za-z][A-Za-z0-9_]*/(msg|srv|action)/[A-Za-z][A-Za-z0-9_]*$")]


class Ros2RecordConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The `[recorder.ros2]` table: the robot's own ROS 2 network, recorded next to tether's traffic."""

    # The robot's Zenoh router (rmw_zenoh) or zenoh-bridge-ros2dds, as a Zenoh locator.
    endpoint: Annotated[str, Meta(pattern=r"^[a-z][a-z0-9-]*/.+$")] = ROS2_DEFAULT_ENDPOINT
    mode: Literal["client", "peer"] = "client"
    # None: ROS_DOMAIN_ID from the environment, else 0 (see `domain`).
    domain_id: Annotated[int, Meta(ge=0, le=MAX_DOMAIN_ID)] | None = None
    style: Style = Style.RMW_ZENOH
    # The typestore the schemas come from.
    distro: Literal["humble", "iron", "jazzy", "kilted"] = "jazzy"
    # Bridge keys are bare names: each topic to record, with its ROS type ("/odom" = "nav_msgs/msg/Odometry").
    topics: dict[str, RosTypeName] = {}

    def __post_init__(self) -> None:
        if self.style is Style.BRIDGE and not self.topics:
            raise ValueError(
                'style "bridge" needs [recorder.ros2.topics]: bridge keys carry no type, so name each topic '
                'and its ROS type (odom = "nav_msgs/msg/Odometry")'
            )
        if self.style is Style.RMW_ZENOH and self.topics:
            raise ValueError('topics is for style "bridge"; rmw_zenoh keys carry their type and every topic is kept')
        for name in self.topics:
            try:
                qualify(name)
            except ValueError as exc:
                raise ValueError(f"topics: {exc}") from None

    def domain(self, environ: Mapping[str, str] = os.environ) -> int:
        """The ROS domain to record, as the ros2 backend takes it: ROS_DOMAIN_ID, else domain_id, else 0."""
        value = environ.get(ROS_DOMAIN_ENV, "").strip()
        if not value:
            return 0 if self.domain_id is None else self.domain_id
        if not value.isdigit() or int(value) > MAX_DOMAIN_ID:
            raise ValueError(f"{ROS_DOMAIN_ENV}={value!r} is not a ROS domain id (0 to {MAX_DOMAIN_ID})")
        return int(value)


class RecorderConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The `[recorder]` table of a tether config file."""

    output_dir: Annotated[str, Meta(min_length=1)] = "recordings"
    # `{robot}` is the robot name, `{stamp}` the UTC start time (20250131T120000Z).
    file_pattern: Annotated[str, Meta(min_length=1, max_length=200)] = "{robot}_{stamp}.mcap"
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    # Messages are compressed per chunk; a chunk is written when it reaches this size or on flush.
    chunk_size: Annotated[int, Meta(ge=1024, le=64 * 1024 * 1024)] = 1024 * 1024
    # At most this much is lost if the recorder is killed without a chance to finish the file.
    flush_interval: Annotated[float, Meta(gt=0.0, le=3600.0)] = 1.0
    # A new file is started when the current one reaches this size or age (None, from code only: never).
    max_file_bytes: Annotated[int, Meta(ge=64 * 1024)] | None = 1024 * 1024 * 1024
    max_file_seconds: Annotated[float, Meta(ge=1.0)] | None = 3600.0
    # Also record a ROS 2 robot's own traffic, into `<stem>.ros2.mcap` beside each file.
    ros2: Ros2RecordConfig | None = None

    def __post_init__(self) -> None:
        # msgspec turns a ValueError here into a ValidationError naming the field.
        try:
            fields = {name for _, name, _, _ in string.Formatter().parse(self.file_pattern) if name is not None}
        except ValueError as exc:
            raise ValueError(f"file_pattern {self.file_pattern!r} is not a valid pattern: {exc}") from None
        if fields != PATTERN_FIELDS:
            raise ValueError(
                f"file_pattern {self.file_pattern!r} must use exactly the fields {{robot}} and {{stamp}}, "
                f"not {sorted(fields)}"
            )
        if "/" in self.file_pattern or "\\" in self.file_pattern:
            raise ValueError(f"file_pattern {self.file_pattern!r} must be a file name; put directories in output_dir")

    def path_for(self, robot: str, started: dt.datetime) -> Path:
        """The recording's path for `robot`, started at the aware datetime `started`."""
        stamp = started.astimezone(dt.UTC).strftime(STAMP_FORMAT)
        return Path(self.output_dir) / self.file_pattern.format(robot=robot, stamp=stamp)
