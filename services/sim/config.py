"""The simulator's frozen config: which world, how fast, how often it reports, and its camera."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

Hz = Annotated[float, Meta(gt=0.0, le=1000.0)]
WallSeconds = Annotated[float, Meta(gt=0.0, le=60.0)]
# How long a cmd_vel holds: at most the policy's default cmd_vel_horizon (1 s), the time safety checks
# its path for, as [ros2] cmd_vel_timeout.
CmdVelSeconds = Annotated[float, Meta(gt=0.0, le=1.0)]
Pixels = Annotated[int, Meta(ge=16, le=1920)]


class CameraConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[sim.camera]`: the depth camera on the robot and the detector reading its images.

    Objects are reported where the camera sees them (segmentation and depth rendered by pybullet),
    never from the simulator's own state. The defaults see each furniture top from its approach
    pose with the arm stowed, and the coffee table from the start pose.
    """

    # On a mast at the front edge of the base (base frame, metres): ahead of the stowed arm, so the
    # arm never blocks the view, and high enough to look down onto the kitchen counter.
    mount_x: Annotated[float, Meta(ge=-1.0, le=1.0)] = 0.3
    mount_z: Annotated[float, Meta(ge=0.1, le=2.5)] = 1.35
    pitch_deg: Annotated[float, Meta(ge=0.0, le=90.0)] = 45.0  # down from horizontal
    # A RealSense D435's depth field of view is 87 degrees across. The CPU renderer pays per
    # triangle and per pixel drawn: about 3 ms a frame at 160 x 120 with the arm's hulls; 4:3 gives
    # 70 degrees vertically, enough to see both the near edge of a table and the room ahead.
    # It renders in a process of its own (services/sim/renderer.py), never on the sim thread.
    width: Pixels = 160
    height: Pixels = 120
    hfov_deg: Annotated[float, Meta(ge=20.0, le=150.0)] = 87.0
    near: Annotated[float, Meta(ge=0.01, le=0.4)] = 0.1  # metres; nearer is not drawn
    # Metres; depth beyond this is no reading, as with a real depth sensor.
    max_range: Annotated[float, Meta(ge=0.5, le=20.0)] = 4.0
    # A body needs this many pixels in range to count as seen.
    min_pixels: Annotated[int, Meta(ge=1, le=10000)] = 10
    # Gaussian noise (standard deviation, metres, per axis) on every reported position; 0 for none.
    # Seeded, so a run can be repeated exactly.
    noise: Annotated[float, Meta(ge=0.0, le=0.1)] = 0.003
    seed: Annotated[int, Meta(ge=0)] = 0
    # The arm drawn with the Panda's detailed meshes (about 20 ms more a frame, 40 MB more in the
    # renderer) instead of its collision hulls, which hide a little more from the camera: for pictures.
    detailed_arm: bool = False


class SimConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[sim]` in the config file. Timeouts are wall-clock seconds (cmd_vel's as below); rates are per wall second."""

    world: Annotated[str, Meta(min_length=1, max_length=1000)] = "household"
    # Sim seconds per wall second; tests run the sim a few times faster than real time.
    realtime_factor: Annotated[float, Meta(ge=0.1, le=20.0)] = 1.0
    physics_hz: Annotated[float, Meta(ge=60.0, le=2000.0)] = 240.0
    # The most passes Bullet's constraint solver makes over the joints' motors and the contacts each
    # step (pybullet's default, 50); it stops sooner once they agree. Fewer cost less CPU and hold the
    # motors and contacts a little less stiffly (tests/fastsim.py: why the tests keep 50).
    solver_iterations: Annotated[int, Meta(ge=5, le=500)] = 50
    heartbeat_timeout: WallSeconds = 0.2
    # A heartbeat counts for heartbeat_timeout from its arrival, but never once its stamp (safety's
    # wall clock) is older than this by the sim's: one held back by a stalled link is no sign of life.
    # It covers the heartbeat's transit and how far the robot's clock may be ahead of safety's (not
    # at all when they run on one host); a robot whose clock is this much ahead never moves, and says
    # why. services/robotrules.py, HeartbeatGuard; docs/robot.md.
    heartbeat_max_age: WallSeconds = 0.5
    # A goal that arrives before safety's first heartbeat (right after start-up, while the peers are
    # still connecting) waits this long for it before it is refused.
    first_heartbeat_wait: WallSeconds = 3.0
    # Held for this times realtime_factor sim seconds: wall time while the sim keeps pace (docs/robot.md).
    # At most the policy's cmd_vel_horizon, the time safety checks a cmd_vel's path for (it took 60 s).
    cmd_vel_timeout: CmdVelSeconds = 0.5
    joint_states_hz: Hz = 50.0
    odom_hz: Hz = 50.0
    # Each report of objects renders a camera frame (about 3 ms of CPU, in the renderer process,
    # services/sim/renderer.py); a frame not drawn before the next is due is dropped, not queued.
    objects_hz: Hz = 5.0
    humans_hz: Hz = 5.0
    camera: CameraConfig = CameraConfig()
    # The key safety signs robot commands and heartbeats with (services/robotlink.py); None:
    # $TETHER_ROBOT_KEY_FILE, else robot-<robot>.key beside the operator token. Made if missing.
    robot_key_file: Annotated[str, Meta(min_length=1, max_length=4096)] | None = None
