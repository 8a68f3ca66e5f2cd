"""Arm motion planning for picks: random reachable pick poses in the default world, planned in-process.

    python -m bench.motion --json        one JSON object on stdout, progress on stderr
    python -m bench.motion               a short table

Each trial puts one graspable object (its mass within the payload, something about it fitting
between the fingers) at a random heading and a random spot on a random piece of furniture: on the
top with its footprint inside, within the robot's reach (world file `robot.reach`) of the base at
that furniture's approach pose, and clear of the other objects, which stay where the world file
puts them. It then times the whole planning of the pick from the stowed arm: the planning scene,
grasp candidates, collision-free IK of the pre-grasp, the straight approach, the straight lift
with the object held, the paths from the stowed pose to the pre-grasp and back to it holding the
object (straight when free, else RRTConnect), and the time parameterisation of the four motions,
all with the executor's default configuration. A trial succeeds when a plan is found.

Baselines measured on the same trials: `ik_*` is the damped least-squares IK alone for the first
candidate's pre-grasp (no collision checks, from the stowed pose); `direct_*` is collision-checking
the straight joint-space line from the stowed pose to the pre-grasp configuration that was found.
Medians and p99 in milliseconds; `rrt_fraction` is the share of successful trials that needed
RRTConnect. The random spots, and OMPL, are seeded: a run is reproducible up to timing.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import time
from collections import Counter
from typing import Any

import numpy as np

from bench.service import bench_main, bounded, ms_summary, notes, print_rows, reporter, show
from schemas.common import Vec3
from schemas.world import Furniture, WorldObject
from services.executor.armplanning import ArmPlanner, ArmPlannerConfig, SceneObject, plan_pick, time_parameterize
from services.executor.config import ExecutorConfig
from services.executor.errors import PlanningFailed
from services.executor.grasps import GraspConfig, fits, grasps
from services.executor.manipulation import grasp_config
from services.robotmodel import map_to_base
from services.worldmodel import WorldModel, load_world

PROG = "bench.motion"
# What the executor plans with, by default.
CONFIG = ExecutorConfig()
# Spots keep the object's footprint this far inside the top's edges and from other objects.
EDGE_MARGIN = 0.02
OBJECT_GAP = 0.05
SPOT_ATTEMPTS = 1000
FAILURES_SHOWN = 10

progress = reporter(PROG)


def graspable(world: WorldModel) -> list[WorldObject]:
    payload = world.world.robot.payload
    return [o for o in world.world.objects if o.mass <= payload and fits(min(o.size.x, o.size.y), GraspConfig())]


def footprint_radius(obj: WorldObject) -> float:
    return math.hypot(obj.size.x, obj.size.y) / 2 if obj.shape == "box" else obj.size.x / 2


def random_pose(
    rng: np.random.Generator, world: WorldModel, surface: Furniture, obj: WorldObject
) -> tuple[Vec3, float] | None:
    """A spot on `surface` for `obj` within reach of its approach pose, clear of the other objects."""
    robot = world.world.robot
    radius = footprint_radius(obj)
    others = [
        (world.initial_position(o), footprint_radius(o))
        for o in world.world.objects
        if o.support == surface.id and o.id != obj.id
    ]
    cx, cy = surface.center
    half_x, half_y = surface.size.x / 2 - radius - EDGE_MARGIN, surface.size.y / 2 - radius - EDGE_MARGIN
    for _ in range(SPOT_ATTEMPTS):
        x, y = cx + rng.uniform(-half_x, half_x), cy + rng.uniform(-half_y, half_y)
        ahead, _ = map_to_base(surface.approach, x, y)
        if math.hypot(*map_to_base(surface.approach, x, y)) > robot.reach or ahead <= 0:
            continue
        if any(math.hypot(x - p.x, y - p.y) < radius + r + OBJECT_GAP for p, r in others):
            continue
        return Vec3(x=x, y=y, z=surface.size.z + obj.size.z / 2), float(rng.uniform(-math.pi, math.pi))
    return None


def run(trials: int, seed: int) -> dict[str, Any]:
    world = WorldModel(load_world())
    started = time.perf_counter()
    planner = ArmPlanner(world, ArmPlannerConfig(planning_time=CONFIG.planning_time, seed=seed))
    build_ms = (time.perf_counter() - started) * 1000
    progress(f"collision model built in {build_ms:.0f} ms; {trials} trials, seed {seed}")
    rng = np.random.default_rng(seed)
    objects = graspable(world)
    surfaces = list(world.world.furniture)
    mount = world.world.robot.arm_mount
    home = planner.home
    plan_ms: list[float] = []
    ik_ms: list[float] = []
    direct_ms: list[float] = []
    kinds: Counter[str] = Counter()
    rrt = 0
    failures: list[str] = []
    errors: list[str] = []
    for trial in range(trials):
        obj = objects[int(rng.integers(len(objects)))]
        surface = surfaces[int(rng.integers(len(surfaces)))]
        spot = random_pose(rng, world, surface, obj)
        if spot is None:
            errors.append(f"trial {trial}: no free spot for {obj.id} on {surface.id}")
            continue
        position, yaw = spot
        base = surface.approach
        others = [SceneObject(o, world.initial_position(o)) for o in world.world.objects if o.id != obj.id] + [
            SceneObject(obj, position, yaw)
        ]
        started = time.perf_counter()
        candidates: list = []
        try:
            scene = planner.scene(base, others)
            candidates = grasps(obj, position, yaw, base, mount, grasp_config(CONFIG))
            pick = plan_pick(scene, home, candidates, obj, surface.id, q_stow=home)
            for path in (pick.to_pregrasp, pick.approach, pick.lift, pick.to_stow or []):
                time_parameterize(path, CONFIG.max_joint_speed, CONFIG.max_joint_acceleration)
        except PlanningFailed as exc:
            plan_ms.append((time.perf_counter() - started) * 1000)
            failures.append(f"{obj.id} on {surface.id} at ({position.x:.2f}, {position.y:.2f}): {str(exc)[:300]}")
            progress(f"trial {trial}: failed: {failures[-1][:200]}")
            continue
        plan_ms.append((time.perf_counter() - started) * 1000)
        kinds[pick.grasp.kind] += 1
        rrt += len(pick.to_pregrasp) > 2
        # Baselines on the same trial.
        if candidates:
            started = time.perf_counter()
            with contextlib.suppress(PlanningFailed):
                planner.kin.solve(candidates[0].pregrasp, home, margin=planner.config.limit_margin)
            ik_ms.append((time.perf_counter() - started) * 1000)
        q_pre = pick.to_pregrasp[-1]
        started = time.perf_counter()
        scene.path_free([home, q_pre])
        direct_ms.append((time.perf_counter() - started) * 1000)
        if (trial + 1) % 20 == 0:
            progress(f"{trial + 1}/{trials} trials, {len(failures)} failed")
    successes = len(plan_ms) - len(failures)
    p50, p99 = ms_summary(plan_ms) if plan_ms else (None, None)
    i50, i99 = ms_summary(ik_ms) if ik_ms else (None, None)
    d50, d99 = ms_summary(direct_ms) if direct_ms else (None, None)
    return {
        "trials": len(plan_ms),
        "success_rate": round(successes / len(plan_ms), 4) if plan_ms else None,
        "plan_p50_ms": p50,
        "plan_p99_ms": p99,
        "ik_p50_ms": i50,
        "ik_p99_ms": i99,
        "direct_p50_ms": d50,
        "direct_p99_ms": d99,
        "rrt_fraction": round(rrt / successes, 4) if successes else None,
        "grasps": dict(sorted(kinds.items())),
        "build_ms": round(build_ms, 1),
        "seed": seed,
        "failures": failures[:FAILURES_SHOWN],
        "errors": errors,
        "notes": notes(
            plan="scene, grasp candidates, collision-free IK, straight approach and lift, paths from the stowed "
            "pose to the pre-grasp and back holding the object, time parameterisation of the four motions",
            ik="damped least-squares IK of the first candidate's pre-grasp alone, no collision checks",
            direct="collision checks along the straight joint-space line stowed pose -> pre-grasp, "
            f"{planner.config.resolution:g} rad apart",
            limits=f"{CONFIG.max_joint_speed:g} rad/s, {CONFIG.max_joint_acceleration:g} rad/s^2",
            build="the robot's collision model, once, before the trials",
        ),
    }


def print_table(result: dict[str, Any]) -> None:
    rows = [
        ("trials", show(result["trials"]), ""),
        ("success rate", show(result["success_rate"]), ">= 0.95"),
        ("plan p50 / p99 ms", f"{show(result['plan_p50_ms'])} / {show(result['plan_p99_ms'])}", "p50 <= 100"),
        ("IK alone p50 / p99 ms", f"{show(result['ik_p50_ms'])} / {show(result['ik_p99_ms'])}", "baseline"),
        ("direct line p50 / p99 ms", f"{show(result['direct_p50_ms'])} / {show(result['direct_p99_ms'])}", "baseline"),
        ("RRTConnect needed", show(result["rrt_fraction"]), ""),
        ("grasps used", str(result["grasps"]), ""),
    ]
    print_rows(f"motion ({result['trials']} random picks, seed {result['seed']})", rows, result["errors"])
    for failure in result["failures"]:
        print(f"failed: {failure}")


def main(argv: list[str] | None = None) -> None:
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--trials", type=bounded(int, 1, 100_000), default=100, help="random pick poses")
        parser.add_argument("--seed", type=bounded(int, 1, 2**31 - 1), default=1, help="spots, headings and OMPL")

    bench_main(PROG, __doc__ or "", add_arguments, lambda args: run(args.trials, args.seed), print_table, argv)


if __name__ == "__main__":
    main()
