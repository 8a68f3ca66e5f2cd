"""`tether view`'s end with a viewer that stopped reading: Foxglove's own server (the SDK, real) and a
viewer played over a raw socket, subscribed to a channel and then reading nothing."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
import time
from collections.abc import Iterator

import foxglove
import pytest

from tether import view

WAIT = 10.0


def masked(text: str) -> bytes:
    """A client's WebSocket text frame (a client masks what it sends)."""
    data, mask = text.encode(), os.urandom(4)
    size = bytes([0x80 | len(data)]) if len(data) < 126 else bytes([0x80 | 126]) + struct.pack("!H", len(data))
    return bytes([0x81]) + size + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data))


@pytest.fixture
def stalled() -> Iterator[tuple[foxglove.WebSocketServer, socket.socket]]:
    """A server whose one viewer subscribed to a channel flooded with messages, and reads no more: its
    connection is full."""
    context = foxglove.Context()
    channel = foxglove.Channel("/scene", message_encoding="json", context=context)
    server = foxglove.start_server(name="t", host="127.0.0.1", port=0, context=context, message_backlog_size=64)
    viewer = socket.create_connection(("127.0.0.1", server.port), timeout=WAIT)
    try:
        viewer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        key = base64.b64encode(os.urandom(16)).decode()
        viewer.sendall(
            f"GET / HTTP/1.1\r\nHost: t\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n".encode()
        )
        heard = b""
        while b'"op":"advertise"' not in heard or not heard.rstrip().endswith(b"}]}"):
            heard += viewer.recv(65536)
        advertised = heard[heard.index(b'{"op":"advertise"') :]
        channel_id = json.loads(advertised)["channels"][0]["id"]
        viewer.sendall(masked(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel_id}]})))
        payload = json.dumps({"data": "x" * 20_000})
        flooded = time.monotonic() + 2.0
        while time.monotonic() < flooded:
            channel.log(payload)
        yield server, viewer
    finally:
        viewer.close()  # the viewer gone, the server's stop ends: no thread is left in it


def test_the_view_ends_without_waiting_for_a_viewer_that_stopped_reading(
    stalled: tuple[foxglove.WebSocketServer, socket.socket],
) -> None:
    """The server's stop waited for the viewer to take what was sent to it, for good: a Ctrl-C never
    ended `tether view` (seen as a view not stopping within 20 s of its SIGINT in CI)."""
    server, viewer = stalled
    ended: list[bool] = []
    ending = threading.Thread(
        target=lambda: ended.append(view.shut_down(None, threading.Event(), [], server)), daemon=True
    )
    ending.start()
    ending.join(WAIT)
    try:
        assert ended == [False], "the view's end waited for the viewer"
    finally:
        viewer.close()
