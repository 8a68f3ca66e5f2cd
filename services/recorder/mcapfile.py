"""An MCAP file of tether traffic: one json channel per key, each with the JSON Schema of its message type."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, BinaryIO

import msgspec
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from schemas import keys
from schemas.common import DECODE_ERRORS
from services.recorder import scene3d

log = logging.getLogger(__name__)

PROFILE = ""  # no well-known profile fits; json + jsonschema is what Foxglove reads
LIBRARY = "tether recorder"
# A key outside the known topics still gets a channel; its schema accepts any JSON value.
PERMISSIVE_SCHEMA_NAME = "any"
PERMISSIVE_SCHEMA = b"{}"

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
# The metadata record every file carries, and the attachment names of the files it was recorded with.
METADATA_NAME = "tether"
WORLD_ATTACHMENT = "world"
POLICY_ATTACHMENT = "policy"
MEDIA_TYPES = {".yaml": "application/yaml", ".yml": "application/yaml", ".toml": "application/toml"}
# The Zenoh attachments of signed messages (safety's MAC on robot commands and heartbeats,
# services/robotlink.py), each the message after the one it belongs to, on the channel
# `tether/<robot>/_robot_link`: JSON {"seq": the message's sequence, "attachment": hex}. No key
# is published there: the reader puts each back on its message, so replay and the timeline never see it.
LINK_SUFFIX = "/_robot_link"


# The warning for keys past MAX_CHANNELS, once per file (in the set of keys warned about).
CHANNELS_FULL = "<channels>"


def link_channel(robot: str) -> str:
    return keys.prefix(robot) + LINK_SUFFIX


def is_link_channel(topic: str) -> bool:
    return topic.startswith(keys.ROOT + "/") and topic.endswith(LINK_SUFFIX) and topic.count("/") == 2


# A longer attachment is not the robot link's (its is services.robotlink.ATTACHMENT_BYTES): not kept.
MAX_ATTACHMENT = 256
# A record longer than this is not one the recorder writes: the reader refuses it (a corrupt or hostile
# length) before reading it into memory. A chunk holds at most its chunk_size and one message more.
RECORD_SIZE_LIMIT = 128 * 1024 * 1024
# Room left in a chunk's limit for its framing, indexes and the messages before a big one (bytes).
CHUNK_MARGIN = 1024 * 1024
# Keys recorded in one file at most (MCAP channel ids are 16-bit; a peer inventing keys must not
# exhaust them, nor the index): the messages of further keys are dropped and counted, as the twin does.
MAX_CHANNELS = 4096


def link_record(sequence: int, attachment: bytes) -> bytes:
    """The link channel's record of the attachment of the message of `sequence` (written right after it)."""
    return b'{"seq":%d,"attachment":"%s"}' % (sequence, attachment.hex().encode())


def link_attachment(data: bytes, sequence: int) -> bytes | None:
    """The attachment in a link channel's record, if it belongs to the message of `sequence`."""
    try:
        link = json.loads(data)
        if not isinstance(link, dict) or link.get("seq") != sequence:
            return None
        attachment = bytes.fromhex(str(link.get("attachment", "")))
    except (ValueError, RecursionError):
        return None
    return attachment if len(attachment) <= MAX_ATTACHMENT else None


def version() -> str:
    try:
        return metadata.version("tether")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class SourceFile:
    """A file the robot ran with (world, policy), kept in the recording byte for byte."""

    path: Path
    data: bytes

    @classmethod
    def read(cls, path: Path) -> SourceFile:
        return cls(path, path.read_bytes())

    @property
    def hash(self) -> str:
        # The same digest safety puts in every heartbeat and decision (policy_hash).
        return "sha256:" + hashlib.sha256(self.data).hexdigest()


@dataclass(frozen=True)
class Provenance:
    """What a recording was made with: written as a metadata record and attachments in every file."""

    robot: str
    world: SourceFile | None = None
    policy: SourceFile | None = None

    def metadata(self, started_ns: int, part: int, run: str, elapsed_ns: int | None = None) -> dict[str, str]:
        data = {
            "robot": self.robot,
            "run": run,
            "started_ns": str(started_ns),
            "part": str(part),
            "version": version(),
        }
        if elapsed_ns is not None:
            data["elapsed_ns"] = str(elapsed_ns)
        for name, source in ((WORLD_ATTACHMENT, self.world), (POLICY_ATTACHMENT, self.policy)):
            if source is not None:
                data[name] = str(source.path)
                data[f"{name}_hash"] = source.hash
        return data

    def attachments(self) -> list[tuple[str, SourceFile]]:
        return [(n, s) for n, s in ((WORLD_ATTACHMENT, self.world), (POLICY_ATTACHMENT, self.policy)) if s is not None]


_SCHEMAS: dict[Any, tuple[str, bytes]] = {}


def json_schema(type_: Any) -> tuple[str, bytes]:
    """The schema name and JSON Schema document for a message type, its root inlined for viewers."""
    known = _SCHEMAS.get(type_)
    if known is None:
        known = _SCHEMAS[type_] = _make_json_schema(type_)
    return known


def _make_json_schema(type_: Any) -> tuple[str, bytes]:
    document: dict[str, Any] = msgspec.json.schema(type_)
    defs: dict[str, Any] = document.get("$defs", {})
    ref = document.get("$ref", "")
    root_name = ref.removeprefix("#/$defs/")
    if ref.startswith("#/$defs/") and root_name in defs:
        # Some viewers only look at the root; keep $defs for the nested $refs.
        document = {**defs[root_name], "$defs": defs}
    name = str(document.get("title") or getattr(type_, "__name__", repr(type_)))
    return name, json.dumps(document, separators=(",", ":")).encode()


class Recording:
    """Writes each (key, JSON payload) pair as an MCAP message on the key's own channel; thread-safe.

    A payload that is not JSON is dropped and counted: a `json` channel must hold JSON or readers
    choke on the whole file. Payloads are not checked against their schema: a message of the wrong
    shape is exactly what an incident review needs to see.
    """

    def __init__(
        self,
        output: str | Path | BinaryIO,
        robot: str,
        *,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        clock: Callable[[], int] = time.time_ns,
        provenance: Provenance | None = None,
        part: int = 0,
        run: str | None = None,
        elapsed_ns: int | None = None,
    ) -> None:
        """`elapsed_ns`: how long the run had been going when this part started, on a clock that never
        steps (the recorder's monotonic clock): the reader orders the parts by it, not by wall times."""
        self.robot = robot
        self.path = str(output) if isinstance(output, str | Path) else getattr(output, "name", "<stream>")
        self._clock = clock
        self._stream: BinaryIO
        self._owns_stream = isinstance(output, str | Path)
        # "x": never over a file that exists (two recorders starting in the same second).
        self._stream = open(output, "xb") if isinstance(output, str | Path) else output  # noqa: SIM115
        try:
            self._begin(robot, compression, chunk_size, clock, provenance, part, run, elapsed_ns)
        except BaseException:
            # Not a file's beginning left behind (the disk full: a restart after each made one more).
            if self._owns_stream:
                with contextlib.suppress(OSError):
                    self._stream.close()
                with contextlib.suppress(OSError):
                    Path(self.path).unlink()
            raise

    def _begin(
        self,
        robot: str,
        compression: str,
        chunk_size: int,
        clock: Callable[[], int],
        provenance: Provenance | None,
        part: int,
        run: str | None,
        elapsed_ns: int | None,
    ) -> None:
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self._lock = threading.Lock()
        self._schemas: dict[tuple[str, bytes], int] = {}  # (name, document) -> schema id
        self._channels: dict[str, int] = {}  # key -> channel id
        self._link_channel: int | None = None
        self._link_key = link_channel(robot)
        self._warned: set[str] = set()
        self.started_ns = clock()
        self.messages = 0
        self.dropped = 0
        # A message bigger than this would make a chunk the reader refuses, taking its neighbours along.
        self.max_payload = RECORD_SIZE_LIMIT - chunk_size - CHUNK_MARGIN
        # Why writing stopped (the disk full, the file gone), "" while it goes on: then every message is
        # dropped and counted, the rest of the chunk in memory never written.
        self.error = ""
        self.finished = False
        self._size_at_finish = 0
        self._writer.start(profile=PROFILE, library=LIBRARY)
        # Every known schema made now, not on a key's first message: a burst of work on the
        # receiving thread there would delay that message and the ones queued behind it.
        for topic in keys.TOPICS:
            json_schema(topic.type)
        provenance = provenance or Provenance(robot)
        # The parts one recorder writes share a run id: only those are read back as one.
        self.run = run or uuid.uuid4().hex
        self._writer.add_metadata(METADATA_NAME, provenance.metadata(self.started_ns, part, self.run, elapsed_ns))
        for name, source in provenance.attachments():
            self._writer.add_attachment(
                log_time=self.started_ns,
                create_time=self.started_ns,
                name=f"{name}/{source.path.name}",
                media_type=MEDIA_TYPES.get(source.path.suffix, "application/octet-stream"),
                data=source.data,
            )
        # Foxglove's scene, frames and log beside the traffic (services/recorder/scene3d.py), so the file
        # shows the incident in Foxglove's 3D and Log panels; counted apart from the traffic.
        self.derived = 0
        self._derived_channels: dict[str, int] = {}
        self._derive = scene3d.Derived(robot, self._scene(provenance))
        if self._derive.scene is not None:
            self._write_derived(scene3d.SCENE_TOPIC, self._derive.scene.static(self.started_ns / 1e9), self.started_ns)

    @staticmethod
    def _scene(provenance: Provenance) -> scene3d.Scene | None:
        world, policy = provenance.world, provenance.policy
        if world is None:
            return None
        try:
            return scene3d.scene_from_files(
                world.data, world.path, policy.data if policy else None, policy.path if policy else None
            )
        except ValueError as exc:
            log.warning("no 3D scene in the recording: %s", exc)
            return None

    def _write_derived(self, topic: str, message: scene3d.Message, log_time: int) -> None:
        """With the lock held (or before any other thread has the recording)."""
        channel = self._derived_channels.get(topic)
        if channel is None:
            type_ = scene3d.TOPIC_TYPES[topic]
            name, document = scene3d.SCHEMA_NAMES[type_], scene3d.schema_document(type_)
            schema = self._writer.register_schema(name=name, encoding=SchemaEncoding.JSONSchema, data=document)
            channel = self._derived_channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.JSON, schema_id=schema
            )
        data = scene3d.encode(message)
        self._writer.add_message(
            channel_id=channel, log_time=log_time, publish_time=log_time, data=data, sequence=self.derived
        )
        self.derived += 1

    def record(
        self,
        key: str,
        payload: bytes,
        *,
        log_time: int | None = None,
        publish_time: int | None = None,
        attachment: bytes | None = None,
    ) -> bool:
        """Write one message, and its `attachment` (if any, at most MAX_ATTACHMENT bytes) on the link
        channel right after it; False if it was dropped and counted: not JSON, too big for a chunk the
        reader takes, a key past MAX_CHANNELS, the link channel's own key, or the recording finished or
        failed (`error`). Never raises for what a peer sends or the disk does."""
        if len(payload) > self.max_payload:
            self._drop(key, f"payload of {len(payload)} bytes; a file holds messages of {self.max_payload} at most")
            return False
        if key == self._link_key:
            self._drop(key, "the key is the recording's own, for the robot link's records")
            return False
        try:
            msgspec.json.decode(payload)
        except DECODE_ERRORS as exc:
            self._drop(key, f"payload of {len(payload)} bytes is not JSON ({exc})")
            return False
        with self._lock:
            if self.finished or self.error:
                self.dropped += 1
                log.debug("dropped a message on %s: recording %s", key, self.error or "finished")
                return False
            channel = self._channels.get(key)
            if channel is None and len(self._channels) >= MAX_CHANNELS:
                self.dropped += 1
                if CHANNELS_FULL not in self._warned:
                    self._warned.add(CHANNELS_FULL)
                    log.warning("dropping the messages of keys past %d in %s (first: %s)", MAX_CHANNELS, self.path, key)
                return False
            # Taken under the lock, so receive times rise with the sequence.
            now = self._clock() if log_time is None else log_time
            try:
                if channel is None:
                    channel = self._channels[key] = self._register(key)
                self._writer.add_message(
                    channel_id=channel,
                    log_time=now,
                    publish_time=now if publish_time is None else publish_time,
                    data=payload,
                    sequence=self.messages,
                )
                if attachment is not None and len(attachment) <= MAX_ATTACHMENT:
                    self._record_link(self.messages, attachment, now)
                self.messages += 1
                if self._derive.wants(key):
                    for topic, message in self._derive.messages(key, payload, now / 1e9):
                        self._write_derived(topic, message, now)
            except OSError as exc:
                self._failed(exc)
                self.dropped += 1
                return False
        return True

    def _failed(self, exc: OSError) -> None:
        """With the lock held: writing failed (the disk full, read-only, gone); said once."""
        if not self.error:
            self.error = f"cannot write {self.path}: {exc.strerror or exc}"
            log.error("%s; messages are dropped and counted until a new file can be written", self.error)

    def _record_link(self, sequence: int, attachment: bytes, log_time: int) -> None:
        """With the lock held."""
        if self._link_channel is None:
            schema = self._writer.register_schema(name="RobotLink", encoding=SchemaEncoding.JSONSchema, data=b"{}")
            self._link_channel = self._writer.register_channel(
                topic=self._link_key, message_encoding=MessageEncoding.JSON, schema_id=schema
            )
        self._writer.add_message(
            channel_id=self._link_channel,
            log_time=log_time,
            publish_time=log_time,
            data=link_record(sequence, attachment),
            sequence=sequence,
        )

    def _register(self, key: str) -> int:
        topic = keys.topic_for_key(self.robot, key)
        if topic is None:
            name, schema = PERMISSIVE_SCHEMA_NAME, PERMISSIVE_SCHEMA
        else:
            name, schema = json_schema(topic.type)
        schema_id = self._schemas.get((name, schema))
        if schema_id is None:
            schema_id = self._schemas[name, schema] = self._writer.register_schema(
                name=name, encoding=SchemaEncoding.JSONSchema, data=schema
            )
        return int(self._writer.register_channel(topic=key, message_encoding=MessageEncoding.JSON, schema_id=schema_id))

    def _drop(self, key: str, why: str) -> None:
        with self._lock:
            self.dropped += 1
            first = key not in self._warned and len(self._warned) < MAX_CHANNELS
            if first:
                self._warned.add(key)
        # Once per key at warning level, so a noisy publisher cannot flood the log.
        log.log(logging.WARNING if first else logging.DEBUG, "dropped a message on %s: %s", key, why)

    def flush(self) -> None:
        """Write the chunk in progress, so a crash loses at most what arrived since. A write that
        fails is `error`, not raised."""
        with self._lock:
            if not self.finished and not self.error:
                try:
                    self._writer.flush()
                except OSError as exc:
                    self._failed(exc)

    def finish(self) -> None:
        """Write the summary and index, and close the file if this recording opened it. Idempotent.
        The file is closed also when that fails (the disk full: the file is as `tether recover` reads it)."""
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
                if self._owns_stream:
                    with contextlib.suppress(OSError):
                        self._stream.close()

    def removed(self) -> bool:
        """Whether the file this recording writes was removed from its directory (its name is gone,
        or names another file now): what is written goes nowhere anyone can read."""
        if not self._owns_stream:
            return False
        with self._lock:
            if self.finished:
                return False
            try:
                ours = os.fstat(self._stream.fileno())
                there = os.stat(self.path)
            except OSError:
                return True
        return ours.st_nlink == 0 or (ours.st_dev, ours.st_ino) != (there.st_dev, there.st_ino)

    @property
    def size(self) -> int:
        """Bytes written to the file so far (the chunk in progress not counted)."""
        with self._lock:
            return self._stream.tell() if not self.finished else self._size_at_finish

    @property
    def channels(self) -> dict[str, int]:
        with self._lock:
            return dict(self._channels)

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()
