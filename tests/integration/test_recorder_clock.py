"""A recording across a step of the wall clock, over real Zenoh: the robot's clock set back an hour
mid-run (NTP correcting a robot that booted with its clock ahead). The recorder rotates on time, and
`tether inspect` and `tether replay`, as real processes, read its parts as one recording in the order
it was made."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from schemas import keys
from schemas.world import Empty
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance
from services.recorder.node import bind
from services.recorder.recorder import Recorder
from services.runtime import ALL_SERVICES, Node, NodeSettings, encode
from tests.sessions import free_ports

HOUR = 3600 * 1_000_000_000
BATCH = 50


class SteppedClock:
    """The wall clock, stepped by the test as NTP steps it."""

    def __init__(self) -> None:
        self.offset = 0

    def __call__(self) -> int:
        return time.time_ns() + self.offset


def tether(settings: NodeSettings, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "TETHER_ROBOT": settings.robot, "TETHER_BASE_PORT": str(settings.base_port)}
    env.pop("TETHER_ZENOH_CONFIG", None)
    return subprocess.run(
        [sys.executable, "-m", "tether", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        start_new_session=True,
    )


def test_a_recording_across_a_step_back_of_the_wall_clock_rotates_and_replays_as_one(tmp_path: Path) -> None:
    settings = NodeSettings(robot="stepped", base_port=free_ports(len(ALL_SERVICES)))
    key = f"{keys.prefix(settings.robot)}/load/counter"
    wall = SteppedClock()
    config = RecorderConfig(output_dir=str(tmp_path / "recordings"), max_file_seconds=1.0)
    recorder = Recorder(config, Provenance(settings.robot), clock=wall, monotonic=time.monotonic_ns)
    try:
        with Node("recorder", settings) as served, Node("cli", settings) as node:
            bind(served, recorder)
            served.declare_alive()
            assert not node.wait_alive(["recorder"], 30.0)
            publisher = node.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            asked = 0  # each status query is recorded too (its trace)

            def publish_and_wait(first: int) -> None:
                nonlocal asked
                for i in range(first, first + BATCH):
                    publisher.put(encode({"i": i}))
                deadline = time.monotonic() + 20.0
                while node.call(keys.RECORDER_STATUS, Empty()).messages < first + BATCH + asked:
                    asked += 1
                    assert time.monotonic() < deadline, "the recorder never caught up"

            publish_and_wait(0)
            wall.offset -= HOUR
            publish_and_wait(BATCH)
            # The service's loop: a tick about every flush_interval, until the file is a second old.
            deadline = time.monotonic() + 10.0
            while len(node.call(keys.RECORDER_STATUS, Empty()).files) < 2:
                asked += 1
                assert time.monotonic() < deadline, "not rotated 10 s into a file of at most 1 s"
                recorder.tick()
                threading.Event().wait(0.1)
            publish_and_wait(2 * BATCH)
    finally:
        recorder.finish()
    files = [str(path) for path in recorder.files]
    assert len(files) == 2

    inspected = tether(settings, "inspect", "--json", *reversed(files))
    assert inspected.returncode == 0, inspected.stderr
    document = json.loads(inspected.stdout)
    assert document["parts"] == files and document["complete"] and document["messages"] >= 3 * BATCH

    received: list[int] = []
    done = threading.Event()

    def on_sample(_key: str, payload: bytes) -> None:
        received.append(json.loads(payload)["i"])
        if len(received) == 3 * BATCH:
            done.set()

    replay = NodeSettings(robot=f"{settings.robot}_replay", base_port=settings.base_port)
    # Listening where the recorder did, so the replay process finds this subscriber.
    with Node("recorder", replay) as watcher:
        watcher.subscribe_raw(f"{keys.prefix(replay.robot)}/load/counter", on_sample)
        replayed = tether(settings, "replay", *files)
        assert replayed.returncode == 0, replayed.stderr
        assert done.wait(10.0), f"{len(received)} of {3 * BATCH} replayed messages arrived"
    assert received == list(range(3 * BATCH)), "replayed in the order recorded"
