"""A test's stand-in for a remote HTTP service (an LLM's chat-completions API): a handler served on a
loopback port from a thread of its own."""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


class QuietHandler(BaseHTTPRequestHandler):
    """A request handler that logs nothing and answers with `reply`."""

    def reply(self, status: int, body: bytes, content_type: str = "application/json") -> None:
        self.send_response(status)
        self.send_header("content-type", content_type)
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        pass


class _Server(ThreadingHTTPServer):
    # socketserver's backlog of 5: many connections arriving at once on a loaded machine, before the
    # accepting thread ran, were reset ("Connection reset by peer"), and so answered, by the kernel.
    request_queue_size = 128
    daemon_threads = True


class LoopbackServer:
    """`handler` served on 127.0.0.1 at a free port; `url` is its /v1 base, as an OpenAI-style client
    takes it. `close` stops it and waits for its thread."""

    def __init__(self, handler: type[BaseHTTPRequestHandler], name: str, poll_interval: float = 0.5) -> None:
        self.server = _Server(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"
        self.thread = threading.Thread(
            target=self.server.serve_forever, kwargs={"poll_interval": poll_interval}, name=name, daemon=True
        )
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(timeout=5)
