"""Reading recordings back, also files cut short by a crash, and recovering those into complete files."""

from __future__ import annotations

import hashlib
import itertools
import logging
from collections.abc import Callable, Generator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
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
    WORLD_ATTACHMENT,
    is_link_channel,
    link_attachment,
    link_record,
)

log = logging.getLogger(__name__)

# A record longer than this is not one the recorder writes (its chunks are at most 64 MiB): a
# corrupt or hostile length, refused before it is read into memory.
RECORD_SIZE_LIMIT = 128 * 1024 * 1024


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
    the last chunk that was flushed whole, and `problem` says where reading stopped.
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
    complete: bool = False
    problem: str = ""
    # For parts of a rotated recording read as one (join_recordings): every file, in order.
    parts: list[Path] = field(default_factory=list)

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


def _records(path: Path) -> Generator[Any, None, None]:
    with path.open("rb") as stream:
        # CRCs checked: a chunk damaged on disk ends the reading rather than passing as whole.
        reader = StreamReader(stream, validate_crcs=True, record_size_limit=RECORD_SIZE_LIMIT, emit_chunks=True)
        for record in reader.records:
            if isinstance(record, Chunk):
                yield from breakup_chunk(replace(record, compression="", data=_unpack(record)), validate_crc=True)
            else:
                yield record


def read_recording(path: Path, keep: Callable[[str], bool] | None = None) -> RecordingFile:
    """Read `path` front to back, keeping the messages whose key `keep` accepts (default: all).

    Reads a file cut short as far as it is whole; raises RecordingError for a file that is missing or
    not MCAP at all.
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
    records = _records(path)
    try:
        for record in records:
            if isinstance(record, Message):
                channel = recording.channels.get(record.channel_id)
                if channel is None:
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
                recording.channels[record.id] = record
            elif isinstance(record, Schema):
                recording.schemas[record.id] = record
            elif isinstance(record, Metadata):
                recording.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Attachment):
                recording.attachments[record.name] = record
            elif isinstance(record, DataEnd | Footer):
                recording.complete = True
                break
            elif isinstance(record, Header) and record.profile == Profile.ROS2:
                raise RecordingError(
                    f"{path} is a ROS 2 recording (MCAP ros2 profile) for Foxglove and ros2 bag; "
                    "tether's tools read the tether recording beside it"
                )
    except RecordingError:
        raise
    # Whatever a cut or damaged file raises inside the mcap library (short reads, bad lengths,
    # decompression errors, CRC mismatches, absurd sizes) ends the reading there.
    except Exception as exc:
        if not recording.channels and not recording.metadata:
            why = str(exc) or type(exc).__name__
            raise RecordingError(f"{path} ({size} bytes) is not an MCAP recording: {why}") from None
        if isinstance(exc, ChunkError):
            recording.problem = f"reading stopped at a chunk that cannot be trusted: {exc}"
        else:
            recording.problem = "the file ends early (a crash?): read up to the last whole chunk"
        log.debug("%s: reading stopped at %s: %s", path, type(exc).__name__, exc)
    finally:
        records.close()
    if not recording.complete and not recording.problem:
        recording.problem = "the file ends without its summary (a crash?)"
    return recording


def join_recordings(parts: list[RecordingFile]) -> RecordingFile:
    """The parts of one rotated recording as one, in the order they were recorded (whatever order they
    are given in). RecordingError unless they are consecutive parts of one recorder's run (the same
    run id, part numbers without a gap) with the same robot, world and policy files (compared by
    content), and their times follow one another. Metadata and files are the first part's; `complete`
    only if every part is, and `problem` names the parts that are not."""
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
                raise RecordingError(f"{first.path} and {after.path} carry different {kind} files")
    latest: tuple[int, Path] | None = None
    for part in ordered:
        if not part.messages:
            continue
        if latest is not None and min(m.log_time for m in part.messages) < latest[0]:
            raise RecordingError(
                f"{latest[1]} and {part.path} overlap in time: parts of one recording follow one another"
            )
        latest = (max(m.log_time for m in part.messages), part.path)
    return RecordingFile(
        first.path,
        messages=[m for part in ordered for m in part.messages],
        metadata=first.metadata,
        attachments=first.attachments,
        schemas=first.schemas,
        channels=first.channels,
        complete=all(part.complete for part in ordered),
        problem="; ".join(f"{part.path.name}: {part.problem}" for part in ordered if part.problem),
        parts=[part.path for part in ordered],
    )


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
        schema_ids = {
            sid: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data)
            for sid, s in recording.schemas.items()
        }
        channel_ids: dict[str, int] = {}
        link = next((c.topic for c in recording.channels.values() if is_link_channel(c.topic)), None)
        for channel in recording.channels.values():
            channel_ids[channel.topic] = writer.register_channel(
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_id=schema_ids.get(channel.schema_id, 0),
                metadata=channel.metadata,
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
    return Recovered(
        source, output, len(recording.messages), len(recording.channels), recording.complete, recording.problem
    )
