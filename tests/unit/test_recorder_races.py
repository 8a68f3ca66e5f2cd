"""The recorder's files under failure and rotation: the ROS 2 twin's disk failing, what each file holds."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader

from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance
from services.recorder.reader import read_recording
from services.recorder.recorder import Recorder
from services.recorder.ros2file import Ros2Source, RosKeys
from services.ros2.types import RosTypes
from services.ros2.wire import Naming, Style

SECOND = 1_000_000_000
TWIST = "geometry_msgs/msg/Twist"
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
CMD_VEL_KEY = f"0/cmd_vel/geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}"


@pytest.fixture(scope="module")
def types() -> RosTypes:
    return RosTypes("jazzy")


@pytest.fixture
def rmw_keys(types: RosTypes) -> RosKeys:
    return RosKeys(types, Naming(Style.RMW_ZENOH, 0))


def samples(types: RosTypes, count: int) -> Iterator[bytes]:
    """Twists that do not compress to nothing, so that chunks fill and are written."""
    message = types.new(TWIST)
    for i in range(count):
        message.linear.x = i * 0.001
        yield types.encode(TWIST, message) + os.urandom(64)


def fill_disk_under(path: Path) -> None:
    """Every later write of this process to the file at `path` fails as on a full disk: the descriptor
    it writes through is made /dev/full's."""
    fds = [int(fd) for fd in os.listdir("/proc/self/fd") if _names(int(fd), path)]
    assert len(fds) == 1, f"{path} open {len(fds)} times"
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        os.dup2(full, fds[0])
    finally:
        os.close(full)


def _names(fd: int, path: Path) -> bool:
    try:
        return os.readlink(f"/proc/self/fd/{fd}") == str(path.resolve())
    except OSError:  # closed since it was listed (the listing's own descriptor)
        return False


def test_a_twin_whose_disk_fills_as_samples_arrive_stops_there_and_a_new_pair_is_started(
    tmp_path: Path, types: RosTypes, rmw_keys: RosKeys
) -> None:
    """A full chunk written as a sample arrived raised out of record_ros2 (into the ROS 2 link's
    callback), the sample counted nowhere, the status saying nothing till the next flush; the twin
    was never replaced, and went on writing after its torn chunk once there was room again."""
    recorder = Recorder(
        RecorderConfig(output_dir=str(tmp_path), chunk_size=1024),
        Provenance("r1"),
        ros2=Ros2Source(rmw_keys, "tcp/127.0.0.1:7447"),
    )
    try:
        fill_disk_under(recorder.ros2_files[0])
        sent = list(samples(types, 400))
        recorded = [recorder.record_ros2(CMD_VEL_KEY, sample) for sample in sent]
        assert not all(recorded)
        failed = recorder.status()
        assert failed.ros2 is not None
        assert (
            f"cannot write the ROS 2 recording {recorder.ros2_files[0]}: No space left on device" in failed.ros2.error
        )
        assert failed.ros2.messages + failed.ros2.skipped == len(sent)
        assert recorder.record("tether/r1/a", b"{}")

        recorder.tick()  # a new pair: the disk has room for those
        assert recorder.record_ros2(CMD_VEL_KEY, sent[0])
        status = recorder.status()
    finally:
        recorder.finish()
    assert status.ros2 is not None and status.ros2.error == "" and len(status.ros2.files) == 2
    assert status.ros2.messages + status.ros2.skipped == len(sent) + 1
    assert len(recorder.files) == 2
    assert all(read_recording(path).complete for path in recorder.files)
    reader = make_reader(io.BytesIO(recorder.ros2_files[1].read_bytes()))
    assert [message.data for _, _, message in reader.iter_messages()] == [sent[0]]
