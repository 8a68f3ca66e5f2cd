"""The simulated robot as one thing to step: the world, the controllers acting on it and the sensors reading it."""

from __future__ import annotations

from typing import TypeVar

from schemas.actions import GoalState
from schemas.world import World
from services.sim.config import CameraConfig, SimConfig
from services.sim.controllers import Controllers
from services.sim.faults import Faults
from services.sim.sensors import Sensors
from services.sim.world import Motion, RobotBody, SimWorld

F = TypeVar("F")
R = TypeVar("R")

# Sim seconds everything must stand still, with nothing commanded, before a resting sim stops
# stepping physics (see Simulation.step).
REST_AFTER = 0.5


class Simulation:
    """One world, its robot's controllers and sensors, stepped by whoever owns this object (one thread).

    Nothing here but the order of a step: `controllers` set the motors, then `scene` steps physics,
    then `faults` looks at what happened. Ask the parts for the rest: `controllers` for goals,
    cmd_vel and the speed scale, `sensors` for what the robot reports, `scene` for ground truth and
    moving things, `faults` for injected faults and incidents, `robot` for its joints.
    """

    def __init__(
        self,
        world: World,
        *,
        physics_hz: float = 240.0,
        solver_iterations: int = 50,
        camera: CameraConfig | None = None,
        visuals: bool = True,
        rest: bool = False,
    ) -> None:
        """`visuals=False` for a sim whose camera renders in a process of its own (services/sim/renderer.py):
        the robot's visual meshes are not loaded, and `sensors` cannot render. `rest=True` lets a world
        at rest go unstepped (see step); whoever changes the world other than through the controllers
        then calls `wake` first."""
        self.world = world
        camera = camera or CameraConfig()
        self.scene = SimWorld(
            world,
            physics_hz=physics_hz,
            solver_iterations=solver_iterations,
            visuals=visuals,
            detailed_arm=camera.detailed_arm,
        )
        self.robot: RobotBody = self.scene.robot
        self.controllers = Controllers(self.scene)
        self.sensors = Sensors(self.scene, camera)
        # Faults injected (sim/fault) and the incidents only the sim feels: collisions, drops.
        self.faults = Faults(self.scene)
        self.rest = rest
        self.resting = False  # physics not stepped: see step
        self._still_since: float | None = None

    @classmethod
    def served(cls, world: World, config: SimConfig) -> Simulation:
        """The simulation a service runs (the sim, the ROS 2 stand-in) as `[sim]` configures it: without
        visual meshes, its camera rendering in a process of its own; a world at rest left unstepped."""
        return cls(
            world,
            physics_hz=config.physics_hz,
            solver_iterations=config.solver_iterations,
            camera=config.camera,
            visuals=False,
            rest=True,
        )

    @property
    def sim_time(self) -> float:
        return self.scene.sim_time

    @property
    def dt(self) -> float:
        return self.scene.dt

    def step(self, steps: int = 1) -> None:
        """Advance physics by `steps` ticks, running every controller before each.

        With `rest`, a world that has stood still for REST_AFTER sim seconds with nothing commanded
        (no goal, no cmd_vel, nothing settling or falling) is not stepped: time passes and nothing
        moves, as Bullet lets a resting body sleep, here with the robot too. Left to itself, Bullet
        would spend the same step on it (an idle sim at 20x real time used about 45 % of a core) and
        let a base standing under its motors creep (about 2e-5 rad a second). The first tick that
        has a goal or a cmd_vel again, or any tick after `wake`, steps physics."""
        for _ in range(steps):
            if self.rest and self._at_rest():
                self.scene.rest_step()
                self.faults.rest_tick()
            else:
                self.controllers.tick()
                self.scene.step()
                self.faults.tick()

    def wake(self) -> None:
        """Step physics again until the world has stood still for REST_AFTER once more: the world
        was changed other than through a goal (an object or person moved, a fault injected)."""
        self.resting = False
        self._still_since = None

    def _at_rest(self) -> bool:
        if not (self.controllers.idle and self.faults.idle) or self.scene.settling:
            self.wake()
            return False
        if self.resting:
            return True
        if not self.scene.still():
            self._still_since = None
            return False
        if self._still_since is None:
            self._still_since = self.sim_time
        self.resting = self.sim_time - self._still_since >= REST_AFTER
        return self.resting

    def run(self, motion: Motion[F, R], timeout: float) -> Motion[F, R]:
        """Step until `motion` ends, or abort it after `timeout` sim seconds. For tests and scripts."""
        deadline = self.sim_time + timeout
        while motion.running and self.sim_time < deadline:
            self.step()
        if motion.running:
            self.controllers.cancel(motion, GoalState.ABORTED, f"{motion.kind} did not finish within {timeout:g} s")
        return motion

    def settle(self, seconds: float) -> None:
        self.step(max(1, round(seconds / self.dt)))

    def close(self) -> None:
        self.scene.close()
