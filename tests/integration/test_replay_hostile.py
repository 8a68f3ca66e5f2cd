"""`tether replay` of a crafted recording over real Zenoh: as a real process, and its Player in this one."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

from mcap.writer import Writer

from schemas import keys
from services.recorder.mcapfile import MAX_CHANNELS
from services.recorder.reader import read_recording
from services.recorder.replay import plan_replay
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.sessions import free_ports
from tether.recordings import MAX_PUBLISHERS, Player

ROBOT = "crafted"
# Distinct keys, more than the publishers a replay keeps (MAX_PUBLISHERS): it declared one for each key,
# and each declaration takes longer than the last (40,000 keys: some 90 s on this machine).
KEYS = MAX_CHANNELS + 500
REPLAY_TIMEOUT = 60.0


def crafted(path: Path) -> Path:
    """A recording of one message on each of KEYS keys, all received at one time."""
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="crafted")
        writer.add_metadata("tether", {"robot": ROBOT})
        schema = writer.register_schema(name="any", encoding="jsonschema", data=b"{}")
        for i in range(KEYS):
            channel = writer.register_channel(
                topic=f"{keys.prefix(ROBOT)}/junk/{i}", message_encoding="json", schema_id=schema
            )
            writer.add_message(channel_id=channel, log_time=0, publish_time=0, data=b"{}")
        writer.finish()
    return path


def test_a_replay_of_a_file_with_very_many_keys_is_not_held_up_declaring_publishers(tmp_path: Path) -> None:
    file = crafted(tmp_path / "many-keys.mcap")
    replay = NodeSettings(robot=f"{ROBOT}_replay", base_port=free_ports(len(ALL_SERVICES)))
    beyond = threading.Event()  # a key past the publishers kept arrived

    def on_sample(key: str, _payload: bytes) -> None:
        if int(key.rsplit("/", 1)[1]) >= MAX_CHANNELS:
            beyond.set()

    env = {**os.environ, "TETHER_ROBOT": replay.robot, "TETHER_BASE_PORT": str(replay.base_port)}
    env.pop("TETHER_ZENOH_CONFIG", None)
    # Listening where a recorder would, so the replay process finds this subscriber.
    with Node("recorder", replay) as watcher:
        watcher.subscribe_raw(f"{keys.prefix(replay.robot)}/junk/*", on_sample)
        try:
            done = subprocess.run(
                [sys.executable, "-m", "tether", "replay", str(file)],
                env=env,
                capture_output=True,
                text=True,
                timeout=REPLAY_TIMEOUT,
                start_new_session=True,
            )
        except subprocess.TimeoutExpired:
            raise AssertionError(f"a replay of {KEYS} messages did not end within {REPLAY_TIMEOUT:g} s") from None
        assert done.returncode == 0, done.stderr
        assert f"replayed {KEYS} messages" in done.stderr
        assert beyond.wait(10.0), "no message on a key past the publishers kept arrived"
        # The same replay's Player in this process: it keeps publishers for at most MAX_PUBLISHERS keys.
        beyond.clear()
        plan = plan_replay(read_recording(file).messages, ROBOT, replay.robot)
        with Node("replay", replay) as node:
            player = Player(node)
            assert player.play(plan, speed=1000.0) == KEYS
        assert len(player.publishers) <= MAX_PUBLISHERS, len(player.publishers)
        assert beyond.wait(10.0), "no message on a key past the publishers kept arrived"
