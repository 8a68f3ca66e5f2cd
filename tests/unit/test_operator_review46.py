"""The view's teleop bridge under a hostile Foxglove client (a review): @foxglove/ws-protocol's client
under node against the SDK's server in this process, as `tether view --teleop` serves it."""

from __future__ import annotations

import logging
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import foxglove
import pytest
from foxglove.websocket import Capability, Client, ClientChannel

from bench.viewer import ViewerMissing, client_script
from schemas.robot import Twist
from tether.view import Listener, TeleopBridge
from tether.viewteleop import TELEOP_TOPIC

# Advertises the teleop topic and unadvertises it again, `count` times, as fast as the socket takes it.
CHURN = """
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");
const [url, count, topic] = process.argv.slice(2);
const ws = new WebSocket(url, ["foxglove.sdk.v1"]);
const client = new FoxgloveClient({ ws });
client.on("open", () => {
  for (let i = 0; i < Number(count); i++) {
    client.unadvertise(client.advertise({ topic, encoding: "json", schemaName: "geometry_msgs/Twist" }));
  }
  ws.close();
});
client.on("close", () => process.exit(0));
"""


class NoSubscribers:
    def viewer_subscribed(self, topic: str) -> None:
        pass


class Counting(Listener):
    """The view's listener, counting the advertisements it was given."""

    advertised = 0

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        self.advertised += 1
        super().on_client_advertise(client, channel)


@pytest.fixture
def served() -> Iterator[tuple[Counting, foxglove.WebSocketServer, list[Twist]]]:
    sent: list[Twist] = []
    listener = Counting(NoSubscribers(), TeleopBridge(sent.append))  # type: ignore[arg-type]
    server = foxglove.start_server(
        name="review46",
        host="127.0.0.1",
        port=0,
        context=foxglove.Context(),
        server_listener=listener,
        capabilities=[Capability.ClientPublish],
        supported_encodings=["json"],
    )
    try:
        yield listener, server, sent
    finally:
        server.stop()


def test_a_client_advertising_the_teleop_topic_in_a_loop_does_not_fill_the_log(
    served: tuple[Counting, foxglove.WebSocketServer, list[Twist]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    try:
        home = client_script().parent
    except ViewerMissing as exc:
        pytest.skip(str(exc))
    listener, server, sent = served
    assert listener.teleop is not None
    script = tmp_path / "churn.js"
    script.write_text(CHURN)
    rounds = 3000
    with caplog.at_level(logging.WARNING, logger="tether.view"):
        subprocess.run(
            ["node", str(script), f"ws://127.0.0.1:{server.port}", str(rounds), TELEOP_TOPIC],
            env={**os.environ, "NODE_PATH": str(home / "node_modules")},
            timeout=120,
            check=True,
        )
    lines = [r.getMessage() for r in caplog.records if r.name == "tether.view"]
    # The server answered the client's close after reading every round before it, on the same socket.
    assert listener.advertised == rounds, listener.advertised
    # The first is logged, naming the client; the rest are counted into a line every few seconds.
    assert lines and "client 1 drives through channel 1" in lines[0], lines[:3]
    assert len(lines) <= 3, f"{len(lines)} lines for {rounds} rounds: {lines[:3]}"
    assert listener.teleop.gate.channels == 0 and sent == []
