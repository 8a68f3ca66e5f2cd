"""The camera's renderer process: the same detections and pictures as rendering in the sim's own process;
frames dropped rather than queued; a dead renderer named, and the child gone with its parent."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pybullet
import pytest

from schemas.common import ErrorKind
from schemas.world import MoveEntity, PerceivedObjects
from services.errors import CallError
from services.sim.camera import png_base64
from services.sim.config import CameraConfig
from services.sim.renderer import Renderer
from services.sim.robot_urdf import mobile_manipulator_urdf
from services.sim.simulation import Simulation
from services.sim.world import STILL, TEXTURE_SIZE, Drop, hulls_as_visuals, with_small_textures
from services.worldmodel import load_world
from tests.procs import gone, wait_until

WORLD = load_world("household")
CAMERA = CameraConfig()  # with its seeded noise: both processes must draw the same numbers
DEADLINE = 30.0  # seconds for the child to load the world and draw, on a busy machine


class Frames:
    """What a renderer delivers, for waiting on."""

    def __init__(self) -> None:
        self.objects: list[PerceivedObjects] = []
        self._arrived = threading.Condition()

    def deliver(self, objects: PerceivedObjects) -> None:
        with self._arrived:
            self.objects.append(objects)
            self._arrived.notify_all()

    def wait(self, count: int, timeout: float = DEADLINE) -> bool:
        with self._arrived:
            return self._arrived.wait_for(lambda: len(self.objects) >= count, timeout)


@pytest.fixture(scope="module")
def sims() -> Iterator[tuple[Simulation, Simulation]]:
    """(the sim without visuals, as the service runs it; one rendering in this process, the reference)."""
    sim, reference = Simulation(WORLD, camera=CAMERA, visuals=False), Simulation(WORLD, camera=CAMERA)
    yield sim, reference
    sim.close()
    reference.close()


@pytest.fixture(scope="module")
def renderer() -> Iterator[Renderer]:
    renderer = Renderer(WORLD, CAMERA)
    yield renderer
    renderer.close()


def test_detections_and_pictures_are_the_ones_the_sims_own_process_would_render(
    sims: tuple[Simulation, Simulation], renderer: Renderer
) -> None:
    sim, reference = sims
    frames = Frames()
    # An object moved into view, the robot turned and its arm swung: the renderer sees what the sim has.
    assert isinstance(sim.scene.move(MoveEntity(id="red_cup", x=7.8, y=2.4)), Drop)
    sim.settle(1.0)
    robot = sim.robot
    robot.bullet.resetJointState(robot.id, robot.base_joints[2], 0.15)
    robot.bullet.resetJointState(robot.id, robot.arm_joints[0], 0.4)
    for i in range(3):
        renderer.detect(sim.scene.poses(float(i)), frames.deliver)
        assert frames.wait(i + 1), "no detections from the renderer"
    # The reference renders in this process, its bodies put where the sim's are.
    reference.scene.pose_as(sim.scene.poses(0.0))
    expected = [reference.sensors.perceived_objects(float(i)) for i in range(3)]
    assert frames.objects == expected
    assert {"red_cup", "blue_book"} <= {o.id for o in frames.objects[0].objects}
    # The noise is the same seeded sequence, frame after frame: the positions differ between frames.
    assert frames.objects[0].objects != frames.objects[1].objects

    image = renderer.camera_image(sim.scene.poses(9.0), scale=2, timeout=DEADLINE)
    assert (image.width, image.height, image.stamp) == (2 * CAMERA.width, 2 * CAMERA.height, 9.0)
    assert image.data == png_base64(reference.sensors.camera_picture(2))


def test_a_frame_is_drawn_again_once_anything_moved_and_kept_while_nothing_did(
    sims: tuple[Simulation, Simulation], renderer: Renderer
) -> None:
    sim, _ = sims
    frames = Frames()

    def red_cup_seen_at(stamp: float) -> tuple[float, float]:
        renderer.detect(sim.scene.poses(stamp), frames.deliver)
        assert frames.wait(len(frames.objects) + 1), "no detections from the renderer"
        (cup,) = (o for o in frames.objects[-1].objects if o.id == "red_cup")
        return cup.position.x, cup.position.y

    drawn = renderer.frames
    for x, y in ((7.8, 2.4), (7.65, 2.6)):
        assert isinstance(sim.scene.move(MoveEntity(id="red_cup", x=x, y=y)), Drop)
        sim.settle(1.0)
        for stamp in (300.0, 301.0):  # the second with nothing moved: the same drawing, fresh noise
            seen = red_cup_seen_at(stamp)
            assert abs(seen[0] - x) < 0.02 and abs(seen[1] - y) < 0.02, (x, y, seen)
    assert renderer.frames - drawn == 4

    # Where things stand, to the tolerance: a creep of a tenth of it is standing still, a centimetre is not.
    still = sim.scene.poses(0.0)
    crept = replace(still, joints=(still.joints[0] + STILL / 10, *still.joints[1:]))
    moved = replace(still, joints=(still.joints[0] + 0.01, *still.joints[1:]))
    cup = still.objects["red_cup"]
    lifted = replace(still, objects=still.objects | {"red_cup": ((cup[0][0], cup[0][1], cup[0][2] + 0.01), cup[1])})
    assert crept.stands_as(still) and not moved.stands_as(still) and not lifted.stands_as(still)


def test_a_sim_without_visuals_refuses_to_render_in_its_own_process(sims: tuple[Simulation, Simulation]) -> None:
    sim, _ = sims
    with pytest.raises(RuntimeError, match="renderer"):
        sim.sensors.perceived_objects(0.0)


def test_frames_asked_for_while_the_renderer_is_busy_are_dropped_for_the_latest(
    sims: tuple[Simulation, Simulation], renderer: Renderer
) -> None:
    sim, _ = sims
    frames = Frames()
    dropped, drawn = renderer.dropped, renderer.frames
    for i in range(30):  # far faster than it draws
        renderer.detect(sim.scene.poses(100.0 + i), frames.deliver)
    assert frames.wait(1)
    assert wait_until(lambda: renderer.frames - drawn == len(frames.objects) and frames.objects[-1].stamp == 129.0, 20)
    assert renderer.dropped - dropped == 30 - len(frames.objects) > 0
    stamps = [f.stamp for f in frames.objects]
    assert stamps == sorted(stamps) and len(stamps) < 30


def test_a_dead_renderer_is_named_and_refuses_pictures(
    sims: tuple[Simulation, Simulation], caplog: pytest.LogCaptureFixture
) -> None:
    sim, _ = sims
    renderer = Renderer(WORLD, CAMERA)
    try:
        frames = Frames()
        renderer.detect(sim.scene.poses(1.0), frames.deliver)
        assert frames.wait(1)
        with caplog.at_level(logging.ERROR, logger="services.sim.renderer"):
            os.kill(renderer.pid, signal.SIGKILL)
            assert wait_until(lambda: renderer.failure is not None, 10.0)
        assert renderer.failure is not None and str(renderer.pid) in renderer.failure
        assert f"code {-signal.SIGKILL}" in renderer.failure
        assert any("camera renderer is gone" in r.getMessage() for r in caplog.records)
        renderer.detect(sim.scene.poses(2.0), frames.deliver)  # no error, nothing delivered
        with pytest.raises(CallError) as refused:
            renderer.camera_image(sim.scene.poses(2.0), scale=1, timeout=5.0)
        assert refused.value.error.kind is ErrorKind.UNAVAILABLE
        assert str(renderer.pid) in refused.value.error.message
        assert len(frames.objects) == 1
    finally:
        renderer.close()


HOST = """
import sys, time
from services.sim.config import CameraConfig
from services.sim.renderer import Renderer
from services.worldmodel import load_world
from tests.procs import gone, wait_until
renderer = Renderer(load_world("household"), CameraConfig())
print(renderer.pid, flush=True)
time.sleep(600)
"""


def test_the_renderer_exits_when_its_parent_is_killed() -> None:
    host = subprocess.Popen([sys.executable, "-c", HOST], stdout=subprocess.PIPE, text=True)
    child = None
    try:
        assert host.stdout is not None
        child = int(host.stdout.readline())
        assert not gone(child)
        assert "services.sim.renderer" in Path(f"/proc/{child}/cmdline").read_text()
        host.kill()  # SIGKILL: nothing of the parent's runs
        host.wait(10)
        assert wait_until(lambda: gone(child), 10.0), f"renderer {child} outlived its parent"
    finally:
        host.kill()
        host.wait(10)
        if host.stdout is not None:
            host.stdout.close()
        if child is not None and not gone(child):
            os.kill(child, signal.SIGKILL)


def _drawn(urdf: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The robot alone, close up from beside it: each pixel's colour, and whether the arm (a link of
    the Panda's, not the base's box) covers it."""
    client = pybullet.connect(pybullet.DIRECT)
    try:
        path.write_text(urdf)
        body = pybullet.loadURDF(str(path), useFixedBase=True, physicsClientId=client)
        links = range(pybullet.getNumJoints(body, physicsClientId=client))
        arm = [i for i in links if pybullet.getJointInfo(body, i, physicsClientId=client)[12].startswith(b"panda_")]
        view = pybullet.computeViewMatrix([1.0, 0.9, 1.2], [0.2, 0.0, 0.8], [0, 0, 1], physicsClientId=client)
        projection = pybullet.computeProjectionMatrixFOV(60, 1.0, 0.05, 10, physicsClientId=client)
        by_link = pybullet.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX
        _, _, rgba, _, segmentation = pybullet.getCameraImage(
            200, 200, view, projection, flags=by_link, physicsClientId=client
        )
        colours = np.asarray(rgba, dtype=int).reshape(200, 200, 4)[..., :3]
        # With the link index: body + ((link + 1) << 24) where something is hit, -1 where nothing is.
        seen = np.asarray(segmentation).reshape(200, 200)
        return colours, (seen >= 0) & np.isin((seen >> 24) - 1, arm)
    finally:
        pybullet.disconnect(client)


def test_the_arm_drawn_with_its_small_palette_looks_as_with_the_full_one(tmp_path: Path) -> None:
    """The renderer's copy of the Panda's colour palette (with_small_textures, for `detailed_arm`)
    changes no colour the camera can see: the arm drawn both ways, close up, differs in almost no pixel."""
    from PIL import Image

    full = mobile_manipulator_urdf(WORLD.robot)
    small = with_small_textures(full, tmp_path)
    sizes = []
    for palette in tmp_path.glob("*/*.png"):
        with Image.open(palette) as image:
            sizes.append(image.size)
    assert sizes and set(sizes) == {(TEXTURE_SIZE, TEXTURE_SIZE)}, sizes
    assert str(tmp_path) in small and str(tmp_path) not in full

    (before, arm), (after, _) = _drawn(full, tmp_path / "full.urdf"), _drawn(small, tmp_path / "small.urdf")
    assert arm.mean() > 0.05, "the arm is in the picture"
    changed = (np.abs(before - after).max(-1) > 10).mean()
    assert changed < 0.005, f"{changed:.2%} of the pixels changed colour"


def test_the_arm_drawn_as_its_hulls_hides_all_its_meshes_hide_and_little_more(tmp_path: Path) -> None:
    """The camera's arm by default (hulls_as_visuals): every pixel the detailed meshes cover, the
    hulls cover too, so nothing behind the arm is seen that the meshes would hide; they add some 7 %
    round the edges (measured: 7.4 %, none missed), and the arm has no mesh left to draw."""
    full = mobile_manipulator_urdf(WORLD.robot)
    hulls = hulls_as_visuals(full)
    assert "meshes/visual" in full and "meshes/visual" not in hulls
    (_, meshes), (_, hulled) = _drawn(full, tmp_path / "full.urdf"), _drawn(hulls, tmp_path / "hulls.urdf")
    assert meshes.mean() > 0.05, "the arm is in the picture"
    missed = (meshes & ~hulled).sum() / meshes.sum()
    added = (hulled & ~meshes).sum() / meshes.sum()
    assert missed < 0.002, f"{missed:.2%} of the arm's pixels are not covered by its hulls"
    assert added < 0.1, f"the hulls cover {added:.2%} more than the arm"
