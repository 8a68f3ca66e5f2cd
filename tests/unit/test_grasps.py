"""Grasps and place poses from shape and size, and pick and place of every graspable object of the
default world on every surface, planned with real pinocchio, coal and OMPL."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.common import Vec3
from schemas.robot import GRIPPER_MAX_GAP
from schemas.world import WorldObject
from services.executor.armplanning import ArmPlanner, HeldObject, SceneObject, plan_pick, plan_place
from services.executor.errors import PlanningFailed
from services.executor.grasps import (
    FINGERTIP_BEYOND,
    WRIST_HALF_THICKNESS,
    Grasp,
    GraspConfig,
    fits,
    grasps,
    object_pose,
    placements,
)
from services.resolver.placement import place_position
from services.worldmodel import WorldModel, load_world

WORLD = WorldModel(load_world())
ROBOT = WORLD.world.robot
MOUNT = ROBOT.arm_mount
CONFIG = GraspConfig()
# The resolver's defaults for where on a top things are put down.
PLACE_INSET = PLACE_CLEARANCE = 0.15
GRASPABLE = [o.id for o in WORLD.world.objects if o.mass <= ROBOT.payload and fits(min(o.size.x, o.size.y), CONFIG)]


@pytest.fixture(scope="module")
def planner() -> ArmPlanner:
    return ArmPlanner(WORLD)


def on_support(obj: WorldObject) -> tuple[Vec3, list[Grasp]]:
    position = WORLD.initial_position(obj)
    support = WORLD.furniture[obj.support]
    return position, grasps(obj, position, 0.0, support.approach, MOUNT)


def up(height: float) -> np.ndarray:
    return np.array([0.0, 0.0, height])


def heading(vector: np.ndarray) -> float:
    return math.atan2(float(vector[1]), float(vector[0]))


def test_the_default_world_has_cups_a_sphere_and_a_box_to_grasp() -> None:
    assert GRASPABLE == ["red_cup", "coffee_mug", "blue_cup", "apple", "blue_book"]


def test_a_top_grasp_closes_at_most_grasp_depth_below_a_tall_objects_top() -> None:
    cup = WORLD.objects["red_cup"]
    position, candidates = on_support(cup)
    top = [g for g in candidates if g.kind == "top"]
    assert len(top) == 2 * CONFIG.round_headings  # each heading from above, and from above nearer the robot
    grasp = top[0]
    centre = object_pose(position, 0.0, WORLD.furniture[cup.support].approach, MOUNT).translation
    assert grasp.pose.translation == pytest.approx(centre + up(cup.size.z / 2 - CONFIG.grasp_depth))
    assert grasp.pose.rotation[:, 2] == pytest.approx([0.0, 0.0, -1.0])  # pointing down
    # The comfortable hand first: its x along the reach from panda_link0, as in the stowed pose.
    assert abs(math.remainder(heading(grasp.pose.rotation[:, 0]) - heading(centre), math.tau)) < 1e-9
    assert grasp.pregrasp.translation == pytest.approx(grasp.pose.translation + up(CONFIG.pregrasp_distance))
    assert grasp.lift.translation == pytest.approx(grasp.pose.translation + up(CONFIG.lift_height))
    assert grasp.gap == pytest.approx(cup.size.x)
    # The cup hangs 2 cm below the grasp frame, which points down: +z in its frame.
    assert grasp.object_in_grasp.translation == pytest.approx([0.0, 0.0, cup.size.z / 2 - CONFIG.grasp_depth])


def test_a_flat_box_is_gripped_across_the_side_that_fits_both_ways_round() -> None:
    book = WORLD.objects["blue_book"]  # 6 x 20 x 3 cm
    table = WORLD.furniture[book.support]
    position = WORLD.initial_position(book)
    candidates = grasps(book, position, 0.3, table.approach, MOUNT)
    assert {g.kind for g in candidates} == {"top"}  # 3 cm: too low for the wrist beside it
    assert len(candidates) == 4
    box_x = object_pose(position, 0.3, table.approach, MOUNT).rotation[:, 0]
    for grasp in candidates:
        assert abs(float(grasp.pose.rotation[:, 1] @ box_x)) == pytest.approx(1.0)  # fingers along its 6 cm side
        assert grasp.gap == pytest.approx(book.size.x)
        # Fingertips clear of the table under it.
        fingertips = grasp.pose.translation[2] - FINGERTIP_BEYOND + MOUNT.z
        assert fingertips >= table.size.z + CONFIG.fingertip_clearance - 1e-9
    headings = sorted({round(heading(g.pose.rotation[:, 0]), 6) for g in candidates})
    assert len(headings) == 2 and abs(math.remainder(headings[1] - headings[0], math.tau)) == pytest.approx(math.pi)


def test_a_sphere_is_gripped_across_its_chord_from_above_or_at_an_angle() -> None:
    apple = WORLD.objects["apple"]
    _, candidates = on_support(apple)
    assert [g.kind for g in candidates] == ["top"] * 2 * CONFIG.round_headings + ["angled"] * 2
    assert all(g.gap < apple.size.x for g in candidates if g.kind == "top")


def test_an_angled_grasp_reaches_an_apple_at_the_back_of_the_shelf(planner: ArmPlanner) -> None:
    apple = WORLD.objects["apple"]
    shelf = WORLD.furniture["shelf"]
    far = Vec3(x=5.82, y=8.71, z=shelf.size.z + apple.size.z / 2)  # 0.66 m from panda_link0, 0.54 m above it
    scene = planner.scene(shelf.approach, [SceneObject(apple, far)])
    candidates = grasps(apple, far, 0.0, shelf.approach, MOUNT)
    with pytest.raises(PlanningFailed, match="no grasp of apple works"):
        plan_pick(scene, planner.home, [g for g in candidates if g.kind == "top"], apple, shelf.id)
    pick = plan_pick(scene, planner.home, candidates, apple, shelf.id, q_stow=planner.home)
    assert pick.grasp.kind == "angled"
    tilt = math.acos(-float(pick.grasp.pose.rotation[2, 2]))
    assert tilt == pytest.approx(CONFIG.tilts[0])
    # Held at an angle, it is put down upright elsewhere on the shelf.
    held = HeldObject(apple, pick.grasp.object_in_grasp)
    spot = Vec3(x=6.2, y=8.6, z=shelf.size.z)
    options = placements(apple, pick.grasp.object_in_grasp, spot, shelf.approach, MOUNT)
    place = plan_place(planner.scene(shelf.approach, [], held), planner.home, options, shelf.id)
    placed = place.placement.pose * pick.grasp.object_in_grasp
    assert placed.translation[2] + MOUNT.z - apple.size.z / 2 == pytest.approx(shelf.size.z + CONFIG.place_clearance)


def test_what_the_fingers_cannot_span_has_no_grasp(planner: ArmPlanner) -> None:
    pan = WORLD.objects["cast_iron_pan"]
    assert pan.size.x > GRIPPER_MAX_GAP
    _, candidates = on_support(pan)
    assert candidates == []
    scene = planner.scene(WORLD.furniture[pan.support].approach)
    with pytest.raises(PlanningFailed, match="nothing about it fits between the fingers"):
        plan_pick(scene, planner.home, candidates, pan, pan.support)


def test_side_grasps_hold_the_hand_level_from_the_robots_side_with_the_wrist_clear() -> None:
    cup = WORLD.objects["red_cup"]
    position, candidates = on_support(cup)
    support = WORLD.furniture[cup.support]
    centre = object_pose(position, 0.0, support.approach, MOUNT).translation
    side = [g for g in candidates if g.kind == "side"]
    assert side
    for grasp in side:
        approach, fingers = grasp.pose.rotation[:, 2], grasp.pose.rotation[:, 1]
        assert approach[2] == pytest.approx(0.0) and fingers[2] == pytest.approx(0.0)
        assert float(approach[:2] @ centre[:2]) > 0  # away from panda_link0: from the robot's side
        height = grasp.pose.translation[2] + MOUNT.z - support.size.z
        assert height >= WRIST_HALF_THICKNESS + CONFIG.hand_clearance - 1e-9
        assert grasp.lift.translation == pytest.approx(grasp.pose.translation + up(CONFIG.lift_height))
    first = side[0]
    assert first.pregrasp.translation == pytest.approx(
        first.pose.translation - first.pose.rotation[:, 2] * CONFIG.pregrasp_distance
    )
    assert abs(math.remainder(heading(first.pose.rotation[:, 2]) - heading(centre), math.tau)) < 1e-9


@pytest.mark.parametrize("kind", ["top", "side"])
def test_placements_stand_the_object_upright_just_above_the_surface(kind: str) -> None:
    cup = WORLD.objects["red_cup"]
    _, candidates = on_support(cup)
    grasp = next(g for g in candidates if g.kind == kind)
    table = WORLD.furniture["coffee_table"]
    spot = Vec3(x=8.0, y=2.35, z=table.size.z)
    options = placements(cup, grasp.object_in_grasp, spot, table.approach, MOUNT)
    assert len(options) == 2 * CONFIG.place_headings
    for placement in options:
        placed = placement.pose * grasp.object_in_grasp
        assert placed.rotation[:, 2] == pytest.approx([0.0, 0.0, 1.0])  # upright
        assert np.allclose(placed.homogeneous, placement.object_pose.homogeneous)
        bottom = placed.translation[2] + MOUNT.z - cup.size.z / 2
        assert bottom == pytest.approx(table.size.z + CONFIG.place_clearance)
        assert placement.preplace.translation[2] > placement.pose.translation[2]
        back = placement.retreat.translation - placement.pose.translation
        assert np.linalg.norm(back) == pytest.approx(CONFIG.retreat_distance)
        assert float(back @ placement.pose.rotation[:, 2]) < 0  # backs off against the approach
    # The first keeps the hand as it is comfortable: pointing down along the reach, or level and away.
    first = options[0].pose
    reach = heading(first.translation)
    reference = first.rotation[:, 0] if kind == "top" else first.rotation[:, 2]
    assert abs(math.remainder(heading(reference) - reach, math.tau)) < 1e-6


@pytest.mark.parametrize("object_id", GRASPABLE)
def test_every_graspable_object_is_picked_from_its_support_with_each_kind_of_grasp(
    planner: ArmPlanner, object_id: str
) -> None:
    obj = WORLD.objects[object_id]
    support = WORLD.furniture[obj.support]
    scene = planner.scene(support.approach, [SceneObject(o, WORLD.initial_position(o)) for o in WORLD.world.objects])
    _, candidates = on_support(obj)
    kinds = {"box": {"top"}, "sphere": {"top", "angled"}, "cylinder": {"top", "side", "angled"}}[obj.shape]
    assert {g.kind for g in candidates} == kinds
    for kind in sorted(kinds):
        pick = plan_pick(
            scene, planner.home, [g for g in candidates if g.kind == kind], obj, obj.support, q_stow=planner.home
        )
        assert pick.grasp.kind == kind
        assert scene.path_free(pick.to_pregrasp)


@pytest.mark.parametrize("object_id", GRASPABLE)
def test_every_object_is_placed_on_and_picked_again_from_every_surface(planner: ArmPlanner, object_id: str) -> None:
    """Held as picked from its support (top grasp, and side grasp for what allows one), put down at
    the resolver's spot on each piece of furniture from its approach pose, then picked from there
    with a top grasp and a side grasp (what allows one)."""
    obj = WORLD.objects[object_id]
    home = planner.home
    others = [SceneObject(o, WORLD.initial_position(o)) for o in WORLD.world.objects if o.id != obj.id]
    support = WORLD.furniture[obj.support]
    start = planner.scene(support.approach, [*others, SceneObject(obj, WORLD.initial_position(obj))])
    _, candidates = on_support(obj)
    kinds = sorted({g.kind for g in candidates} & {"top", "side"})
    for kind in kinds:
        held = plan_pick(start, home, [g for g in candidates if g.kind == kind], obj, obj.support).grasp
        for surface in WORLD.world.furniture:
            occupied = [(p.position.x, p.position.y) for p in others if WORLD.objects[p.obj.id].support == surface.id]
            spot = place_position(surface, occupied, inset=PLACE_INSET, clearance=PLACE_CLEARANCE)
            assert spot is not None
            scene = planner.scene(surface.approach, others, HeldObject(obj, held.object_in_grasp))
            options = placements(obj, held.object_in_grasp, spot, surface.approach, MOUNT)
            place = plan_place(scene, home, options, surface.id, q_stow=home)
            placed = scene.to_arm.inverse() * place.placement.object_pose
            assert placed.translation[:2] == pytest.approx([spot.x, spot.y])
            # Settled on the top, where perception would then see it.
            position = Vec3(x=spot.x, y=spot.y, z=surface.size.z + obj.size.z / 2)
            yaw = heading(placed.rotation[:, 0])
            there = planner.scene(surface.approach, [*others, SceneObject(obj, position, yaw)])
            again = grasps(obj, position, yaw, surface.approach, MOUNT)
            for kind_again in kinds:
                try:
                    plan_pick(there, home, [g for g in again if g.kind == kind_again], obj, surface.id)
                except PlanningFailed as exc:
                    pytest.fail(f"held by a {kind} grasp, put on {surface.id}, no {kind_again} grasp: {exc}")


def test_candidates_do_not_change_between_calls() -> None:
    cup = WORLD.objects["coffee_mug"]
    _, first = on_support(cup)
    _, second = on_support(cup)
    assert [g.description for g in first] == [g.description for g in second]
    assert all(np.array_equal(a.pose.homogeneous, b.pose.homogeneous) for a, b in zip(first, second, strict=True))
