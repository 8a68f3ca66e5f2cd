"""The robot's sensors in the sim: odometry, joint encoders, the depth camera and detector, a people tracker."""

from __future__ import annotations

import numpy as np

from schemas.common import Vec3
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, JointState, Odometry
from schemas.world import PerceivedHuman, PerceivedHumans, PerceivedObjects, WorldObject
from services.sim.camera import Camera
from services.sim.config import CameraConfig
from services.sim.detection import Target
from services.sim.world import SimWorld, has_heading


def _target(obj: WorldObject) -> Target:
    """What the camera looks for: the object's height, and for a box with unequal sides, its sides."""
    footprint = (obj.size.x, obj.size.y) if has_heading(obj) else None
    return Target(obj.id, obj.size.z, footprint)


class Sensors:
    """What the robot reports about itself and what it perceives, read from the world on the sim thread."""

    def __init__(self, world: SimWorld, camera: CameraConfig | None = None) -> None:
        self.world = world
        # Only a world that can be drawn has its floor hidden from detection frames (Camera): the sim's
        # own world, physics only (visuals=False), is left exactly as loaded.
        self.camera = Camera(
            world.bullet, camera or CameraConfig(), floor=world.floor if world.visuals else None, robot=world.robot.id
        )
        self._camera_targets = {world.object_bodies[o.id]: _target(o) for o in world.spec.objects}

    def _can_render(self) -> None:
        if not self.world.visuals:
            raise RuntimeError("this sim was built without visuals: its camera renders in services/sim/renderer.py")

    def joint_state(self, stamp: float) -> JointState:
        position, velocity = self.world.robot.joints()
        return JointState(stamp=stamp, name=[*ARM_JOINTS, *FINGER_JOINTS], position=position, velocity=velocity)

    def odometry(self, stamp: float) -> Odometry:
        robot = self.world.robot
        linear, angular = robot.base_velocity()
        return Odometry(
            stamp=stamp, sim_time=self.world.sim_time, pose=robot.base_pose(), linear_x=linear, angular_z=angular
        )

    def perceived_objects(self, stamp: float) -> PerceivedObjects:
        """What the camera sees from where the base stands, and what the gripper holds: the robot
        knows what it grasped without looking, so that one is exact and `on` the gripper."""
        self._can_render()
        world = self.world
        targets = {body: t for body, t in self._camera_targets.items() if t.name != world.holding}
        seen = self.camera.look(world.robot.base_pose(), targets)
        objects = []
        for obj in world.spec.objects:
            if obj.id == world.holding:
                objects.append(world.exact(obj, stamp))
            elif obj.id in seen:
                x, y, z = (float(v) for v in seen[obj.id].centre)
                position = Vec3(x=x, y=y, z=z)
                on = world.model.support_under(position, obj.size.z / 2)
                objects.append(world.report(obj, position, on, stamp, seen[obj.id].yaw))
        return PerceivedObjects(stamp=stamp, objects=objects)

    def camera_picture(self, scale: int = 2) -> np.ndarray:
        """What the robot's camera sees now, in colour, `scale` times the detector's resolution (see Camera.picture)."""
        self._can_render()
        return self.camera.picture(self.world.robot.base_pose(), scale)

    def perceived_humans(self, stamp: float) -> PerceivedHumans:
        """Every person where they stand: a people tracker, not the camera."""
        world = self.world
        humans = []
        for human in world.spec.humans:
            pose = world.human_poses[human.id]
            room = world.model.room_of(pose.x, pose.y)
            humans.append(PerceivedHuman(id=human.id, name=human.name, pose=pose, room=room))
        return PerceivedHumans(stamp=stamp, humans=humans)
