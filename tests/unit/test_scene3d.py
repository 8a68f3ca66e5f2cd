"""Foxglove's messages made from tether's (services/recorder/scene3d.py), the recording's Foxglove channels,
and the live view's bounded buffers (tether/view.py). Pure logic; the view on a real stack is in
tests/integration/test_view.py."""

from __future__ import annotations

import io
import json
import logging
import math
from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader

from schemas import keys
from schemas.common import Pose2D, Vec3
from schemas.robot import Odometry
from schemas.safety import Decision, SafetyEvent
from schemas.world import PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.bundled import DEFAULT_POLICY, world_path
from services.recorder import scene3d
from services.recorder.mcapfile import Provenance, Recording, SourceFile
from services.runtime import encode
from tether.view import Latest, LogQueue, Throttle

ROBOT = "r1"


def scene(separation: scene3d.Separation | None = None) -> scene3d.Scene:
    path = world_path()
    world = scene3d.scene_from_files(path.read_bytes(), path, None, None).world
    return scene3d.Scene(world, [], separation or scene3d.Separation())


def test_people_are_ringed_at_the_policys_stop_and_slow_distances_from_their_body() -> None:
    seen = PerceivedHumans(stamp=10.5, humans=[PerceivedHuman(id="ann", name="Ann", pose=Pose2D(x=2.0, y=3.0))])
    update = scene(scene3d.Separation(person_radius=0.3, stop_distance=0.5, slow_distance=2.0)).people(seen)

    [entity] = update.entities
    radii = []
    for line in entity.lines:
        assert line.type == scene3d.LINE_LOOP
        radii.append(round(math.dist((line.points[0].x, line.points[0].y), (2.0, 3.0)), 6))
    assert radii == [0.8, 2.3]
    assert entity.cylinders[0].size.x == pytest.approx(0.6)
    # Whoever is no longer reported disappears: every update replaces the whole set.
    assert [d.type for d in update.deletions] == [scene3d.DELETE_ALL]
    assert entity.timestamp == scene3d.Time(sec=10, nsec=500_000_000)


def test_objects_take_their_shape_and_colour_from_the_world_file_and_fade_when_stale() -> None:
    cup = PerceivedObject(id="red_cup", name="red cup", cls="cup", color="red", position=Vec3(x=1, y=2, z=0.95))
    old = msgspec.structs.replace(cup, id="apple", name="apple", stale=True)
    update = scene().objects(PerceivedObjects(stamp=1.0, objects=[cup, old]))

    by_id = {e.id: e for e in update.entities}
    [cylinder] = by_id["object/red_cup"].cylinders
    assert (cylinder.size.x, cylinder.size.z) == (0.06, 0.1) and cylinder.color.r == 0.9
    [sphere] = by_id["object/apple"].spheres
    assert sphere.color.a < 1.0


def test_the_static_scene_holds_walls_furniture_keep_out_zones_and_the_robots_body() -> None:
    update = scene().static(100.0)

    ids = {e.id for e in update.entities}
    assert {"walls", "furniture/bed", "keep_out/stairs", "room/office", "place/charging_dock", "robot/base"} <= ids
    body = next(e for e in update.entities if e.id == "robot/base")
    assert body.frame_id == scene3d.BASE_FRAME and body.frame_locked


def test_odometry_becomes_the_map_to_base_frame() -> None:
    odom = Odometry(stamp=5.25, sim_time=1.0, pose=Pose2D(x=1.5, y=-2.0, yaw=math.pi / 2), linear_x=0.1, angular_z=0)
    frame = scene3d.base_transform(odom)

    assert (frame.parent_frame_id, frame.child_frame_id) == ("map", "base")
    assert (frame.translation.x, frame.translation.y, frame.translation.z) == (1.5, -2.0, 0.0)
    assert 2 * math.atan2(frame.rotation.z, frame.rotation.w) == pytest.approx(math.pi / 2)


def test_derived_messages_for_a_recording() -> None:
    derived = scene3d.Derived(ROBOT, scene())
    odom = Odometry(stamp=1.0, sim_time=1.0, pose=Pose2D(x=1, y=2), linear_x=0, angular_z=0)
    event = SafetyEvent(stamp=2.0, key="cmd/cmd_vel", decision=Decision.VETOED, reason="too fast", rule=None)

    [(topic, tf)] = derived.messages(keys.ODOM.key(ROBOT), encode(odom), 1.0)
    assert topic == scene3d.TF_TOPIC and isinstance(tf, scene3d.FrameTransforms)
    [(topic, line)] = derived.messages(keys.SAFETY_EVENTS.key(ROBOT), encode(event), 2.0)
    assert topic == scene3d.LOG_TOPIC and isinstance(line, scene3d.Log)
    assert line.level == scene3d.LOG_WARNING and "too fast" in line.message
    # Not decodable, or not a key it knows: nothing, and no exception.
    assert derived.messages(keys.ODOM.key(ROBOT), b'{"stamp": "soon"}', 3.0) == []
    assert derived.messages(keys.CMD_VEL.key(ROBOT), b"{}", 3.0) == []


@pytest.mark.parametrize("when", [-1e300, 1e300, -1.0, 5e9])
def test_a_stamp_foxglove_time_cannot_hold_becomes_the_nearest_it_can(when: float) -> None:
    """-1e300 raised OverflowError (the view ended, the recorder lost the frame with a traceback),
    1e300 made a time of 301 digits that no reader takes as Foxglove's uint32 seconds."""
    derived = scene3d.Derived(ROBOT, scene())
    odom = Odometry(stamp=when, sim_time=1.0, pose=Pose2D(x=1, y=2), linear_x=0, angular_z=0)
    [(_topic, tf)] = derived.messages(keys.ODOM.key(ROBOT), encode(odom), 1.0)
    assert isinstance(tf, scene3d.FrameTransforms)
    [frame] = tf.transforms
    nearest = (0, 0) if when < 0 else (scene3d.MAX_STAMP_SEC, 999_999_999)
    assert (frame.timestamp.sec, frame.timestamp.nsec) == nearest
    assert msgspec.json.decode(scene3d.encode(tf), type=scene3d.FrameTransforms) == tf


def test_schemas_are_named_for_foxglove_with_the_image_data_marked_base64() -> None:
    for type_, name in scene3d.SCHEMA_NAMES.items():
        document = json.loads(scene3d.schema_document(type_))
        assert document["title"] == name and document["type"] == "object"
    image = json.loads(scene3d.schema_document(scene3d.CompressedImage))
    assert image["properties"]["data"]["contentEncoding"] == "base64"


def test_a_policy_that_is_not_one_is_named() -> None:
    with pytest.raises(ValueError, match=r"policy file bad\.toml"):
        scene3d.policy_drawn(b"[humans]\nslow_distance = 'far'\n", Path("bad.toml"))
    separation, zones = scene3d.policy_drawn(DEFAULT_POLICY.read_bytes(), DEFAULT_POLICY)
    assert (separation.stop_distance, separation.slow_distance) == (0.2, 1.5) and zones == []


def test_a_recording_starts_with_the_scene_and_has_a_frame_for_each_odometry_message() -> None:
    stream = io.BytesIO()
    world, policy = world_path(), DEFAULT_POLICY
    provenance = Provenance(ROBOT, world=SourceFile.read(world), policy=SourceFile.read(policy))
    recording = Recording(stream, ROBOT, provenance=provenance)
    for i in range(3):
        odom = Odometry(stamp=float(i), sim_time=float(i), pose=Pose2D(x=float(i), y=0), linear_x=0, angular_z=0)
        assert recording.record(keys.ODOM.key(ROBOT), encode(odom))
    recording.finish()

    reader = make_reader(io.BytesIO(stream.getvalue()))
    topics = [(channel.topic, schema.name) for schema, channel, _ in reader.iter_messages()]
    assert topics[0] == (scene3d.SCENE_TOPIC, "foxglove.SceneUpdate")
    assert topics.count((scene3d.TF_TOPIC, "foxglove.FrameTransforms")) == 3
    # The traffic is counted as before; what was made for Foxglove apart.
    assert recording.messages == 3 and recording.derived == 4


def test_the_views_buffers_are_bounded_newest_wins_and_oldest_log_lines_go_first() -> None:
    latest = Latest()
    for i in range(1000):
        latest.put("odom", "k", b"%d" % i)
    assert latest.take() == {"odom": ("k", b"999")} and latest.replaced == 999
    assert latest.take() == {}

    logs = LogQueue(size=10)
    for i in range(25):
        logs.put("safety", "k", b"%d" % i)
    assert [p for _, _, p in logs.take()] == [b"%d" % i for i in range(15, 25)]
    assert logs.dropped == 15


def test_the_sdks_log_is_throttled_so_a_garbage_sending_viewer_cannot_fill_the_disk() -> None:
    now = [0.0]
    throttle = Throttle(burst=3, window=10.0, clock=lambda: now[0])

    def record(name: str) -> logging.LogRecord:
        return logging.LogRecord(name, logging.ERROR, __file__, 1, "bad frame", None, None)

    assert [throttle.filter(record("foxglove.websocket.server")) for _ in range(5)] == [True] * 3 + [False] * 2
    assert throttle.filter(record("tether.view"))  # ours are not throttled
    now[0] = 11.0
    line = record("foxglove.websocket.server")
    assert throttle.filter(line) and "2 more lines" in str(line.msg)
