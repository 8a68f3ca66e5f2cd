"""An MCAP file of a ROS 2 robot's traffic in the ros2 profile: CDR as received, ros2msg schemas from the typestore."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import Writer

# MAX_CHANNELS, as tether's file: a hostile publisher inventing names cannot grow a file's channels or
# our memory without bound.
from services.recorder.mcapfile import COMPRESSION, LIBRARY, MAX_CHANNELS
from services.ros2.wire import Attachment, Naming, Style

if TYPE_CHECKING:
    from services.ros2.types import RosTypes

log = logging.getLogger(__name__)

SUFFIX = ".ros2.mcap"
METADATA_NAME = "tether_ros2"
# The first two bytes of a sample, its CDR encapsulation: plain CDR, big or little endian, as ROS 2 sends it.
CDR_KINDS = frozenset({b"\x00\x00", b"\x00\x01"})
MAX_WARNINGS = 1024


def ros2_path(tether_path: Path) -> Path:
    """`robot1_20250131T120000Z.mcap` -> `robot1_20250131T120000Z.ros2.mcap`, beside it."""
    return tether_path.with_name(tether_path.stem + SUFFIX)


@dataclass(frozen=True)
class RosTopic:
    """What one Zenoh key carries: a ROS 2 topic (`/cmd_vel`, named as ros2 bag names it) of one type."""

    name: str
    ros_type: str
    type_hash: str


class Skipped(Exception):
    """A sample that has no place in the file; `kind` groups the ones warned about once."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind


class RosKeys:
    """Which topic and type a Zenoh key carries, and each type's ros2msg schema.

    rmw_zenoh keys name both (`0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_…`); bridge keys are the
    bare name, so the types come from `[recorder.ros2.topics]`.
    """

    def __init__(self, types: RosTypes, naming: Naming, topics: Mapping[str, str] | None = None) -> None:
        self.types = types
        self.naming = naming
        self._bridged: dict[str, RosTopic] = {}
        for name, ros_type in (topics or {}).items():
            if not types.known(ros_type):
                raise ValueError(f"topic {name}: unknown ROS 2 type {ros_type!r} (distribution {types.distro})")
            type_hash = types.hash(ros_type)
            topic = RosTopic(naming.qualify(name), ros_type, type_hash)
            self._bridged[naming.topic(name, ros_type, type_hash)] = topic
        self._schemas: dict[str, bytes | None] = {}
        self._lock = threading.Lock()

    def key_exprs(self) -> list[str]:
        """What to subscribe to: the whole domain, or each configured topic's key."""
        if self.naming.style is Style.RMW_ZENOH:
            return [f"{self.naming.domain_id}/**"]
        return sorted(self._bridged)

    def resolve(self, key: str) -> RosTopic:
        """The topic `key` carries; Skipped for a key that names none, or a type without a schema here."""
        if self.naming.style is Style.BRIDGE:
            topic = self._bridged.get(key)
            if topic is None:
                raise Skipped(f"key {key[:200]}", f"{key[:200]!r} is not one of [recorder.ros2.topics]")
            return topic
        parsed = self.naming.parse(key)
        if parsed is None:
            raise Skipped("not an rmw_zenoh topic key", f"{key[:200]!r} is not an rmw_zenoh topic key")
        name, ros_type, type_hash = parsed
        if self.schema(ros_type) is None:
            why = "gives no ros2msg text for" if self.types.known(ros_type) else "does not know"
            raise Skipped(
                f"type {ros_type}", f"the {self.types.distro} typestore {why} {ros_type} (on {name}): no schema for it"
            )
        known = self.types.hash(ros_type)
        if type_hash != known:
            # The bytes follow another definition of the type than the schema we have (another distro?).
            raise Skipped(
                f"type {ros_type} {type_hash}",
                f"{ros_type} on {name} has type hash {type_hash}, the {self.types.distro} typestore's is {known}: "
                "its schema would not describe the bytes",
            )
        return RosTopic(name, ros_type, type_hash)

    def schema(self, ros_type: str) -> bytes | None:
        """The ros2msg text of a type, made once; None when the typestore cannot describe it."""
        with self._lock:
            if ros_type in self._schemas:
                return self._schemas[ros_type]
        schema: bytes | None = None
        if self.types.known(ros_type):
            try:
                schema = self.types.msgdef(ros_type).encode()
            # rosbags' generator raises whatever a definition it cannot write makes it raise (assertions).
            except Exception as exc:
                log.debug("no ros2msg schema for %s: %s", ros_type, exc)
        with self._lock:
            if len(self._schemas) < MAX_CHANNELS:
                self._schemas[ros_type] = schema
        return schema


def publish_time(attachment: bytes | None) -> int | None:
    """The source timestamp of rmw_zenoh's attachment (ns since the epoch); None if absent or not valid."""
    if attachment is None:
        return None
    try:
        stamp = Attachment.decode(attachment).source_timestamp
    except ValueError:
        return None
    return stamp if stamp > 0 else None


@dataclass(frozen=True)
class Ros2Source:
    """The ROS 2 network a recorder records: how keys map to topics, and where it was reached."""

    keys: RosKeys
    endpoint: str
    mode: str = "client"

    def metadata(self) -> dict[str, str]:
        naming = self.keys.naming
        return {
            "endpoint": self.endpoint,
            "mode": self.mode,
            "style": str(naming.style),
            "domain_id": str(naming.domain_id),
            "distro": self.keys.types.distro,
        }


class WarnOnce:
    """Logs the first of each kind at WARNING and the rest at DEBUG, so a noisy robot cannot flood the log."""

    def __init__(self) -> None:
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def __call__(self, kind: str, message: str) -> None:
        with self._lock:
            first = kind not in self._seen and len(self._seen) < MAX_WARNINGS
            if first:
                self._seen.add(kind)
        log.log(logging.WARNING if first else logging.DEBUG, "ROS 2 sample not recorded: %s", message)


class Ros2Recording:
    """Writes each ROS 2 sample as received, on a channel per topic and type, in MCAP's ros2 profile.

    Channel topics are ROS names with the leading slash (`/cmd_vel`), message encoding cdr, schemas
    ros2msg named by the ROS type, as `ros2 bag record -s mcap` writes them, for Foxglove and ros2 bag.
    Thread-safe.
    """

    def __init__(
        self,
        output: str | Path | BinaryIO,
        keys: RosKeys,
        *,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        clock: Callable[[], int] = time.time_ns,
        metadata: Mapping[str, str] | None = None,
        warn: WarnOnce | None = None,
    ) -> None:
        self.path = str(output) if isinstance(output, str | Path) else getattr(output, "name", "<stream>")
        self.keys = keys
        self._clock = clock
        self._warn = warn or WarnOnce()
        self._owns_stream = isinstance(output, str | Path)
        # "x": never over a file that exists.
        self._stream: BinaryIO = open(output, "xb") if isinstance(output, str | Path) else output  # noqa: SIM115
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}  # ROS type -> schema id
        self._channels: dict[tuple[str, str], int] = {}  # (topic, ROS type) -> channel id
        self.messages = 0
        self.skipped = 0
        # Why writing stopped (the disk full), "" while it goes on. As in tether's file, nothing is written
        # after a failed write (no chunk after a torn one): every later sample is skipped and counted,
        # and the recorder starts a new pair of files.
        self.error = ""
        self.finished = False
        self._size_at_finish = 0
        self._writer.start(profile=Profile.ROS2, library=LIBRARY)
        self._writer.add_metadata(METADATA_NAME, dict(metadata or {}))

    def record(self, key: str, payload: bytes, attachment: bytes | None = None, *, log_time: int | None = None) -> bool:
        """Write one sample as it came; False if it was skipped (and why is logged, once per kind)."""
        try:
            topic = self.keys.resolve(key)
            if payload[:2] not in CDR_KINDS or len(payload) < 4:
                raise Skipped(f"not CDR on {topic.name}", f"a sample on {topic.name} is not CDR ({len(payload)} bytes)")
        except Skipped as skip:
            return self._skip(skip)
        sent = publish_time(attachment)
        with self._lock:
            if self.finished or self.error:
                self.skipped += 1
                return False
            channel = self._channels.get((topic.name, topic.ros_type))
            if channel is None and len(self._channels) >= MAX_CHANNELS:
                self.skipped += 1
                self._warn("too many topics", f"{topic.name}: the file has {MAX_CHANNELS} channels already")
                return False
            # Taken under the lock, so receive times rise with the sequence.
            now = self._clock() if log_time is None else log_time
            try:
                if channel is None:
                    channel = self._channels[topic.name, topic.ros_type] = self._register(topic)
                # A full chunk is written here, on the receiving thread.
                self._writer.add_message(
                    channel_id=channel,
                    log_time=now,
                    publish_time=now if sent is None else sent,
                    data=payload,
                    sequence=self.messages,
                )
            except OSError as exc:
                self._failed(exc)
                self.skipped += 1
                return False
            self.messages += 1
        return True

    def _failed(self, exc: OSError) -> None:
        """With the lock held: writing failed (the disk full, read-only, gone); said once."""
        if not self.error:
            self.error = f"cannot write the ROS 2 recording {self.path}: {exc.strerror or exc}"
            log.error("%s; its samples are skipped until the next file; tether's recording goes on", self.error)

    def _skip(self, skip: Skipped) -> bool:
        with self._lock:
            self.skipped += 1
        self._warn(skip.kind, str(skip))
        return False

    def _register(self, topic: RosTopic) -> int:
        schema_id = self._schemas.get(topic.ros_type)
        if schema_id is None:
            data = self.keys.schema(topic.ros_type)
            assert data is not None, "resolve() passes only types with a schema"
            schema_id = self._schemas[topic.ros_type] = self._writer.register_schema(
                name=topic.ros_type, encoding=SchemaEncoding.ROS2, data=data
            )
        # ros2 bag reads the QoS from here when it plays a topic back; empty: its default. The hash is
        # what `ros2 bag info` shows as the topic's type hash.
        metadata = {"offered_qos_profiles": "", "topic_type_hash": topic.type_hash}
        return int(
            self._writer.register_channel(
                topic=topic.name, message_encoding=MessageEncoding.CDR, schema_id=schema_id, metadata=metadata
            )
        )

    def flush(self) -> None:
        """Write the chunk in progress, so a crash loses at most what arrived since. A write that fails
        is `error`, not raised."""
        with self._lock:
            if not self.finished and not self.error:
                try:
                    self._writer.flush()
                except OSError as exc:
                    self._failed(exc)

    def finish(self) -> None:
        """Write the summary and index, and close the file if this recording opened it. Idempotent."""
        with self._lock:
            if self.finished:
                return
            self.finished = True
            try:
                if not self.error:
                    self._writer.finish()
                    self._stream.flush()
                self._size_at_finish = self._stream.tell()
            except OSError as exc:
                self._failed(exc)
            finally:
                # Closed even when the disk refuses the summary: the file is then cut, and recoverable.
                if self._owns_stream:
                    with contextlib.suppress(OSError):
                        self._stream.close()

    @property
    def size(self) -> int:
        with self._lock:
            return self._stream.tell() if not self.finished else self._size_at_finish
