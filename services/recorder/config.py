"""The recorder's frozen config: where recordings go, how they are named, chunked and flushed."""

from __future__ import annotations

import datetime as dt
import string
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

# Fields a file name pattern may use; both must appear so two robots or two runs never collide.
PATTERN_FIELDS = frozenset({"robot", "stamp"})
STAMP_FORMAT = "%Y%m%dT%H%M%SZ"


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
