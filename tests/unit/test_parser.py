"""The parser: the plan shapes LLMs emit become Plans; everything else is refused with a reason."""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgspec
import pytest

from schemas.common import ErrorKind, ServiceError, Stage
from schemas.plan import MAX_PLAN_BYTES, MAX_STEPS, Action, Coordinates, Plan, PlanText
from services.parser.config import ParserConfig
from services.parser.errors import ParseError, VocabularyError
from services.parser.parser import Parser, answer, default_parser, parse
from services.parser.vocabulary import load_vocabulary

DEMO = {
    "plan": [
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "coffee table"},
        {"action": "place", "target": "coffee table"},
    ]
}

# The shape of seed 001: an object holding a "plan" array of {action, target, parameters}.
OBJECT_SHAPE = {
    "description": "Bring the mug to the living room",
    "plan": [
        {"action": "navigate_to", "target": "kitchen", "parameters": {"x": 3.0, "y": 2.5}, "description": "go"},
        {"action": "detect_object", "target": "coffee mug", "parameters": {}},
        {"action": "grasp_object", "target": "coffee mug", "parameters": {"approach": "top"}},
        {"action": "place_object", "target": "coffee table", "parameters": {}},
        {"action": "speak_text", "target": "Here is your mug.", "parameters": {"volume": 0.8}},
    ],
}

# The shape of seed 000: a bare array of {action, target_object, target_location, parameters}.
ARRAY_SHAPE = [
    {"action": "navigate", "target_location": "kitchen table", "parameters": {}, "description": "walk over"},
    {"action": "pick_up", "target_object": "blue cup", "target_location": "kitchen table"},
    {"action": "put_down", "target_object": "blue cup", "target_location": "shelf"},
    {"action": "pause", "parameters": {"duration": 2}},
    {"action": "halt"},
]


def refusal(text: str, fmt: str = "auto") -> ServiceError:
    with pytest.raises(ParseError) as caught:
        parse(text, fmt)
    error = caught.value.error
    assert error.stage is Stage.PARSE
    return error


def test_demo_plan_parses() -> None:
    plan = parse(json.dumps(DEMO))
    assert [s.action for s in plan.steps] == [Action.NAVIGATE_TO, Action.PICK, Action.NAVIGATE_TO, Action.PLACE]
    assert plan.steps[0].target == "kitchen counter"
    assert plan.steps[1].target == "red cup"
    assert (plan.steps[3].target, plan.steps[3].location) == (None, "coffee table")
    assert plan.warnings == []


def test_object_with_plan_array() -> None:
    plan = parse(json.dumps(OBJECT_SHAPE))
    assert plan.description == "Bring the mug to the living room"
    assert [s.action for s in plan.steps] == [Action.NAVIGATE_TO, Action.DETECT, Action.PICK, Action.PLACE, Action.SAY]
    assert plan.steps[0].params == {}
    assert plan.steps[0].description == "go"
    assert plan.steps[2].params == {"approach": "top"}
    assert plan.steps[3].location == "coffee table"
    assert plan.steps[4].params == {"text": "Here is your mug.", "volume": 0.8}
    # The LLM's coordinates are carried, untrusted, for the resolver to check against the kitchen.
    assert plan.steps[0].coordinates == Coordinates(x=3.0, y=2.5)
    assert [s.coordinates for s in plan.steps[1:]] == [None] * 4
    assert plan.warnings == []


def test_bare_array_with_target_object_and_location() -> None:
    plan = parse(json.dumps(ARRAY_SHAPE))
    navigate, pick, place, wait, stop = plan.steps
    assert (navigate.action, navigate.target) == (Action.NAVIGATE_TO, "kitchen table")
    assert navigate.description == "walk over"
    assert (pick.action, pick.target, pick.location) == (Action.PICK, "blue cup", "kitchen table")
    assert (place.action, place.target, place.location) == (Action.PLACE, "blue cup", "shelf")
    assert (wait.action, wait.params) == (Action.WAIT, {"duration": 2.0})
    assert stop.action is Action.STOP
    assert plan.warnings == []


def test_fenced_block_with_prose_around_it() -> None:
    text = (
        "Sure! Here is a plan for the robot:\n\n```json\n"
        + json.dumps(DEMO, indent=2)
        + "\n```\n\nThe robot first goes to the counter. Let me know if you need anything else {or not}."
    )
    plan = parse(text)
    assert len(plan.steps) == 4


def test_plain_fence_and_unfenced_json_in_prose() -> None:
    assert len(parse("Plan:\n```\n" + json.dumps(ARRAY_SHAPE) + "\n```").steps) == 5
    text = "Here [as asked] is the plan: " + json.dumps(DEMO) + " -- hope it helps"
    assert len(parse(text).steps) == 4


@pytest.mark.parametrize(
    ("name", "action"),
    [
        ("go_to", Action.NAVIGATE_TO),
        ("Move To", Action.NAVIGATE_TO),
        ("goto", Action.NAVIGATE_TO),
        ("grab", Action.PICK),
        ("pickUp", Action.PICK),
        ("take", Action.PICK),
        ("put", Action.PLACE),
        ("drop-off", Action.PLACE),
        ("locate", Action.DETECT),
        ("find", Action.DETECT),
        ("halt", Action.STOP),
    ],
)
def test_synonyms(name: str, action: Action) -> None:
    step = {"action": name, "target": "red cup"} if action is not Action.STOP else {"action": name}
    assert parse(json.dumps([step])).steps[0].action is action


def test_say_and_wait_values() -> None:
    plan = parse(
        json.dumps(
            [
                {"action": "tell", "parameters": {"text": "hello", "volume": "0.5"}},
                {"action": "sleep", "parameters": {"duration": "1.5 seconds"}},
                {"action": "wait", "parameters": {"seconds": "500 ms"}},
            ]
        )
    )
    assert plan.steps[0].params == {"text": "hello", "volume": 0.5}
    assert plan.steps[1].params == {"duration": 1.5}
    assert plan.steps[2].params == {"duration": 0.5}


def test_unknown_parameters_and_fields_are_warned_about_not_kept() -> None:
    text = json.dumps(
        [
            {"action": "pick", "target": "red cup", "parameters": {"force": 9, "approach": "side"}, "confidence": 1},
            {"action": "stop", "target": "everything"},
        ]
    )
    plan = parse(text)
    assert plan.steps[0].params == {"approach": "side"}
    assert plan.steps[1].target is None
    assert any(w.startswith("step 1: unknown parameter(s) 'force' for pick ignored") for w in plan.warnings)
    assert any(w.startswith("step 1: field(s) 'confidence' ignored") for w in plan.warnings)
    assert any(w.startswith("step 2: target 'everything' ignored") for w in plan.warnings)


def test_unknown_action_suggests_the_nearest() -> None:
    steps = [{"action": "navigate_to", "target": "x"}, {"action": "plcae", "target": "t"}]
    error = refusal(json.dumps({"plan": steps}))
    assert error.kind is ErrorKind.UNKNOWN_ACTION
    assert error.step == 1
    assert "step 2" in error.message
    assert "did you mean 'place'?" in error.message
    assert "navigate_to, pick, place, detect, look_at, drive, turn, stop, say" in error.message
    assert error.candidates[0] == "place"


def test_unknown_action_without_a_near_name_lists_known_ones() -> None:
    error = refusal(json.dumps([{"action": "juggle", "target": ""}]))
    assert error.kind is ErrorKind.UNKNOWN_ACTION
    assert "'juggle'" in error.message and "known actions" in error.message


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "plan text is empty"),
        ("  \n\t ", "only whitespace"),
        ("I could not make a plan, sorry.", "no plan found: expected a JSON object with a 'plan' array"),
        ('{"goal": "tidy up"}', "found an object with keys 'goal'"),
        ("42", "no plan found"),
        ('{"plan": []}', "the plan has no steps"),
        ('{"plan": "go to the kitchen"}', "'plan' must be an array of steps"),
        ("```yaml\nplan:\n  - action: stop\n  - [unclosed\n```", "malformed YAML"),
    ],
)
def test_garbage_is_refused_with_a_reason(text: str, expected: str) -> None:
    error = refusal(text)
    assert error.kind is ErrorKind.INVALID_REQUEST
    assert expected in error.message


def test_malformed_json_names_the_position() -> None:
    # Cut off mid-plan: never repaired, since the missing steps would be silently lost.
    error = refusal('{"plan": [\n  {"action": "pick", "target": "red cup"},\n  {"action": "pla')
    assert "malformed JSON" in error.message
    assert "line 3" in error.message
    assert "still open" in error.message


def test_mismatched_brackets_are_refused() -> None:
    error = refusal('{"plan": [{"action": "stop"}}')
    assert "malformed JSON at line 1" in error.message


def test_small_repairable_json_is_read_with_a_warning() -> None:
    plan = parse("{'plan': [{'action': 'pick', 'target': 'red cup',},]}")
    assert plan.steps[0].target == "red cup"
    assert plan.warnings and "read leniently" in plan.warnings[0]


def test_strict_parser_refuses_what_lenient_repairs() -> None:
    strict = Parser(load_vocabulary(), config=ParserConfig(lenient_json=False))
    with pytest.raises(ParseError) as caught:
        strict.parse('{"plan": [{"action": "stop",}]}')
    assert "malformed JSON: Expecting property name" in caught.value.error.message


@pytest.mark.parametrize(
    ("steps", "expected", "step"),
    [
        (["go to the kitchen", "fly to the moon"], "step 2: cannot read 'fly to the moon': unknown verb 'fly'", 1),
        ([{"action": "stop"}, 3], "step 2: is a number, not an object with an 'action'", 1),
        ([{"action": "stop"}, {"target": "red cup"}], "step 2: has no 'action'", 1),
        ([{"action": 7}], "'action' must be a string", 0),
        ([{"action": "pick"}], "pick needs a target", 0),
        ([{"action": "place", "target_object": "red cup"}], "place needs a location", 0),
        ([{"action": "say"}], "say needs the words", 0),
        ([{"action": "wait"}], "wait needs parameter 'duration'", 0),
        ([{"action": "wait", "parameters": {"duration": 61}}], "'duration' is 61 s; allowed 0..60 s", 0),
        ([{"action": "wait", "parameters": {"duration": -1}}], "allowed 0..60 s", 0),
        ([{"action": "wait", "parameters": {"duration": "2 hours"}}], "unit 'hours'", 0),
        ([{"action": "wait", "parameters": {"duration": True}}], "must be a number", 0),
        ([{"action": "say", "target": "hi", "parameters": {"volume": 3}}], "'volume' is 3; allowed 0..1", 0),
        ([{"action": "pick", "target": "cup", "parameters": {"approach": "under"}}], "expected one of top, side", 0),
        ([{"action": "pick", "target": {"name": "cup"}}], "'target' must be a name", 0),
        ([{"action": "pick", "target": "x" * 500}], "a name has at most 200", 0),
        ([{"action": "pick", "target": "cup", "parameters": [1]}], "'parameters' must be an object", 0),
    ],
)
def test_bad_steps_are_refused_naming_the_step(steps: list[object], expected: str, step: int) -> None:
    error = refusal(json.dumps(steps))
    assert expected in error.message
    assert error.step == step


def test_nan_and_infinity_are_refused() -> None:
    error = refusal('[{"action": "wait", "parameters": {"duration": NaN}}]')
    assert "finite" in error.message
    error = refusal('[{"action": "wait", "parameters": {"duration": 1e999}}]')
    assert "finite" in error.message


def test_too_many_steps() -> None:
    error = refusal(json.dumps([{"action": "stop"}] * (MAX_STEPS + 1)))
    assert f"{MAX_STEPS + 1} steps; at most {MAX_STEPS}" in error.message


def test_too_large_text() -> None:
    error = refusal('{"plan": [{"action": "say", "target": "' + "a" * MAX_PLAN_BYTES + '"}]}')
    assert "bytes; at most" in error.message


@pytest.mark.parametrize(
    "text",
    [
        "[" * 50_000,
        "[" * 5_000 + "]" * 5_000,
        '{"plan": ' + '{"a": ' * 1000 + "1" + "}" * 1000 + "}",
        "Here: " + "{" * 20_000,
        '{"plan": [{"action": "pick", "target": "' + "\\u0000" * 100 + '"}]}',
        "\x00\x01\x02 binary",
        "\ud800 lone surrogate",
        '"just a string"',
        "```json\n```",
        "{" + '"a": 1, ' * 10_000 + "}",
    ],
)
def test_hostile_input_is_refused_not_raised(text: str) -> None:
    error = refusal(text)
    assert error.kind in (ErrorKind.INVALID_REQUEST, ErrorKind.UNKNOWN_ACTION)
    assert len(error.message) <= 4000


def test_huge_unknown_parameter_set_gives_a_bounded_warning() -> None:
    params = {f"p{i}": i for i in range(5000)}
    plan = parse(json.dumps([{"action": "stop", "parameters": params}]))
    assert len(plan.warnings) == 1
    assert "and 4990 more" in plan.warnings[0]


def test_formats() -> None:
    assert len(parse(json.dumps(DEMO), "json").steps) == 4
    # JSON is YAML too; as English it is unreadable, and refused by line and column.
    assert parse(json.dumps(DEMO), "yaml").steps == parse(json.dumps(DEMO), "json").steps
    error = refusal(json.dumps(DEMO), "text")
    assert error.line == 1 and error.column is not None
    assert "unknown format 'xml'" in refusal(json.dumps(DEMO), "xml").message


def test_plans_round_trip_the_wire_schema() -> None:
    plan = parse(json.dumps(OBJECT_SHAPE))
    assert msgspec.json.decode(msgspec.json.encode(plan), type=Plan) == plan


def test_answer_is_always_a_value() -> None:
    assert isinstance(answer(default_parser(), PlanText(text=json.dumps(DEMO))), Plan)
    reply = answer(default_parser(), PlanText(text="{{{{"))
    assert isinstance(reply, ServiceError)
    assert reply.stage is Stage.PARSE


def test_vocabulary_file_errors_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "vocabulary.yaml"
    bad.write_text("actions:\n  pick: {synonyms: [grab]}\n")
    with pytest.raises(VocabularyError, match="no entry for actions"):
        load_vocabulary(bad)
    bad.write_text("actions: {}\nfoo: 1\n")
    with pytest.raises(VocabularyError, match=str(bad)):
        load_vocabulary(bad)


def test_a_number_too_large_for_a_float_is_refused_not_crashed() -> None:
    error = refusal('[{"action": "wait", "parameters": {"duration": ' + "9" * 400 + "}}]")
    assert "too large" in error.message and error.step == 0


def test_a_text_full_of_code_blocks_gets_a_refusal() -> None:
    text = ("```\n{}\n```\n" * 30000)[: MAX_PLAN_BYTES - 1]
    error = answer(default_parser(), PlanText(text=text))
    assert isinstance(error, ServiceError) and "no plan found" in error.message


# Coordinates: carried, untrusted, for the resolver; malformed ones refuse the step.


@pytest.mark.parametrize(
    ("fields", "point"),
    [
        ({"x": 3.5, "y": 2.0}, Coordinates(x=3.5, y=2.0)),
        ({"parameters": {"x": 3, "y": -2, "z": 0.5}}, Coordinates(x=3.0, y=-2.0, z=0.5)),
        ({"x": "350 cm", "parameters": {"y": "2 m"}}, Coordinates(x=3.5, y=2.0)),
        ({"position": {"x": 1, "y": 2}}, Coordinates(x=1.0, y=2.0)),
        ({"coordinates": [1, 2, 0.7]}, Coordinates(x=1.0, y=2.0, z=0.7)),
        ({"coords": "3.5, 2.0"}, Coordinates(x=3.5, y=2.0)),
        ({"point": "(3.5, 2.0)"}, Coordinates(x=3.5, y=2.0)),
        ({"xyz": "[1, 2, 3]"}, Coordinates(x=1.0, y=2.0, z=3.0)),
        ({"parameters": {"position": "x: 1, y = 2, z 30 cm"}}, Coordinates(x=1.0, y=2.0, z=0.3)),
        ({"location": [1, 2]}, Coordinates(x=1.0, y=2.0)),
        ({"pose": {"x": 1, "y": 2, "yaw": 1.57}}, Coordinates(x=1.0, y=2.0)),
        ({"target_pose": [1, 2]}, Coordinates(x=1.0, y=2.0)),
        ({"goal_pose": {"position": {"x": 1, "y": 2, "z": 0}, "orientation": {"w": 1}}}, Coordinates(x=1, y=2, z=0)),
        ({"goal_pose": {"header": {"frame_id": "/map"}, "pose": {"position": [1, 2]}}}, Coordinates(x=1.0, y=2.0)),
        ({"x": 1, "y": 2, "frame_id": "map"}, Coordinates(x=1.0, y=2.0)),
        ({"x": 1, "y": 2, "position": {"x": "100 cm", "y": 2, "z": 0.4}}, Coordinates(x=1.0, y=2.0, z=0.4)),
        ({"x": -1000, "y": 1000}, Coordinates(x=-1000.0, y=1000.0)),
        ({"x": None, "y": None, "pose": None}, None),
    ],
)
def test_coordinates_in_the_shapes_llms_write_them(fields: dict[str, object], point: Coordinates | None) -> None:
    step = parse(json.dumps([{"action": "navigate_to", "target": "kitchen", **fields}])).steps[0]
    assert step.target == "kitchen"
    assert step.coordinates == point


@pytest.mark.parametrize(
    "step",
    [
        {"action": "navigate_to"},
        {"action": "look_at"},
        {"action": "pick"},
        {"action": "detect"},
        {"action": "place", "target_object": "red cup"},
    ],
)
def test_a_step_with_coordinates_needs_no_name(step: dict[str, object]) -> None:
    parsed = parse(json.dumps([{**step, "x": 1.5, "y": 2.5}])).steps[0]
    assert parsed.coordinates == Coordinates(x=1.5, y=2.5)
    assert parsed.location is None
    assert parsed.target == step.get("target_object")
    error = refusal(json.dumps([step]))
    assert "or coordinates x and y in metres" in error.message


def test_a_name_and_coordinates_are_both_kept_for_the_resolver_to_compare() -> None:
    plan = parse(json.dumps([{"action": "place", "object": "cup", "surface": "shelf", "position": [4, 1, 0.9]}]))
    step = plan.steps[0]
    assert (step.target, step.location, step.coordinates) == ("cup", "shelf", Coordinates(x=4.0, y=1.0, z=0.9))
    assert plan.warnings == []


def test_actions_without_a_point_ignore_coordinates_with_a_warning() -> None:
    plan = parse(
        json.dumps(
            [
                {"action": "drive", "distance": 1, "x": 1, "y": 2},
                {"action": "say", "target": "hi", "position": "not even a point"},
                {"action": "move_arm", "target": "home", "joints": [0, 1, 2]},
            ]
        )
    )
    assert [s.coordinates for s in plan.steps] == [None, None, None]
    assert plan.warnings == [
        "step 1: parameters x, y ignored: positions come from the world model",
        "step 2: parameter position ignored: positions come from the world model",
        "step 3: parameter joints ignored: positions come from the world model",
    ]


def test_headings_and_joints_are_ignored_with_a_warning_beside_a_point() -> None:
    plan = parse(json.dumps([{"action": "navigate_to", "x": 1, "y": 2, "theta": 1.5, "latitude": 52.5}]))
    assert plan.steps[0].coordinates == Coordinates(x=1.0, y=2.0)
    assert plan.warnings == [
        "step 1: parameter latitude ignored: positions come from the world model",
        "step 1: parameter theta ignored: the resolver chooses headings",
    ]


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"x": 1}, "gives coordinate 'x' without 'y'"),
        ({"y": 1, "z": 0}, "gives coordinate 'y' and 'z' without 'x'"),
        ({"x": "abc", "y": 1}, "coordinate 'x' must be a number, got 'abc'"),
        ({"x": True, "y": 1}, "coordinate 'x' must be a number, got a boolean"),
        ({"x": [1], "y": 1}, "coordinate 'x' must be a number, got an array"),
        ({"x": 1001, "y": 1}, "coordinate 'x' is 1001 m; allowed -1000..1000 m"),
        ({"x": "2 km", "y": 1}, "coordinate 'x' has unit 'km'"),
        ({"x": "1e999", "y": 1}, "coordinate 'x' must be a finite number"),
        ({"position": [1, 2, 3, 4, 5]}, "'position' must be 2 or 3 numbers"),
        ({"position": [1]}, "'position' must be 2 or 3 numbers"),
        ({"position": [1, True]}, "'position' y must be a number, got a boolean"),
        ({"position": "1, 2, 3, 4"}, "'position' must be a point such as"),
        ({"position": "the window"}, "got 'the window'; a name goes in 'target'"),
        ({"position": "x=1, x=2"}, "'position' must be a point such as"),
        ({"position": "(1; 2)"}, "'position' must be a point such as"),
        ({"position": 5}, "'position' must be a point such as"),
        ({"position": {"x": 1}}, "'position' needs x and y"),
        ({"position": {"room": "kitchen"}}, "got 'room'; a name goes in 'target'"),
        ({"position": {"x": 1, "X": 2, "y": 0}}, "'position' gives a coordinate twice"),
        ({"location": {"x": 1, "y": "far"}}, "'location' y must be a number"),
        ({"pose": [1, 2, 0.5]}, "'pose' has three numbers"),
        ({"pose": "1, 2, 0.5"}, "'pose' has three numbers"),
        ({"pose": {"x": 1, "y": 2, "frame_id": "odom"}}, "'pose' is in frame 'odom'; coordinates are read in the map"),
        ({"pose": {"header": {"frame_id": 7}, "x": 1, "y": 2}}, "'pose' is in frame a number"),
        ({"x": 1, "y": 2, "frame": "base_link"}, "the step's point is in frame 'base_link'"),
        ({"position": "1, " * 200}, "a point is at most 200"),
    ],
)
def test_malformed_coordinates_are_refused_naming_the_field(fields: dict[str, object], expected: str) -> None:
    error = refusal(json.dumps([{"action": "stop"}, {"action": "navigate_to", "target": "kitchen", **fields}]))
    assert expected in error.message
    assert error.message.startswith("step 2: ") and error.step == 1


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"x": 1, "y": 2, "position": [1, 3]}, "two different points: x/y (1, 2) and 'position' (1, 3)"),
        ({"pose": {"x": 1, "y": 2}, "point": "1, 2.5"}, "two different points: 'pose' (1, 2) and 'point' (1, 2.5)"),
        ({"x": 1, "y": 2, "z": 0, "xyz": [1, 2, 1]}, "x/y/z (1, 2, 0) and 'xyz' (1, 2, 1)"),
        (
            {"x": 1, "y": 2, "parameters": {"x": 1.5}},
            "gives coordinate 'x' twice: 1.5 ('x' in parameters) and 1 ('x' beside the action)",
        ),
    ],
)
def test_coordinate_sources_that_disagree_are_refused_naming_both(fields: dict[str, object], expected: str) -> None:
    error = refusal(json.dumps([{"action": "pick", "target": "cup", **fields}]))
    assert expected in error.message


def test_a_location_name_is_still_a_name() -> None:
    step = parse(json.dumps([{"action": "navigate_to", "location": "kitchen"}])).steps[0]
    assert (step.target, step.coordinates) == ("kitchen", None)


def test_english_points_become_coordinates() -> None:
    plan = parse("1. Go to (3.5, 2.0)\n2. go to the kitchen at x 2.5 y 250 cm\n3. look at 1, 2, 1.2", "text")
    assert [(s.target, s.coordinates) for s in plan.steps] == [
        (None, Coordinates(x=3.5, y=2.0)),
        ("kitchen", Coordinates(x=2.5, y=2.5)),
        (None, Coordinates(x=1.0, y=2.0, z=1.2)),
    ]
    error = refusal("1. go to the kitchen\n2. go to (1, 2000)", "text")
    assert (error.line, error.step) == (2, 1)
    assert "'point' y is 2000 m" in error.message


def test_coordinates_round_trip_the_wire_schema() -> None:
    plan = parse(json.dumps([{"action": "pick", "target": "cup", "position": [1, 2, 0.9]}, {"action": "stop"}]))
    assert msgspec.json.decode(msgspec.json.encode(plan), type=Plan) == plan


@pytest.mark.parametrize(
    ("coordinates", "problem"),
    [
        ({"points": ["position", "target"], "poses": []}, "point key 'target' is also a step field"),
        ({"points": ["position", "surface"], "poses": []}, ""),  # a target_location name may also hold a point
        ({"headings": ["yaw", "x"]}, "'x' is listed as a coordinate axis and a heading key"),
        ({"points": ["spot"], "poses": ["pose"]}, "coordinates.poses must be among coordinates.points"),
    ],
)
def test_vocabulary_coordinate_keys_are_checked(tmp_path: Path, coordinates: dict[str, object], problem: str) -> None:
    vocabulary = msgspec.to_builtins(load_vocabulary())
    vocabulary["coordinates"].update(coordinates)
    path = tmp_path / "vocabulary.yaml"
    path.write_text(json.dumps(vocabulary))  # JSON is YAML
    if not problem:
        assert load_vocabulary(path).coordinates.points == coordinates["points"]
        return
    with pytest.raises(VocabularyError, match=str(path)) as caught:
        load_vocabulary(path)
    assert problem in str(caught.value)


# Arrays of English sentences: each string is read by the English grammar as one step (or a group).


def test_an_array_of_sentences_is_a_plan() -> None:
    plan = parse(json.dumps(["Go to the kitchen table", "Pick up the blue cup", "Bring it to me"]))
    assert plan.source_format == "json" and plan.warnings == []
    go, pick, bring = plan.steps
    assert (go.action, go.target, go.description) == (Action.NAVIGATE_TO, "kitchen table", "Go to the kitchen table")
    assert (pick.action, pick.target) == (Action.PICK, "blue cup")
    assert bring.action is None and bring.description == "Bring it to me"
    assert [(s.action, s.target, s.location) for s in bring.substeps] == [
        (Action.PICK, "it", None),
        (Action.PLACE, "it", "me"),
    ]


@pytest.mark.parametrize(
    ("text", "source_format"),
    [
        ('{"plan": ["go to the kitchen", "bring me the cup"]}', "json"),
        ('{"steps": ["go to the kitchen", "bring me the cup"]}', "json"),
        ('Sure! Here is the plan: ["go to the kitchen", "bring me the cup"]', "json"),
        ("plan:\n  - go to the kitchen\n  - bring me the cup\n", "yaml"),
        ('[{"action": "navigate_to", "target": "kitchen"}, "bring me the cup"]', "json"),
    ],
)
def test_sentences_in_structured_plans(text: str, source_format: str) -> None:
    plan = parse(text)
    assert plan.source_format == source_format
    assert [s.action for s in plan.steps] == [Action.NAVIGATE_TO, None]
    assert [(s.action, s.location) for s in plan.steps[1].substeps] == [(Action.PICK, None), (Action.PLACE, "me")]


def test_a_sentence_with_several_clauses_is_a_group_and_bad_ones_name_their_index() -> None:
    plan = parse(json.dumps(["go to the kitchen and pick up the cup", "stop"]))
    assert plan.steps[0].action is None and plan.steps[0].description == "go to the kitchen and pick up the cup"
    assert [s.action for s in plan.steps[0].substeps] == [Action.NAVIGATE_TO, Action.PICK]
    error = refusal(json.dumps(["go to the kitchen", "pick up the cup", "plce it on the table"]))
    assert error.step == 2 and error.kind is ErrorKind.UNKNOWN_ACTION
    assert error.message.startswith("step 3: cannot read 'plce it on the table': unknown verb 'plce'")
    assert error.candidates[0] == "place"
    error = refusal(json.dumps(["go to the kitchen", "drive forward 9 m"]))
    assert error.step == 1 and "step 2: parameter 'distance' is 9 m; allowed -5..5 m" in error.message
    error = refusal(json.dumps({"plan": ["tidy up the cup"]}))
    assert (
        error.message
        == "step 1: cannot read 'tidy up the cup': tidy up needs a place to put cup: say 'tidy up cup onto the shelf'"
    )


def test_prose_with_a_list_of_words_is_not_a_plan() -> None:
    assert "no plan found" in refusal('I could use ["red", "blue"] cups.').message


# Structured steps whose action stands for several steps, driven by vocabulary.yaml `expansions`.


def steps_of(step: dict[str, object]) -> list[tuple[Action | None, str | None, str | None]]:
    (only,) = parse(json.dumps([step])).steps
    return [(s.action, s.target, s.location) for s in (only.substeps or [only])]


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "bring", "target": "red cup"}, [(Action.PICK, "red cup", None), (Action.PLACE, "red cup", "me")]),
        ({"action": "fetch", "object": "keys"}, [(Action.PICK, "keys", None), (Action.PLACE, "keys", "me")]),
        ({"action": "get", "target": "mug"}, [(Action.PICK, "mug", None), (Action.PLACE, "mug", "me")]),
        (
            {"action": "bring", "object": "cup", "target": "operator"},
            [(Action.PICK, "cup", None), (Action.PLACE, "cup", "operator")],
        ),
        (
            {"action": "deliver", "target_object": "cup", "destination": "kitchen table"},
            [(Action.PICK, "cup", None), (Action.PLACE, "cup", "kitchen table")],
        ),
        (
            {"action": "tidy_up", "target": "book", "location": "bookshelf"},
            [(Action.PICK, "book", None), (Action.PLACE, "book", "bookshelf")],
        ),
        ({"action": "put_back", "target": "cup"}, [(Action.PLACE, "cup", "where it was found")]),
        ({"action": "putBack"}, [(Action.PLACE, "it", "where it was found")]),
        ({"action": "go_home"}, [(Action.NAVIGATE_TO, "home", None)]),
        ({"action": "return home"}, [(Action.NAVIGATE_TO, "home", None)]),
        ({"action": "return_to_dock"}, [(Action.NAVIGATE_TO, "dock", None)]),
    ],
)
def test_structured_expansions(step: dict[str, object], expected: list[tuple[Action, str, str | None]]) -> None:
    assert steps_of(step) == expected


def test_an_expansion_keeps_its_fallback_and_hands_on_its_parameters() -> None:
    step = {
        "action": "bring",
        "target": "cup",
        "approach": "top",
        "description": "the user is thirsty",
        "on_failure": [{"action": "say", "text": "I could not bring it"}],
    }
    plan = parse(json.dumps([step]))
    (group,) = plan.steps
    assert group.description == "the user is thirsty"
    assert [s.params for s in group.substeps] == [{"approach": "top"}, {"approach": "top"}]
    assert [s.action for s in group.on_failure] == [Action.SAY]
    (home,) = parse(json.dumps([{"action": "go_home", "speed": 0.5, "target": "kitchen"}])).steps
    assert (home.target, home.params) == ("home", {"speed": 0.5})  # the plan's target is not where go_home goes


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "bring"}, "step 1: 'bring' needs which object to bring"),
        ({"action": "tidy_up", "target": "cup"}, "step 1: 'tidy_up' needs a place to put it"),
        ({"action": "bring", "target": "cup", "approach": "under"}, "step 1.1: parameter 'approach' is 'under'"),
        ({"action": "go_home", "speed": 3}, "step 1: parameter 'speed' is 3 m/s; allowed 0.05..1 m/s"),
        ({"action": "bring", "target": "cup", "substeps": [{"action": "stop"}]}, "cannot also have sub-steps"),
    ],
)
def test_structured_expansions_never_invent_and_never_skip_checks(step: dict[str, object], expected: str) -> None:
    assert expected in refusal(json.dumps([step])).message


def test_a_target_an_expansion_does_not_use_is_warned_about() -> None:
    plan = parse(json.dumps([{"action": "go_home", "target": "kitchen"}]))
    assert plan.steps[0].target == "home"
    assert any("target 'kitchen' ignored: go_home does not use it" in w for w in plan.warnings)


# Hints: not commands; warnings, and a mapping where one exists.


@pytest.mark.parametrize(
    ("params", "warning"),
    [
        ({"approach": "pinch"}, "a precision (pinch) grasp is what the parallel gripper does"),
        ({"grasp_type": "power"}, "the parallel gripper has no power grasp"),
        ({"grasp": "Precision grasp"}, "the approach is left to the robot"),
        ({"approach_distance": 0.1}, "'approach_distance' is a hint the robot does not take"),
        ({"pre_grasp_offset": "5 cm"}, "the robot plans its approach from the world model"),
        ({"manner": "gently"}, "manner 'gently' read as a hint: pick has no slower speed"),
    ],
)
def test_a_hint_is_a_warning_not_a_refusal(params: dict[str, object], warning: str) -> None:
    plan = parse(json.dumps([{"action": "pick", "target": "cup", "parameters": params}]))
    assert plan.steps[0].params == {}
    assert any(warning in w for w in plan.warnings), plan.warnings


def test_a_grasp_type_beside_a_real_approach_keeps_the_approach() -> None:
    plan = parse(json.dumps([{"action": "pick", "target": "cup", "approach": "side"}]))
    assert plan.steps[0].params == {"approach": "side"} and plan.warnings == []
    assert (
        "expected one of top, side"
        in refusal(json.dumps([{"action": "pick", "target": "c", "approach": "under"}])).message
    )


def test_a_manner_only_ever_slows_the_robot() -> None:
    vocabulary = load_vocabulary()
    slow = vocabulary.hints.manner.speeds["slow"]
    plan = parse(
        json.dumps(
            [
                {"action": "navigate_to", "target": "kitchen", "manner": "carefully"},
                {"action": "drive", "distance": 0.5, "parameters": {"manner": "slowly"}},
                {"action": "navigate_to", "target": "hall", "speed": 0.1, "manner": "gently"},
                {"action": "turn", "angle": "90 degrees", "manner": "carefully"},
                {"action": "navigate_to", "target": "hall", "manner": "quickly"},
            ]
        )
    )
    speeds = [s.params.get("speed") for s in plan.steps]
    assert speeds == [slow[Action.NAVIGATE_TO], slow[Action.DRIVE], 0.1, None, None]
    # Every speed a manner sets is below the robot's usual one, and within what the parameter allows.
    for action, speed in slow.items():
        spec = vocabulary.actions[action].params["speed"]
        assert spec.min is not None and spec.max is not None and spec.min <= speed < 0.5 * spec.max
    assert plan.steps[0].units == {"speed": "m/s"}
    assert any("speed set to 0.25 m/s" in w for w in plan.warnings)
    assert any("the step's speed 0.1 m/s is kept" in w for w in plan.warnings)
    assert any("manner 'quickly' ignored" in w for w in plan.warnings)


def test_english_hints_become_warnings_and_mappings() -> None:
    plan = parse("1. go to the kitchen carefully\n2. pick up the cup with a pinch grasp from 10 cm above\n3. stop")
    assert plan.steps[0].params == {"speed": 0.25} and plan.steps[1].params == {}
    assert [w.split(":")[0] for w in plan.warnings] == ["line 1, column 4", "line 2, column 4", "line 2, column 4"]


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "navigate_to", "target": "kitchen", "speed": 2.0, "manner": "carefully"}, "'speed' is 2 m/s"),
        ({"action": "drive", "distance": "9 m", "manner": "gently"}, "'distance' is 9 m"),
        ({"action": "close_gripper", "force": 500, "manner": "gently"}, "'force' is 500 N"),
        ({"action": "pick", "target": "cup", "approach": "pinchy"}, "expected one of top, side"),
    ],
)
def test_parameters_that_touch_safety_are_checked_beside_hints(step: dict[str, object], expected: str) -> None:
    assert expected in refusal(json.dumps([step])).message


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        ({"expansions": {"bring": {"synonyms": ["grab"], "steps": [{"action": "pick"}]}}}, "'grab' also names pick"),
        (
            {"expansions": {"x": {"steps": [{"action": "pick", "target": "{thing}"}]}}},
            "'{thing}', not one of its slots",
        ),
        ({"expansions": {"x": {"slots": {"a": {"fields": ["target"]}}, "steps": [{"action": "stop"}]}}}, "`needs`"),
        ({"hints": {"manner": {"params": ["speed"]}}}, "'speed' is a parameter of"),
        ({"hints": {"manner": {"words": {"slowly": "slow"}, "speeds": {"slow": {"navigate_to": 5.0}}}}}, "not one"),
        ({"hints": {"manner": {"words": {"slowly": "slow"}, "speeds": {"slow": {"pick": 0.1}}}}}, "not one"),
        ({"hints": {"grasp": {"params": ["approach"], "types": {"pinch": "precision"}}}}, "has no meaning"),
    ],
)
def test_vocabulary_expansions_and_hints_are_checked(tmp_path: Path, change: dict[str, object], problem: str) -> None:
    vocabulary = msgspec.to_builtins(load_vocabulary())
    vocabulary.update(change)
    path = tmp_path / "vocabulary.yaml"
    path.write_text(json.dumps(vocabulary))
    with pytest.raises(VocabularyError, match=str(path)) as caught:
        load_vocabulary(path)
    assert problem in str(caught.value)


# JSON's \ud800 escape decodes to a lone surrogate, which no reply can encode as UTF-8.
LONE_SURROGATES = [
    r'[{"action": "navigate_to", "target": "\ud800"}]',
    r'{"plan": [{"action": "say", "parameters": {"text": "hi \udfff"}}], "description": "x"}',
    r'[{"action": "\ud800 dance"}]',
    r'[{"type": "tool_use", "name": "wait", "input": {"duration": 1}}, {"type": "\ud800"}]',
]


@pytest.mark.parametrize("text", LONE_SURROGATES)
def test_a_lone_surrogate_escape_is_refused_in_words_the_reply_can_carry(text: str) -> None:
    reply = answer(default_parser(), PlanText(text=text, format="auto"))
    assert isinstance(reply, ServiceError), reply
    encoded = msgspec.json.encode(reply)  # raised UnicodeEncodeError before: the service answered "internal"
    assert msgspec.json.decode(encoded, type=ServiceError).stage is Stage.PARSE


def test_a_lone_surrogate_in_a_plan_is_named() -> None:
    with pytest.raises(ParseError, match="not valid Unicode: a lone surrogate"):
        parse(LONE_SURROGATES[0], "json")
    # A pair of escapes is one character (an emoji): read as it is.
    assert parse(r'[{"action": "say", "target": "hi \ud83d\ude00"}]', "json").steps[0].params["text"] == "hi \U0001f600"


def test_a_step_key_with_a_lone_surrogate_is_an_ignored_field_on_every_path() -> None:
    """The plain path's conversion raised UnicodeEncodeError on such a key (a crash); the general mapping warns."""
    plan = parse(r'[{"action": "wait", "target": "1", "\ud800": 0}]', "json")
    assert plan.steps[0].params == {"duration": 1.0}
    assert len(plan.warnings) == 1 and "ignored" in plan.warnings[0]


def test_a_gemini_part_with_a_key_that_is_not_text_is_read() -> None:
    """YAML keys may be numbers or null: a part holding only `1: null` is skipped, not a TypeError."""
    for text in (
        "- functionCall:\n    name: wait\n    args: {duration: 1}\n- 1: null\n",
        "parts:\n- functionCall: {name: wait, args: {duration: 1}}\n- ~: ~\n",
    ):
        assert parse(text, "yaml").steps[0].params == {"duration": 1.0}


def test_a_number_with_its_unit_is_never_cut_before_the_unit() -> None:
    """Cut at 100 characters, "5 <99 spaces> mm" was read as 5 m; over 100 it is refused, naming the length."""
    drive = {"action": "drive", "parameters": {"distance": "5" + " " * 99 + "mm", "direction": "forward"}}
    with pytest.raises(
        ParseError, match=r"parameter 'distance' is 102 characters; a number with its unit has at most 100"
    ):
        parse(json.dumps([drive]), "json")
    drive["parameters"]["distance"] = "5" + " " * 50 + "mm"  # type: ignore[index]
    assert parse(json.dumps([drive]), "json").steps[0].params["distance"] == pytest.approx(0.005)


def test_malformed_json_too_large_and_deep_to_repair_is_refused_at_once() -> None:
    """json-repair's time grows with length times depth: 60 KB of text 30 levels deep took 3 s of CPU."""
    deep = "{" * 30 + "x" * 61_000 + "}" * 30
    started = time.thread_time()
    with pytest.raises(ParseError, match=r"not repaired: .* 61060 characters 30 levels deep"):
        parse(deep, "auto")
    assert time.thread_time() - started < 0.5


def test_a_parse_shares_one_repair_budget_over_all_its_candidates() -> None:
    """Four fenced blocks, each one repaired alone (0.3 s of CPU each): in one text, only the first is."""
    block = "```json\n" + "{" * 30 + "x" * 8_000 + "}" * 30 + "\n```\n"
    with pytest.raises(ParseError) as alone:
        parse(block, "auto")
    assert "not repaired" not in str(alone.value)
    with pytest.raises(ParseError, match="not repaired: the plan's malformed JSON is too large or too deeply nested"):
        parse(block * 4, "auto")


def test_a_plan_with_trailing_commas_is_still_repaired() -> None:
    steps = [{"action": "navigate_to", "target": "kitchen", "parameters": {"speed": 0.5}}] * 40
    broken = json.dumps({"plan": steps}).replace("}", ",}")
    plan = parse(broken, "json")
    assert len(plan.steps) == 40 and "read leniently" in plan.warnings[0]
