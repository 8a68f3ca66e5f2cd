"""Reading recordings back, also files cut short by a crash, and recovering those into complete files."""

from __future__ import annotations

import hashlib
import io
import itertools
import logging
import struct
import zlib
from collections.abc import Callable, Generator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, breakup_chunk
from mcap.well_known import Profile
from mcap.writer import Writer

from schemas import keys
from services.recorder import scene3d
from services.recorder.mcapfile import (
    COMPRESSION,
    LIBRARY,
    METADATA_NAME,
    POLICY_ATTACHMENT,
    PROFILE,
    RECORD_SIZE_LIMIT,
    WORLD_ATTACHMENT,
    is_link_channel,
    link_attachment,
    link_record,
)

log = logging.getLogger(__name__)


class RecordingError(Exception):
    """A file that is not a tether recording at all (missing, empty, not MCAP)."""


@dataclass(frozen=True)
class Recorded:
    """One message as it was received: nanosecond receive time, full key, JSON payload."""

    log_time: int
    key: str
    data: bytes
    # The Zenoh attachment it came with (safety's MAC on robot commands and heartbeats), if recorded.
    attachment: bytes | None = None


@dataclass
class RecordingFile:
    """Everything in one recording: messages in the order they were received, metadata, attachments.

    `complete` is False for a file without its summary (the recorder was killed): it is read up to
    the last chunk that was flushed whole, and `problem` says where reading stopped. It is False too
    when a damaged chunk (or other record) was skipped, reading on past it: `skipped` counts those,
    and `problem` names each with its offset and what is wrong with it.
    """

    path: Path
    messages: list[Recorded] = field(default_factory=list)
    # Foxglove's scene, frames and log the recorder made from the traffic (scene3d): kept apart, so
    # nothing replays or checks them; `tether recover` copies them.
    derived: list[Recorded] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, Attachment] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    # Each topic's channel and schema as first defined (an id may be defined again for another topic).
    topics: dict[str, tuple[Channel, Schema | None]] = field(default_factory=dict)
    complete: bool = False
    problem: str = ""
    # For parts of a rotated recording read as one (join_recordings): every file, in order.
    parts: list[Path] = field(default_factory=list)
    # How many damaged records were skipped (named in `problem`).
    skipped: int = 0

    @property
    def files(self) -> list[Path]:
        """Every file read: the parts in order, or the one file."""
        return self.parts or [self.path]

    @property
    def name(self) -> str:
        """The file's name, or the first part's and how many follow."""
        more = len(self.files) - 1
        return self.path.name + (f" (+{more} part{'s' if more > 1 else ''})" if more > 0 else "")

    @property
    def robot(self) -> str:
        """The robot the file was recorded for: from its metadata, else from its first key."""
        robot = self.metadata.get(METADATA_NAME, {}).get("robot")
        if robot:
            return robot
        for message in self.messages:
            parts = message.key.split("/")
            if len(parts) > 2 and parts[0] == keys.ROOT:
                return parts[1]
        return ""

    def attachment(self, kind: str) -> Attachment | None:
        """The world or policy file recorded with this run (`kind` is "world" or "policy")."""
        for name, attachment in self.attachments.items():
            if name.split("/", 1)[0] == kind:
                return attachment
        return None

    @property
    def world(self) -> Attachment | None:
        return self.attachment(WORLD_ATTACHMENT)

    @property
    def policy(self) -> Attachment | None:
        return self.attachment(POLICY_ATTACHMENT)

    def counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for message in self.messages:
            counts[message.key] = counts.get(message.key, 0) + 1
        return counts

    @property
    def duration(self) -> float:
        if not self.messages:
            return 0.0
        return (self.messages[-1].log_time - self.messages[0].log_time) / 1e9


class ChunkError(Exception):
    """A chunk whose contents are not what its header declares."""


def _unpack(chunk: Chunk) -> bytes:
    """A chunk's records, decompressed into at most the size its header declares (itself at most
    RECORD_SIZE_LIMIT), with a zstd window no bigger than a frame of that size needs: a hostile chunk
    cannot make the reader allocate much more than that."""
    size = chunk.uncompressed_size
    if size > RECORD_SIZE_LIMIT:
        raise ChunkError(f"a chunk declares {size} bytes uncompressed, more than {RECORD_SIZE_LIMIT}")
    if chunk.compression == "zstd":
        window = 1 << max(20, (size - 1).bit_length())  # a frame never needs a window beyond its size
        parts: list[bytes] = []
        wanted = size + 1  # one byte more than declared tells a chunk that holds more
        try:
            with zstandard.ZstdDecompressor(max_window_size=window).stream_reader(chunk.data) as reader:
                while wanted > 0 and (part := reader.read(wanted)):
                    parts.append(part)
                    wanted -= len(part)
        except zstandard.ZstdError as exc:
            raise ChunkError(f"a chunk declares {size} bytes uncompressed and its data does not fit: {exc}") from None
        data = b"".join(parts)
    elif chunk.compression == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ChunkError(f"a chunk is compressed with {chunk.compression!r}, which tether does not write")
    if len(data) > size:
        raise ChunkError(f"a chunk declares {size} bytes uncompressed and holds more")
    if len(data) < size:
        raise ChunkError(f"a chunk declares {size} bytes uncompressed and holds {len(data)}")
    return data


MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")  # every record: opcode, then the length of what follows
# A chunk's fields before its compression's name: start and end time, uncompressed size and CRC,
# the name's length.
_CHUNK_FIELDS = struct.Struct("<QQQII")
_RECORD_TYPES: dict[int, Any] = {
    Opcode.ATTACHMENT: Attachment,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK: Chunk,
    Opcode.DATA_END: DataEnd,
    Opcode.FOOTER: Footer,
    Opcode.HEADER: Header,
    Opcode.MESSAGE: Message,
    Opcode.METADATA: Metadata,
    Opcode.SCHEMA: Schema,
}
SCAN_WINDOW = 1 << 20


@dataclass(frozen=True)
class Damaged:
    """A record that could not be read and was skipped: where it starts in the file, and why."""

    offset: int
    why: str
    what: str = "record"  # the kind of record, where its opcode is known


class NotMcap(Exception):
    """A file that does not start as MCAP does."""


class FileEndsEarly(Exception):
    """The file ends inside a record (or before its footer): a recorder killed mid-write."""


def _cause(exc: BaseException) -> str:
    if isinstance(exc, CRCValidationError):
        return f"its CRC does not match its contents (expected {exc.expected:#010x}, found {exc.actual:#010x})"
    if isinstance(exc, EndOfFile):
        return "its fields run past its own length"
    if isinstance(exc, UnicodeDecodeError):
        return f"a text in it is not UTF-8 ({exc.reason} at byte {exc.start})"
    return str(exc) or type(exc).__name__


def _parse(opcode: int, body: bytes) -> Any:
    """The record `body` holds, or None for one tether does not read (indexes, statistics...)."""
    kind = _RECORD_TYPES.get(opcode)
    if kind is None:
        return None
    stream = ReadDataStream(io.BytesIO(body))
    if kind is Message:
        return Message.read(stream, len(body))
    record = kind.read(stream)
    if kind is Attachment:
        # The mcap library skips an attachment's CRC; the world and policy a recording carries are what
        # recheck decides with, so one changed on disk must not pass for the files the robot ran with.
        crc_at = stream.count - 4
        (expected,) = struct.unpack_from("<I", body, crc_at)
        if expected != 0 and (actual := zlib.crc32(body[:crc_at])) != expected:
            raise CRCValidationError(expected, actual, record)
    return record


def _is_chunk_at(head: bytes, room: int) -> bool:
    """Whether `head` (a record's first bytes) is a chunk's, whole within `room` bytes: its own
    fields must add up to the length it declares, which a damaged or random stretch of bytes does
    not do by chance."""
    if len(head) < _HEAD.size + _CHUNK_FIELDS.size or head[0] != Opcode.CHUNK:
        return False
    _, length = _HEAD.unpack_from(head)
    if length > RECORD_SIZE_LIMIT or _HEAD.size + length > room:
        return False
    *_, name_length = _CHUNK_FIELDS.unpack_from(head, _HEAD.size)
    name_at = _HEAD.size + _CHUNK_FIELDS.size
    if name_length > 4 or len(head) < name_at + name_length + 8:
        return False
    if head[name_at : name_at + name_length] not in (b"", b"lz4", b"zstd"):
        return False
    (data_length,) = struct.unpack_from("<Q", head, name_at + name_length)
    return _CHUNK_FIELDS.size + name_length + 8 + data_length == length


def _next_chunk(stream: Any, start: int, size: int) -> int | None:
    """The offset of the first whole chunk at or after `start`, or None."""
    overlap = _HEAD.size + _CHUNK_FIELDS.size + 4 + 8
    at = start
    while at < size:
        stream.seek(at)
        window = stream.read(SCAN_WINDOW + overlap)
        if not window:
            return None
        found = window.find(bytes([Opcode.CHUNK]))
        while 0 <= found < SCAN_WINDOW:
            if _is_chunk_at(window[found : found + overlap], size - (at + found)):
                return at + found
            found = window.find(bytes([Opcode.CHUNK]), found + 1)
        at += SCAN_WINDOW
    return None


def _records(path: Path, size: int) -> Generator[Any, None, None]:
    """The records of `path` in order, a chunk's broken up into the records it holds. A record that
    cannot be read is yielded as Damaged and skipped: by its length when that is sound, else up to
    the next whole chunk. Raises FileEndsEarly where the file is cut."""
    with path.open("rb") as stream:
        magic = stream.read(len(MAGIC))
        if magic != MAGIC:
            raise NotMcap(f"it does not start as MCAP does (magic {magic!r})")
        at = len(MAGIC)
        crc: int | None = zlib.crc32(MAGIC)  # the data section's, while every record was read
        while True:
            head = stream.read(_HEAD.size)
            if len(head) < _HEAD.size:
                raise FileEndsEarly()
            opcode, length = _HEAD.unpack(head)
            if length > RECORD_SIZE_LIMIT or at + _HEAD.size + length > size:
                following = _next_chunk(stream, at + 1, size)
                if following is None:
                    if length <= RECORD_SIZE_LIMIT:
                        raise FileEndsEarly()
                    raise ChunkError(
                        f"a record at byte {at} declares {length} bytes, more than the {RECORD_SIZE_LIMIT} "
                        "a tether file holds, and no whole chunk follows it"
                    )
                limit = f"more than the {RECORD_SIZE_LIMIT} a tether file holds"
                beyond = limit if length > RECORD_SIZE_LIMIT else f"past the file's end ({size} bytes)"
                yield Damaged(at, f"it declares {length} bytes, {beyond}")
                stream.seek(following)
                at, crc = following, None  # the data section's CRC cannot be checked past a skip
                continue
            body = stream.read(length)
            if len(body) < length:
                raise FileEndsEarly()  # the file shrank while it was read
            try:
                record = _parse(opcode, body)
                if isinstance(record, DataEnd) and crc is not None and record.data_section_crc not in (0, crc):
                    yield Damaged(at, "its CRC does not match: a record outside the chunks changed", "data section")
                if isinstance(record, Chunk):
                    inner = breakup_chunk(replace(record, compression="", data=_unpack(record)), validate_crc=True)
            except Exception as exc:  # whatever the bytes make the mcap library raise: this record only
                kind = _RECORD_TYPES.get(opcode)
                yield Damaged(
                    at,
                    _cause(exc),
                    "record" if kind is None else "chunk" if kind is Chunk else f"{kind.__name__.lower()} record",
                )
                record = None
            else:
                if isinstance(record, Chunk):
                    yield from inner
                elif record is not None:
                    yield record
            if crc is not None:
                crc = zlib.crc32(body, zlib.crc32(head, crc))
            at += _HEAD.size + length
            if isinstance(record, Footer):
                return


def read_recording(path: Path, keep: Callable[[str], bool] | None = None) -> RecordingFile:
    """Read `path` front to back, keeping the messages whose key `keep` accepts (default: all).

    Reads a file cut short as far as it is whole, and skips a damaged record (a chunk whose CRC,
    compression or contents are wrong) to read on past it, naming it in `problem`; raises
    RecordingError for a file that is missing, cannot be read, or is not MCAP at all.
    """
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise RecordingError(f"no such file: {path}") from None
    except OSError as exc:
        raise RecordingError(f"cannot read recording {path}: {exc.strerror}") from None
    if path.is_dir():
        raise RecordingError(f"{path} is a directory, not a recording")
    if size == 0:
        raise RecordingError(f"{path} is empty: the recorder never wrote to it")
    recording = RecordingFile(path)
    kept: dict[int, bool] = {}
    last_sequence: int | None = None  # of the last message kept, which a link record may belong to
    damaged: list[Damaged] = []
    unknown_channel = 0
    ending = ""
    records = _records(path, size)
    try:
        for record in records:
            if isinstance(record, Message):
                channel = recording.channels.get(record.channel_id)
                if channel is None:
                    unknown_channel += 1
                    continue
                if is_link_channel(channel.topic):
                    if (
                        last_sequence is not None
                        and (attachment := link_attachment(record.data, last_sequence)) is not None
                    ):
                        recording.messages[-1] = replace(recording.messages[-1], attachment=attachment)
                    last_sequence = None
                    continue
                if scene3d.is_derived(channel.topic):
                    recording.derived.append(Recorded(record.log_time, channel.topic, record.data))
                    continue
                if record.channel_id not in kept:
                    kept[record.channel_id] = keep is None or keep(channel.topic)
                last_sequence = None
                if kept[record.channel_id]:
                    recording.messages.append(Recorded(record.log_time, channel.topic, record.data))
                    last_sequence = record.sequence
            elif isinstance(record, Channel):
                if recording.channels.get(record.id, record) != record:
                    kept.pop(record.id, None)  # an id defined again: its messages are the new topic's
                recording.channels[record.id] = record
                recording.topics.setdefault(record.topic, (record, recording.schemas.get(record.schema_id)))
            elif isinstance(record, Schema):
                recording.schemas[record.id] = record
            elif isinstance(record, Metadata):
                recording.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Attachment):
                recording.attachments[record.name] = record
            elif isinstance(record, Damaged):
                damaged.append(record)
                last_sequence = None
                log.debug("%s: skipped a damaged record at byte %d: %s", path, record.offset, record.why)
            elif isinstance(record, DataEnd | Footer):
                recording.complete = True
                break
            elif isinstance(record, Header) and record.profile == Profile.ROS2:
                raise RecordingError(
                    f"{path} is a ROS 2 recording (MCAP ros2 profile) for Foxglove and ros2 bag; "
                    "tether's tools read the tether recording beside it"
                )
    except NotMcap as exc:
        raise RecordingError(f"{path} ({size} bytes) is not an MCAP recording: {exc}") from None
    except OSError as exc:  # not ours to read (permissions), or the disk failed under it
        raise RecordingError(f"cannot read recording {path}: {exc.strerror or exc}") from None
    except FileEndsEarly:
        ending = "the file ends early (a crash?): read up to the last whole chunk"
    except ChunkError as exc:
        ending = f"reading stopped at a record that cannot be trusted: {exc}"
    finally:
        records.close()
    if not recording.channels and not recording.metadata and not recording.complete:
        why = damaged[0].why if damaged else ending or "it holds no record"
        raise RecordingError(f"{path} ({size} bytes) is not an MCAP recording: {why}")
    problems = [_skipped(damaged)] if damaged else []
    if unknown_channel:
        problems.append(
            f"{unknown_channel} message{'s' if unknown_channel > 1 else ''} on a channel the file does not "
            "define (defined in a skipped record?) dropped"
        )
    if ending:
        problems.append(ending)
    elif not recording.complete:
        problems.append("the file ends without its summary (a crash?)")
    recording.problem = "; ".join(problems)
    recording.skipped = len(damaged)
    recording.complete = recording.complete and not damaged and not unknown_channel
    return recording


def _skipped(damaged: list[Damaged]) -> str:
    """The damaged records, each with its offset and cause (the first few)."""
    shown = "; ".join(f"{d.what} at byte {d.offset}: {d.why}" for d in damaged[:3])
    more = f"; and {len(damaged) - 3} more" if len(damaged) > 3 else ""
    count = f"{len(damaged)} damaged record{'s' if len(damaged) > 1 else ''}"
    return f"{count} skipped, read on past {'them' if len(damaged) > 1 else 'it'} ({shown}{more})"


def join_recordings(parts: list[RecordingFile]) -> RecordingFile:
    """The parts of one rotated recording as one, in the order they were recorded (whatever order they
    are given in). RecordingError unless they are consecutive parts of one recorder's run (the same
    run id, part numbers without a gap) with the same robot, world and policy files (compared by
    content), and they follow one another in time: on the recorder's monotonic clock where every
    part carries it (`elapsed_ns`), so a step of the wall clock between or inside parts does not part
    them, else by their messages' receive times. The messages stay in the order they were recorded,
    their receive times as they are. Metadata and files are the first part's; `complete` only if
    every part is, and `problem` names the parts that are not."""
    if not parts:
        raise RecordingError("no recording given")
    if len(parts) == 1:
        return parts[0]
    seen: set[Path] = set()
    for part in parts:
        resolved = part.path.resolve()
        if resolved in seen:
            raise RecordingError(f"{part.path} is given twice")
        seen.add(resolved)

    def meta(part: RecordingFile) -> dict[str, str]:
        return part.metadata.get(METADATA_NAME, {})

    try:
        numbered = sorted(((int(meta(part).get("part", "")), part) for part in parts), key=lambda pair: pair[0])
    except ValueError:
        raise RecordingError("to be read as one, every part must carry its part number in its metadata") from None
    ordered = [part for _, part in numbered]
    first = ordered[0]
    for (number, before), (next_number, after) in itertools.pairwise(numbered):
        if meta(after).get("run") != meta(first).get("run"):
            raise RecordingError(f"{first.path} and {after.path} are from different recorder runs: not parts of one")
        if next_number != number + 1:
            raise RecordingError(
                f"{before.path} is part {number} and {after.path} part {next_number}: "
                + ("given twice" if next_number == number else "the parts between them are missing")
            )
        if after.robot != first.robot:
            raise RecordingError(f"{first.path} is of robot {first.robot!r} and {after.path} of {after.robot!r}")
        for kind in (WORLD_ATTACHMENT, POLICY_ATTACHMENT):
            if _content(first.attachment(kind)) != _content(after.attachment(kind)):
                # A part's file may be missing for a damaged record, not for another file: said.
                damage = "".join(f"; {part.path}: {part.problem}" for part in (first, after) if part.skipped)
                raise RecordingError(f"{first.path} and {after.path} carry different {kind} files{damage}")
    _check_follow(ordered)
    return RecordingFile(
        first.path,
        messages=[m for part in ordered for m in part.messages],
        metadata=first.metadata,
        attachments=first.attachments,
        schemas=first.schemas,
        channels=first.channels,
        topics={topic: found for part in ordered[::-1] for topic, found in part.topics.items()},
        complete=all(part.complete for part in ordered),
        skipped=sum(part.skipped for part in ordered),
        problem="; ".join(f"{part.path.name}: {part.problem}" for part in ordered if part.problem),
        parts=[part.path for part in ordered],
    )


def _check_follow(ordered: list[RecordingFile]) -> None:
    """RecordingError unless the parts (in part order) follow one another in time."""
    elapsed = [value for part in ordered if (value := _elapsed(part)) is not None]
    if len(elapsed) == len(ordered):
        # Written by the recorder on a clock NTP does not step: the wall times in the parts may run
        # backwards (a robot that booted with its clock ahead), and that recording is still one.
        for (before, started), (after, then) in itertools.pairwise(zip(ordered, elapsed, strict=True)):
            if then < started:
                raise RecordingError(
                    f"{after.path} starts before {before.path} on the recorder's own clock: parts of one "
                    "recording follow one another"
                )
        return
    latest: tuple[int, Path] | None = None
    for part in ordered:
        if not part.messages:
            continue
        if latest is not None and min(m.log_time for m in part.messages) < latest[0]:
            raise RecordingError(
                f"{latest[1]} and {part.path} overlap in time: parts of one recording follow one another"
            )
        latest = (max(m.log_time for m in part.messages), part.path)


def _elapsed(part: RecordingFile) -> int | None:
    """The run's time when `part` started, on the recorder's monotonic clock; None if the part does not say."""
    value = part.metadata.get(METADATA_NAME, {}).get("elapsed_ns", "")
    return int(value) if value.isascii() and value.isdigit() else None


def _content(attachment: Attachment | None) -> str | None:
    return None if attachment is None else hashlib.sha256(attachment.data).hexdigest()


@dataclass(frozen=True)
class Recovered:
    source: Path
    output: Path
    messages: int
    channels: int
    complete: bool
    problem: str


def recover(source: Path, output: Path, compression: str = "zstd") -> Recovered:
    """Write every whole record of `source` into a new, complete file at `output` (with summary and
    index), as `mcap recover` does. Works on complete files too (it then copies them)."""
    if output.resolve() == source.resolve():
        raise RecordingError(f"recover writes a new file; {output} is the file being recovered")
    recording = read_recording(source)
    with output.open("wb") as stream:
        writer = Writer(stream, compression=COMPRESSION[compression])
        writer.start(profile=PROFILE, library=LIBRARY)
        # One channel per topic, as each was first defined: a file may define an id again for
        # another topic, and every message keeps the topic it was read under.
        channel_ids: dict[str, int] = {}
        schema_ids: dict[tuple[str, str, bytes], int] = {}
        link = next((topic for topic in recording.topics if is_link_channel(topic)), None)
        for topic, (channel, schema) in recording.topics.items():
            schema_id = 0
            if schema is not None:
                described = (schema.name, schema.encoding, schema.data)
                if described not in schema_ids:
                    schema_ids[described] = writer.register_schema(*described)
                schema_id = schema_ids[described]
            channel_ids[topic] = writer.register_channel(
                topic=topic, message_encoding=channel.message_encoding, schema_id=schema_id, metadata=channel.metadata
            )
        for name, values in recording.metadata.items():
            writer.add_metadata(name, values)
        for attachment in recording.attachments.values():
            writer.add_attachment(
                create_time=attachment.create_time,
                log_time=attachment.log_time,
                name=attachment.name,
                media_type=attachment.media_type,
                data=attachment.data,
            )
        for sequence, message in enumerate(recording.messages):
            writer.add_message(
                channel_id=channel_ids[message.key],
                log_time=message.log_time,
                publish_time=message.log_time,
                data=message.data,
                sequence=sequence,
            )
            if message.attachment is not None and link is not None:
                # Its attachment right after it, as the recorder wrote it.
                writer.add_message(
                    channel_id=channel_ids[link],
                    log_time=message.log_time,
                    publish_time=message.log_time,
                    data=link_record(sequence, message.attachment),
                    sequence=sequence,
                )
        for sequence, message in enumerate(recording.derived):
            writer.add_message(
                channel_id=channel_ids[message.key],
                log_time=message.log_time,
                publish_time=message.log_time,
                data=message.data,
                sequence=sequence,
            )
        writer.finish()
    return Recovered(source, output, len(recording.messages), len(channel_ids), recording.complete, recording.problem)
