"""What an identity (or none) tries against a robot it must not command: run on the operator host by the tests.

    python -m tests.multihost.intruder --config FILE --robot r1 [--token-file F] ATTEMPT...

ATTEMPTs: cmd_vel (puts robot/cmd_vel), navigate (asks robot/navigate_to_pose for a goal), reset
(asks safety/reset with the operator token), humans (puts a made-up person on world/humans),
alive (declares alive/safety and alive/sim, prints HOLDING on a line of its own, and holds them
until its stdin closes, HOLD_MAX at most: the test looks for them meanwhile), listen (subscribes to
tether/** for LISTEN_S). Prints one JSON object last: "opened" (false with "error" when the router
would not let the session in), and per attempt what came back. Puts and tokens have no answer here:
the tests check what the router passed on from their own session. Each put carries MARKER, so they
can tell it apart.
"""

from __future__ import annotations

import argparse
import json
import select
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import zenoh

from schemas import keys
from schemas.actions import SendGoal
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import ResetRequest
from schemas.world import PerceivedHuman, PerceivedHumans
from services.runtime import encode, zenoh_config_file

MARKER_SPEED = 0.4321  # m/s: no one else sends this
MARKER_NAME = "intruder"
QUERY_TIMEOUT = 2.0
# The heartbeat alone comes 50 times a second: a listener that may hear the robot hears it within this.
LISTEN_S = 1.0
# Puts of cmd_vel (each would move the robot were it let through) and the pause between them.
PUTS = 20
PUT_GAP = 0.01
HOLDING = "holding"
HOLD_MAX = 15.0


def answers(session: zenoh.Session, key: str, payload: bytes) -> dict[str, Any]:
    ok, errors = 0, []
    for reply in session.get(key, payload=payload, timeout=QUERY_TIMEOUT):
        if reply.ok is not None:
            ok += 1
        elif reply.err is not None:
            errors.append(reply.err.payload.to_bytes()[:300].decode(errors="replace"))
    return {"replies": ok, "errors": errors}


def attempt(session: zenoh.Session, robot: str, what: str, token_file: Path | None) -> dict[str, Any]:
    if what == "cmd_vel":
        for _ in range(PUTS):
            session.put(keys.ROBOT_CMD_VEL.key(robot), encode(Twist(linear_x=MARKER_SPEED, stamp=time.time())))
            time.sleep(PUT_GAP)
        return {"sent": PUTS}
    if what == "navigate":
        goal = SendGoal(goal_id=uuid.uuid4().hex, goal=NavigateToPoseGoal(pose=Pose2D(x=2.0, y=2.0, yaw=0.0)))
        return answers(session, f"tether/{robot}/robot/navigate_to_pose/_action/send_goal", encode(goal))
    if what == "reset":
        token = token_file.read_text().strip() if token_file else "guess"
        return answers(session, keys.RESET.key(robot), encode(ResetRequest(operator=MARKER_NAME, token=token)))
    if what == "humans":
        person = PerceivedHuman(id=MARKER_NAME, name=MARKER_NAME, pose=Pose2D(x=6.5, y=1.2, yaw=0.0))
        for _ in range(5):
            session.put(keys.HUMANS.key(robot), encode(PerceivedHumans(stamp=time.time(), humans=[person])))
            time.sleep(0.05)
        return {"sent": 5}
    if what == "alive":
        tokens = [session.liveliness().declare_token(keys.alive_key(robot, name)) for name in ("safety", "sim")]
        print(HOLDING, flush=True)
        select.select([sys.stdin], [], [], HOLD_MAX)  # held while the test looks for them
        for held in tokens:
            held.undeclare()
        return {"declared": 2}
    if what == "listen":
        heard: list[str] = []
        sub = session.declare_subscriber(f"tether/{robot}/**", lambda s: heard.append(str(s.key_expr)))
        time.sleep(LISTEN_S)
        sub.undeclare()
        return {"heard": len(heard), "keys": sorted(set(heard))[:10]}
    raise SystemExit(f"unknown attempt {what!r}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="intruder", description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--config", type=Path, required=True, help="a Zenoh client config")
    parser.add_argument("--robot", required=True)
    parser.add_argument("--token-file", type=Path)
    parser.add_argument("attempts", nargs="+")
    args = parser.parse_args(argv)
    out: dict[str, Any] = {"opened": False}
    try:
        session = zenoh.open(zenoh_config_file(args.config))
    except zenoh.ZError as exc:
        out["error"] = str(exc)
    else:
        out["opened"] = True
        with session:
            for what in args.attempts:
                out[what] = attempt(session, args.robot, what, args.token_file)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
