"""Binds the recorder to a ROS 2 robot's own Zenoh network: a second session, every topic sample in."""

from __future__ import annotations

import contextlib
import logging
import re
import threading
from typing import Any

import msgspec
import zenoh

from services.recorder.recorder import Recorder
from services.recorder.ros2file import Ros2Source

log = logging.getLogger(__name__)

# Opening the session is tried again at these intervals (seconds) until it opens: the robot's router
# may come up after the recorder.
RETRY_FIRST = 0.5
RETRY_MAX = 5.0
# zenoh ends its error texts with the Rust source location ("... at /root/.cargo/.../orchestrator.rs:447.").
_SOURCE_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?$")


def session_config(source: Ros2Source) -> zenoh.Config:
    """A client (or peer) connecting to the robot's endpoint only: no multicast scouting, no listening."""
    conf = zenoh.Config()
    conf.insert_json5("mode", msgspec.json.encode(source.mode).decode())
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", msgspec.json.encode([source.endpoint]).decode())
    conf.insert_json5("listen/endpoints", "[]")
    return conf


class Ros2Link:
    """Opens the session in the background, retrying until it opens, and hands every sample under the
    robot's keys to `recorder.record_ros2`. Whatever arrives, nothing here raises into tether's side."""

    def __init__(self, source: Ros2Source, recorder: Recorder) -> None:
        self.source = source
        self.keys = source.keys
        self.recorder = recorder
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._lock = threading.Lock()
        self._failures = 0
        self._connected = True  # as far as poll() last saw
        self._thread = threading.Thread(target=self._run, name="ros2-link", daemon=True)

    def start(self) -> None:
        self.recorder.ros2_link_failed(f"connecting to {self.source.endpoint}")
        self._thread.start()

    def _run(self) -> None:
        delay = RETRY_FIRST
        failed_before = ""
        while not self._stop.is_set():
            try:
                session = zenoh.open(session_config(self.source))
            except zenoh.ZError as exc:
                reason = _SOURCE_LOCATION.sub("", str(exc)).strip()
                where = f"a {self.source.mode} session to the ROS 2 robot at {self.source.endpoint}"
                error = f"cannot open {where}: {reason}"
                self.recorder.ros2_link_failed(f"{error} (trying again)")
                # Once at ERROR, then quietly until it changes: the robot may be down for hours.
                log.log(logging.ERROR if error != failed_before else logging.DEBUG, "%s; trying again", error)
                failed_before = error
                self._stop.wait(delay)
                delay = min(delay * 2, RETRY_MAX)
                continue
            with self._lock:
                if self._stop.is_set():
                    session.close()
                    return
                try:
                    for key_expr in self.keys.key_exprs():
                        self._subscribers.append(session.declare_subscriber(key_expr, self._on_sample))
                except zenoh.ZError as exc:
                    session.close()
                    error = f"cannot subscribe to {key_expr} on the ROS 2 robot's network: {exc}"
                    self.recorder.ros2_link_failed(error)
                    log.error("%s", error)
                    return
                self._session = session
            self.recorder.ros2_link_failed("")
            log.info("recording the ROS 2 robot at %s: %s", self.source.endpoint, ", ".join(self.keys.key_exprs()))
            return

    def poll(self) -> None:
        """Shows in the status whether the open session reaches the robot (zenoh reconnects by itself)."""
        with self._lock:
            session = self._session
            if session is None:
                return
            try:
                connected = bool(session.info.routers_zid() or session.info.peers_zid())
            except zenoh.ZError:
                return
        if connected != self._connected:
            self._connected = connected
            if connected:
                log.info("the ROS 2 robot at %s is back", self.source.endpoint)
            else:
                log.warning("lost the ROS 2 robot at %s; zenoh is reconnecting", self.source.endpoint)
        lost = f"no connection to the ROS 2 robot at {self.source.endpoint} (zenoh is reconnecting)"
        self.recorder.ros2_link_failed("" if connected else lost)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.recorder.record_ros2(str(sample.key_expr), sample.payload.to_bytes(), attachment)
        except Exception:
            # A sample this side cannot handle is lost; the recorder, and tether's file, go on. The
            # traceback once, then a count: a robot sending only such samples must not flood the log.
            self._failures += 1
            if self._failures == 1:
                log.exception("ROS 2 sample on %s not recorded", sample.key_expr)
            else:
                log.debug("ROS 2 sample on %s not recorded (%d so far)", sample.key_expr, self._failures)

    def close(self) -> None:
        """Stop trying, undeclare and close the session: no sample is delivered after this returns."""
        self._stop.set()
        with self._lock:
            for subscriber in self._subscribers:
                with contextlib.suppress(zenoh.ZError):
                    subscriber.undeclare()
            self._subscribers.clear()
            if self._session is not None:
                self._session.close()
                self._session = None
        self._thread.join(timeout=5.0)
