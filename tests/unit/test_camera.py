"""The sim's camera on the household world in pybullet (DIRECT): what it sees and how well."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pybullet_data
import pytest

from schemas.actions import GoalState
from schemas.common import Pose2D, Vec3
from schemas.robot import NavigateToPoseGoal
from schemas.world import MoveEntity, PerceivedObject
from services.executor.navigation import BasePlanner
from services.runtime import ConfigError, load_config
from services.sim.config import CameraConfig, SimConfig
from services.sim.simulation import Simulation
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.simthread import moved

WORLD = load_world("household")
GRASP_TOLERANCE = 0.015
EXACT = CameraConfig(noise=0.0)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    # Physics at 120 Hz, as the integration stacks run it: the drives to each top take half the steps.
    simulation = Simulation(WORLD, camera=EXACT, physics_hz=FAST_PHYSICS_HZ)
    yield simulation
    simulation.close()


def approach(furniture_id: str) -> Pose2D:
    return next(f.approach for f in WORLD.furniture if f.id == furniture_id)


@functools.cache
def _planner(world_name: str) -> BasePlanner:
    return BasePlanner(WorldModel(load_world(world_name)))


def route_planner(sim: Simulation) -> BasePlanner:
    return _planner(sim.world.name)


def drive(sim: Simulation, pose: Pose2D) -> None:
    # Through the doorways, as the executor would plan it.
    path = route_planner(sim).plan(sim.robot.base_pose(), pose)
    motion = sim.run(sim.controllers.navigate(NavigateToPoseGoal(pose=pose, path=path)), timeout=120.0)
    assert motion.state is GoalState.SUCCEEDED, motion.message


def seen(sim: Simulation) -> dict[str, PerceivedObject]:
    return {o.id: o for o in sim.sensors.perceived_objects(0.0).objects}


def error(a: Vec3, b: Vec3) -> float:
    return math.dist((a.x, a.y, a.z), (b.x, b.y, b.z))


def pixel_of(sim: Simulation, point: Vec3) -> tuple[int, int] | None:
    """The pixel (row, column) `point` projects to, if inside the image and in range, whatever may
    stand in between."""
    camera, lens = sim.sensors.camera, sim.sensors.camera.intrinsics
    x, y, z, _ = np.linalg.inv(camera.pose(sim.robot.base_pose())) @ [point.x, point.y, point.z, 1.0]
    depth = -z
    if not (lens.near < depth <= camera.config.max_range):
        return None
    col = round((x / depth / lens.tan_half_h + 1) / 2 * lens.width)
    row = round(lens.height - 1 - (y / depth / lens.tan_half_v + 1) / 2 * lens.height)
    return (row, col) if 0 <= row < lens.height and 0 <= col < lens.width else None


@pytest.mark.parametrize("furniture", ["kitchen_counter", "kitchen_table", "coffee_table"])
def test_from_the_approach_pose_every_object_on_the_furniture_is_seen_well_enough_to_grasp(
    sim: Simulation, furniture: str
) -> None:
    drive(sim, approach(furniture))
    truth = {o.id: o for o in sim.scene.ground_truth().objects}
    visible = seen(sim)
    # The pan, 0.75 m along the counter to the robot's left, is out of the camera's view.
    expected = {o.id for o in WORLD.objects if o.support == furniture and o.id != "cast_iron_pan"}
    assert set(visible) == expected
    for object_id, obj in visible.items():
        assert (obj.on, obj.room) == (truth[object_id].on, truth[object_id].room)
        assert error(obj.position, truth[object_id].position) < GRASP_TOLERANCE, object_id


@pytest.mark.parametrize("furniture", [f.id for f in WORLD.furniture])
def test_the_furniture_top_is_in_view_and_the_stowed_arm_never_blocks_it(sim: Simulation, furniture: str) -> None:
    item = next(f for f in WORLD.furniture if f.id == furniture)
    drive(sim, approach(furniture))
    frame = sim.sensors.camera.render(sim.robot.base_pose())
    assert sim.robot.id not in frame.segmentation
    # The top's centre, and where things are put down: 15 cm in from the near edge, straight ahead.
    here = sim.robot.base_pose()
    cx, cy = item.center
    half_depth = item.size.y / 2 if abs(math.sin(here.yaw)) > 0.5 else item.size.x / 2
    near_edge = math.hypot(cx - here.x, cy - here.y) - half_depth
    spot = (here.x + (near_edge + 0.15) * math.cos(here.yaw), here.y + (near_edge + 0.15) * math.sin(here.yaw))
    for x, y in ((cx, cy), spot):
        pixel = pixel_of(sim, Vec3(x=x, y=y, z=item.size.z))
        assert pixel is not None, f"({x:.2f}, {y:.2f}) on the {furniture} is out of view"
        assert frame.segmentation[pixel] == sim.scene.furniture_bodies[furniture]


def test_from_the_start_the_coffee_table_and_its_book_are_seen_and_the_kitchen_is_not(sim: Simulation) -> None:
    frame = sim.sensors.camera.render(sim.robot.base_pose())
    assert sim.scene.furniture_bodies["coffee_table"] in frame.segmentation
    visible = seen(sim)
    assert set(visible) == {"blue_book"}
    assert visible["blue_book"].on == "coffee_table"
    # Far off and seen edge-on, it is still placed within a few centimetres.
    assert error(visible["blue_book"].position, sim.scene.object_position("blue_book")) < 0.03


def test_an_object_hidden_behind_furniture_is_not_reported(sim: Simulation) -> None:
    drive(sim, approach("kitchen_table"))
    behind_the_table = moved(sim, MoveEntity(id="red_cup", x=2.5, y=4.4))
    assert behind_the_table.position.z == pytest.approx(0.05, abs=0.005)
    assert pixel_of(sim, behind_the_table.position) is not None, "only the table is in the way"
    assert "red_cup" not in seen(sim)
    cup = next(o for o in sim.scene.ground_truth().objects if o.id == "red_cup")
    assert (cup.on, cup.room) == (None, "kitchen")


def test_the_held_object_is_reported_exactly_and_on_the_gripper(sim: Simulation) -> None:
    drive(sim, approach("kitchen_counter"))
    assert sim.scene.grasp("red_cup") is None  # the robot's own record of what it holds, not a camera's
    visible = seen(sim)
    assert visible["red_cup"].on == "gripper"
    assert visible["red_cup"].position == sim.scene.object_position("red_cup")
    assert visible["coffee_mug"].on == "kitchen_counter"


def test_noise_is_seeded_and_has_the_configured_spread() -> None:
    noisy = CameraConfig(noise=0.004, seed=7)
    runs = []
    for config in (noisy, noisy, CameraConfig(noise=0.004, seed=8)):
        simulation = Simulation(WORLD, camera=config)
        try:
            runs.append([seen(simulation)["blue_book"].position for _ in range(40)])
        finally:
            simulation.close()
    assert runs[0] == runs[1], "the same seed gives the same noise"
    assert runs[0] != runs[2]
    xs = np.array([[p.x, p.y, p.z] for p in runs[0]])
    assert 0.002 < float(np.mean(np.std(xs, axis=0))) < 0.006


def test_without_noise_every_frame_agrees(sim: Simulation) -> None:
    first, second = seen(sim)["blue_book"], seen(sim)["blue_book"]
    assert first.position == second.position


def test_an_object_moved_onto_furniture_rests_on_it_and_the_camera_sees_it_there(sim: Simulation) -> None:
    drive(sim, approach("kitchen_counter"))
    assert "blue_book" not in seen(sim)
    put = moved(sim, MoveEntity(id="blue_book", x=2.5, y=0.45, yaw=0.3))
    assert (put.position.x, put.position.y) == pytest.approx((2.5, 0.45), abs=0.005)
    assert put.position.z == pytest.approx(0.9 + 0.015, abs=0.003)
    book = seen(sim)["blue_book"]
    assert book.on == "kitchen_counter" and book.room == "kitchen"
    assert error(book.position, put.position) < GRASP_TOLERANCE


def test_the_floor_is_drawn_in_pictures_only_and_hides_nothing_the_detector_looks_for(sim: Simulation) -> None:
    """Detection frames leave the floor out (it fills much of the frame, and pybullet's CPU renderer pays
    per pixel drawn); what the camera sees is the same with it, an object lying on it too, and
    pictures, for people, draw it."""
    camera, base, floor = sim.sensors.camera, sim.robot.base_pose(), sim.scene.floor
    dropped = moved(sim, MoveEntity(id="apple", x=base.x + 1.4, y=base.y - 0.2))  # on the floor, in view
    assert dropped.position.z < 0.1, dropped
    assert not (camera.render(base).segmentation == floor).any()
    without = seen(sim)
    assert without["apple"].on is None and error(without["apple"].position, dropped.position) < GRASP_TOLERANCE
    camera.show_floor(True)
    try:
        covered = camera.render(base).segmentation == floor
        with_floor = seen(sim)
    finally:
        camera.show_floor(False)
    assert covered.mean() > 0.3, "from the start pose the floor fills much of the frame"
    assert without and with_floor == without
    picture = sim.sensors.camera_picture(1)
    background = (picture[covered] == 255).all(-1).mean()  # the renderer's clear colour is white
    assert background < 0.01, f"{background:.1%} of the floor's pixels are not drawn in the picture"
    assert not (camera.render(base).segmentation == floor).any(), "a picture leaves the floor out again"


def test_camera_config_comes_from_the_sim_table_and_bad_values_are_named(tmp_path: Path) -> None:
    config = tmp_path / "tether.toml"
    config.write_text("[sim]\nrealtime_factor = 2\n\n[sim.camera]\nnoise = 0.0\nseed = 3\n")
    camera = load_config(SimConfig, config, "sim").camera
    assert (camera.noise, camera.seed, camera.hfov_deg) == (0.0, 3, 87.0)
    config.write_text("[sim.camera]\nnoise = -0.01\n")
    with pytest.raises(ConfigError, match=r"camera\.noise"):
        load_config(SimConfig, config, "sim")


def test_the_camera_draws_the_arms_hulls_unless_the_config_asks_for_its_meshes(tmp_path: Path) -> None:
    """`[sim.camera] detailed_arm` reaches the world the camera draws: without it every mesh drawn is
    one of the Panda's collision meshes (the hulls: tests/unit/test_renderer.py compares them with
    the detailed ones); with it the meshes come from the copy with the small palette (with_small_textures)."""
    config = tmp_path / "tether.toml"
    config.write_text("[sim.camera]\ndetailed_arm = true\n")
    detailed = load_config(SimConfig, config, "sim").camera
    assert detailed.detailed_arm and not CameraConfig().detailed_arm

    def drawn(camera: CameraConfig) -> set[Path]:
        """The directories of the meshes the robot is drawn with."""
        simulation = Simulation(WORLD, camera=camera, physics_hz=FAST_PHYSICS_HZ)
        try:
            shapes = simulation.scene.bullet.getVisualShapeData(simulation.robot.id)
            return {Path(shape[4].decode()).parent for shape in shapes if shape[4]}
        finally:
            simulation.close()

    hulls = Path(pybullet_data.getDataPath()) / "franka_panda" / "meshes" / "collision"
    assert drawn(CameraConfig()) == {hulls}
    copies = drawn(detailed)
    assert copies and all(directory.name.startswith("meshes") for directory in copies), copies
