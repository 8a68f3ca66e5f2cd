"""The robot's camera in a process of its own: a second pybullet client draws what the sim thread hands it.

A frame cost some 20 ms of CPU with the GIL held when the camera drew the arm's detailed meshes
(pybullet's CPU renderer, then the detector in numpy and shapely; a picture also its PNG encoding);
about 3 ms now, a picture more. On the sim's thread that held back physics, odometry, joint states
and the action servers for as long. Instead the sim thread reads where every
movable body stands (`SimWorld.poses`, tens of microseconds) and hands that to `Renderer`; the
child (`python -m services.sim.renderer`) has the same world loaded, puts its bodies there,
renders, detects with the same seeded noise (`Sensors.perceived_objects`, as in one process) and
sends back the objects or the PNG, which the sim publishes from the renderer's thread.

Frames never queue: at most one frame of detections and one picture per scale wait to be drawn; a
newer one replaces the waiting one (the older is dropped, counted in `dropped`). The child exits
with the sim, also when the sim is killed: its end of the pipe closes, or its parent changes. A
child that dies is logged once and named in `failure`: detections stop (the resolver sees them go
stale) and pictures are refused, while the sim goes on controlling the robot.
"""

from __future__ import annotations

import argparse
import base64
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from schemas.common import ErrorKind, ServiceError
from schemas.world import CameraImage, PerceivedObjects, World
from services.errors import CallError
from services.sim.config import CameraConfig
from services.sim.world import Poses

log = logging.getLogger(__name__)

# Wall seconds for the child to load the world (slow on a busy machine), and for one frame.
START_TIMEOUT = 60.0
FRAME_TIMEOUT = 10.0
# How often a waiting end checks the other is still there.
CHECK_PERIOD = 0.5
STOP_TIMEOUT = 2.0


@dataclass(frozen=True)
class Picture:
    """A colour image as PNG, and its size in pixels."""

    width: int
    height: int
    png: bytes


Deliver = Callable[[Any], None]


@dataclass
class _Pending:
    """A picture waiting to be drawn: the latest poses asked for, and everyone waiting for it."""

    poses: Poses
    waiting: list[Callable[[Picture | None], None]] = field(default_factory=list)


class RendererDied(Exception):
    """The child exited, stopped answering or could not load the world."""


class Renderer:
    """The sim's end: hands poses to the child and delivers what comes back, on a thread of its own.

    Built on any thread; the child starts at once and loads the world while the sim starts up
    (frames asked for meanwhile wait, the latest of each kind only).
    """

    def __init__(self, world: World, camera: CameraConfig) -> None:
        self.failure: str | None = None
        self.dropped = 0
        self.frames = 0
        self._cond = threading.Condition()
        self._objects: tuple[Poses, Deliver] | None = None
        self._pictures: dict[int, _Pending] = {}
        self._closed = False
        self._publish_failing = False
        ours, theirs = socket.socketpair()
        with theirs:
            fd = theirs.fileno()
            command = [sys.executable, "-m", "services.sim.renderer", "--fd", str(fd), "--parent", str(os.getpid())]
            self._process = subprocess.Popen(command, pass_fds=(fd,), stdin=subprocess.DEVNULL)
        self.pid = self._process.pid
        self._conn = Connection(ours.detach())
        self._thread = threading.Thread(target=self._serve, args=(world, camera), name="camera-renderer", daemon=True)
        self._thread.start()

    # From the sim thread and others

    def detect(self, poses: Poses, deliver: Callable[[PerceivedObjects], None]) -> None:
        """Detect objects as seen from `poses`; `deliver` gets them (on the renderer's thread). A frame
        still waiting is dropped for this one; nothing happens once the child is dead."""
        with self._cond:
            if self.failure is not None or self._closed:
                return
            if self._objects is not None:
                self.dropped += 1
            self._objects = (poses, deliver)
            self._cond.notify()

    def picture(self, poses: Poses, scale: int, deliver: Callable[[Picture | None], None]) -> None:
        """A colour picture as seen from `poses`, `scale` times the detector's resolution; `deliver` gets
        it, or None when the child is dead. Asked again before it is drawn, the later poses win and
        both askers get that picture."""
        with self._cond:
            if self.failure is None and not self._closed:
                pending = self._pictures.setdefault(scale, _Pending(poses))
                pending.poses = poses
                pending.waiting.append(deliver)
                self._cond.notify()
                return
        deliver(None)

    def camera_image(self, poses: Poses, scale: int, timeout: float) -> CameraImage:
        """The picture for a query (sim/camera): waits for it; an unavailable error when the child is
        dead or does not answer within `timeout`."""
        box: list[Picture | None] = []
        drawn = threading.Event()

        def deliver(picture: Picture | None) -> None:
            box.append(picture)
            drawn.set()

        self.picture(poses, scale, deliver)
        if not drawn.wait(timeout) or box[0] is None:
            reason = self.failure or f"no picture within {timeout:g} s"
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=f"the camera: {reason}"))
        picture = box[0]
        data = base64.b64encode(picture.png).decode()
        return CameraImage(stamp=poses.stamp, width=picture.width, height=picture.height, data=data)

    def close(self) -> None:
        """Stop the child (it exits on the closed pipe; killed if it does not) and the thread."""
        with self._cond:
            self._closed = True
            pictures, self._pictures = self._pictures, {}
            self._cond.notify()
        self._thread.join(FRAME_TIMEOUT + CHECK_PERIOD)
        self._conn.close()
        try:
            self._process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        for pending in pictures.values():
            for deliver in pending.waiting:
                deliver(None)

    # The renderer's thread

    def _serve(self, world: World, camera: CameraConfig) -> None:
        try:
            self._conn.send(("setup", world, camera))
            _, pid = self._receive(START_TIMEOUT, "ready")
            log.info("camera renderer up (pid %d)", pid)
            while True:
                with self._cond:
                    # Nothing to draw: still notice at once when the child dies.
                    while not (self._closed or self._objects is not None or self._pictures):
                        if not self._cond.wait(CHECK_PERIOD) and self._process.poll() is not None:
                            raise RendererDied(f"exited with code {self._process.returncode}")
                    if self._closed:
                        return
                    # A picture first: someone waits for it; detections come at their rate anyway.
                    if self._pictures:
                        scale = next(iter(self._pictures))
                        job: tuple[str, Any] = ("picture", (scale, self._pictures.pop(scale)))
                    else:
                        assert self._objects is not None
                        job, self._objects = ("objects", self._objects), None
                self._run(job)
        except (RendererDied, EOFError, OSError) as exc:
            self._died(exc)

    def _run(self, job: tuple[str, Any]) -> None:
        kind, what = job
        if kind == "picture":
            scale, pending = what
            self._conn.send(("picture", pending.poses, scale))
            _, width, height, png = self._receive(FRAME_TIMEOUT, "picture")
            picture = Picture(width, height, png)
            for deliver in pending.waiting:
                deliver(picture)
            return
        poses, deliver = what
        self._conn.send(("objects", poses))
        _, objects = self._receive(FRAME_TIMEOUT, "objects")
        self.frames += 1
        try:
            deliver(objects)
        except Exception:
            if not self._publish_failing:
                log.exception("objects not published")
            self._publish_failing = True
        else:
            if self._publish_failing:
                log.info("objects published again")
            self._publish_failing = False

    def _receive(self, timeout: float, expected: str) -> tuple[Any, ...]:
        """The child's next message, which must be `expected`; RendererDied when it exits or takes
        longer than `timeout` (then it is killed)."""
        deadline = time.monotonic() + timeout
        while not self._conn.poll(CHECK_PERIOD):
            code = self._process.poll()
            if code is not None:
                raise RendererDied(f"exited with code {code}")
            if self._closed and expected == "ready":
                raise RendererDied("closed before it was up")
            if time.monotonic() > deadline:
                self._kill()
                raise RendererDied(f"gave no {expected} within {timeout:g} s and was killed")
        message: tuple[Any, ...] = self._conn.recv()
        if message[0] == "failed":
            raise RendererDied(f"failed: {message[1]}")
        if message[0] != expected:
            raise RendererDied(f"answered {message[0]!r} to a request for {expected!r}")
        return message

    def _kill(self) -> None:
        """Kill the child and reap it: left unwaited it stayed a zombie until the sim restarted."""
        self._process.kill()
        try:
            self._process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            log.error("camera renderer (pid %d) did not exit when killed", self.pid)

    def _died(self, exc: BaseException) -> None:
        with self._cond:
            closing = self._closed
            if not closing:
                code = self._process.poll()
                reason = str(exc) if isinstance(exc, RendererDied) else f"{type(exc).__name__}: {exc}"
                if code is not None and "exited" not in reason:
                    reason = f"{reason} (exited with code {code})"
                self.failure = f"the renderer process (pid {self.pid}) {reason}"
            pictures, self._pictures, self._objects = self._pictures, {}, None
        if not closing:
            log.error(
                "camera renderer is gone: %s; no detections or pictures until the sim restarts "
                "(the robot is still controlled and reports its state)",
                self.failure,
            )
        for pending in pictures.values():
            for deliver in pending.waiting:
                deliver(None)


# The child


def _watch_parent(parent: int) -> None:
    """Exit once the parent is gone, even in the middle of a frame (the pipe tells only between frames)."""
    while True:
        time.sleep(CHECK_PERIOD)
        if os.getppid() != parent:
            os._exit(0)


def serve(conn: Connection, parent: int) -> None:
    """The child's loop: load the world it is sent, then draw each request until the pipe closes."""
    from services.heap import release_free_memory
    from services.sim.camera import png
    from services.sim.sensors import Sensors
    from services.sim.world import SimWorld

    threading.Thread(target=_watch_parent, args=(parent,), name="parent-watch", daemon=True).start()
    try:
        _, world, camera = conn.recv()
        scene = SimWorld(world, detailed_arm=camera.detailed_arm)
        sensors = Sensors(scene, camera)
        # Most frames are asked for while nothing in view moves (a robot at rest, waiting for its next
        # goal): the last drawing is detected on again, with fresh noise, rather than drawn again.
        sensors.camera.keep_frames()
        shown: Poses | None = None
        release_free_memory()  # what loading the meshes freed (services/heap.py)
    except EOFError:
        return
    except Exception as exc:
        log.exception("could not load the world")
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return  # the sim closed its end, or died
        kind, poses = request[0], request[1]
        if shown is None or not poses.stands_as(shown):
            scene.pose_as(poses)
            sensors.camera.scene_moved()
            shown = poses
        scene.holding = poses.holding
        if kind == "objects":
            reply: tuple[Any, ...] = ("objects", sensors.perceived_objects(poses.stamp))
        else:
            pixels = sensors.camera_picture(request[2])
            reply = ("picture", pixels.shape[1], pixels.shape[0], png(pixels))
        try:
            conn.send(reply)
        except OSError:
            return


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m services.sim.renderer", description=__doc__)
    parser.add_argument("--fd", type=int, required=True, help="this end of the socket pair to the sim")
    parser.add_argument("--parent", type=int, required=True, help="the sim's pid: exit once it is gone")
    args = parser.parse_args(argv)
    # A stop meant for the sim reaches this process too (a terminal's Ctrl-C, the Supervisor's and
    # systemd's SIGTERM to the whole group): this one ends when the sim closes its end or is gone,
    # so the sim never sees its renderer die while it shuts down.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(
        level=os.environ.get("TETHER_LOG_LEVEL", "INFO").upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if os.getppid() != args.parent:
        return  # the sim died before this started
    with Connection(args.fd) as conn:
        serve(conn, args.parent)


if __name__ == "__main__":
    main()
