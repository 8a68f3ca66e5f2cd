"""The text reader: English list plans become step fields; what it cannot read is refused with line and column."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.common import ErrorKind, Stage
from services.parser.errors import ParseError, VocabularyError
from services.parser.text import (
    MAX_CLAUSE_CHARS,
    TextGrammar,
    TextStep,
    default_grammar_path,
    load_grammar,
    read_text,
)

GRAMMAR = load_grammar()


def read(text: str, **limits: int) -> list[TextStep]:
    steps, _ = read_text(text, GRAMMAR, **limits)
    return steps


def fields(text: str) -> dict[str, Any]:
    steps = read(text)
    assert len(steps) == 1, steps
    return steps[0].fields


def refused(text: str, **limits: int) -> ParseError:
    with pytest.raises(ParseError) as caught:
        read_text(text, GRAMMAR, **limits)
    assert caught.value.error.stage is Stage.PARSE
    return caught.value


def at(error: ParseError) -> tuple[int | None, int | None]:
    return error.error.line, error.error.column


# Lists


def test_numbered_list_gives_one_step_per_item_with_line_and_column() -> None:
    steps = read("1. Go to the kitchen\n2. Pick up the red cup\n3. Put it on the shelf.")
    assert [s.fields for s in steps] == [
        {"action": "navigate_to", "target": "kitchen"},
        {"action": "pick", "target": "red cup"},
        {"action": "place", "target": "it", "target_location": "shelf"},
    ]
    assert [(s.line, s.column) for s in steps] == [(1, 4), (2, 4), (3, 4)]
    assert [s.description for s in steps] == ["Go to the kitchen", "Pick up the red cup", "Put it on the shelf"]
    assert all(s.substeps == () and s.on_failure == () for s in steps)


@pytest.mark.parametrize(
    ("line", "column"),
    [
        ("1. go home", 4),
        ("1) go home", 4),
        ("(1) go home", 5),
        ("12. go home", 5),
        ("Step 1: go home", 9),
        ("Step 1 - go home", 10),
        ("step 1. go home", 9),
        ("**Step 1:** go home", 13),
        ("**Step 1**: go home", 13),
        ("- go home", 3),
        ("* go home", 3),
        ("\u2022 go home", 3),
        ("+ go home", 3),
        ("a. go home", 4),
        ("b) go home", 4),
        ("(c) go home", 5),
        ("   - go home", 6),
        ("1.\tgo home", 4),
        ("- **go home**", 5),
    ],
)
def test_list_markers(line: str, column: int) -> None:
    steps = read(line)
    assert [(s.fields, s.line, s.column) for s in steps] == [({"action": "navigate_to", "target": "home"}, 1, column)]


def test_indented_items_make_a_group_with_the_parents_text() -> None:
    text = "1. Fetch the cup:\n   - go to the kitchen\n   - pick up the cup\n2. Say Done"
    group, say = read(text)
    assert group.fields == {}
    assert group.description == "Fetch the cup:"
    assert (group.line, group.column) == (1, 4)
    assert [(s.fields["action"], s.line, s.column) for s in group.substeps] == [("navigate_to", 2, 6), ("pick", 3, 6)]
    assert say.fields == {"action": "say", "parameters": {"text": "Done"}}


def test_lettered_items_under_a_numbered_item_are_its_sub_items_without_indentation() -> None:
    text = "1. Fetch the cup\na. go to the kitchen\nb) pick up the cup\n2. go home"
    group, home = read(text)
    assert group.fields == {} and group.description == "Fetch the cup"
    assert [s.fields["action"] for s in group.substeps] == ["navigate_to", "pick"]
    assert home.fields["target"] == "home"


def test_deeper_nesting_and_return_to_outer_levels() -> None:
    text = "- Tidy up:\n  - Cup:\n    - pick up the cup\n    - put it in the sink\n  - stop\n- wave"
    tidy, wave = read(text)
    cup, stop = tidy.substeps
    assert [s.fields["action"] for s in cup.substeps] == ["pick", "place"]
    assert stop.fields == {"action": "stop"}
    assert wave.fields["action"] == "gesture"


def test_a_heading_that_reads_as_a_step_runs_before_its_sub_items() -> None:
    group, *_ = read("1. Go to the kitchen:\n   a. find the cup\n   b. pick it up")
    assert group.fields == {} and group.description == "Go to the kitchen:"
    assert [s.fields["action"] for s in group.substeps] == ["navigate_to", "detect", "pick"]


def test_a_verb_heading_that_cannot_be_read_is_kept_as_heading_with_a_warning() -> None:
    steps, warnings = read_text("1. Turn left\n   - turn left 90 degrees", GRAMMAR)
    assert steps[0].fields == {} and len(steps[0].substeps) == 1
    assert len(warnings) == 1 and "line 1" in warnings[0] and "heading" in warnings[0]


def test_windows_line_endings() -> None:
    steps = read("1. go home\r\n2. stop\r\n")
    assert [(s.line, s.fields["action"]) for s in steps] == [(1, "navigate_to"), (2, "stop")]


# Prose around the list


def test_prose_before_and_after_the_list_is_skipped_with_a_warning() -> None:
    text = "Here is the plan:\n\n```\n1. go home\n2. stop\n```\nLet me know if you need anything else!"
    steps, warnings = read_text(text, GRAMMAR)
    assert [s.line for s in steps] == [4, 5]
    assert len(warnings) == 2
    assert "line(s) 1, 3 before the list" in warnings[0] and "Here is the plan:" in warnings[0]
    assert "line(s) 6, 7 after the list" in warnings[1]


def test_prose_between_list_items_is_refused_with_its_line() -> None:
    error = refused("1. go home\n\n   Then carefully look around.\n2. stop")
    assert at(error) == (3, 4)
    assert "'Then carefully look around.' between list items" in str(error)


def test_without_a_list_each_sentence_is_a_step() -> None:
    steps = read("Go to the kitchen. Pick up the cup!\n  Then put it on the table.")
    assert [(s.fields["action"], s.line, s.column) for s in steps] == [
        ("navigate_to", 1, 1),
        ("pick", 1, 20),
        ("place", 2, 8),
    ]


def test_prose_after_a_chat_preamble_reads_and_a_sentence_that_is_no_step_is_refused() -> None:
    # What a chat model says before its plan is a filler (grammar.yaml), not a step.
    steps = read("Sure! Okay, here is the plan: go to the kitchen table. I will pick up the apple.")
    assert [s.fields["action"] for s in steps] == ["navigate_to", "pick"]
    error = refused("Sure, I can help with that.")
    assert at(error) == (1, 7)
    assert "unknown verb 'i'" in str(error)
    assert "has no step" in str(refused("Okay!"))


# Clauses


def test_compound_items_split_where_a_verb_phrase_follows() -> None:
    line = "1. Go to the kitchen, pick up the mug, and put it in the sink"
    steps = read(line)
    assert [s.fields["action"] for s in steps] == ["navigate_to", "pick", "place"]
    assert [s.column for s in steps] == [4, line.index("pick") + 1, line.index("put") + 1]
    assert [s.description for s in steps] == ["Go to the kitchen", "pick up the mug", "put it in the sink"]


@pytest.mark.parametrize(
    "text",
    [
        "go home; stop",
        "go home, then stop",
        "go home and then stop",
        "go home then stop",
        "go home and stop",
        "go home. Then stop",
        "go home, and finally stop",
    ],
)
def test_clause_separators(text: str) -> None:
    assert [s.fields["action"] for s in read("- " + text)] == ["navigate_to", "stop"]


def test_and_inside_a_noun_phrase_does_not_split() -> None:
    assert fields("- pick up the salt and pepper") == {"action": "pick", "target": "salt and pepper"}
    assert fields("- go to the hall and dining room")["target"] == "hall and dining room"


def test_quoted_text_is_never_split() -> None:
    steps = read('- say "hello; and then goodbye. Bye" and wave')
    assert steps[0].fields["parameters"] == {"text": "hello; and then goodbye. Bye"}
    assert steps[1].fields["action"] == "gesture"


@pytest.mark.parametrize(
    "clause",
    [
        "Please go home",
        "First, go home",
        "then go home",
        "Next go home",
        "Finally, go home.",
        "Now go home",
        "After that, go home",
        "afterwards go home",
        "also go home",
        "go home, please",
        "Then, please go home!",
    ],
)
def test_fillers_are_skipped_and_the_column_points_at_the_verb(clause: str) -> None:
    (step,) = read("1. " + clause)
    assert step.fields == {"action": "navigate_to", "target": "home"}
    assert step.column == 4 + clause.lower().index("go")
    assert step.description.lower() == "go home"


def test_case_is_ignored_and_noun_phrases_are_lower_cased() -> None:
    assert fields("1. PICK UP The Red Cup From The Kitchen Counter") == {
        "action": "pick",
        "target": "red cup",
        "target_location": "kitchen counter",
    }


@pytest.mark.parametrize(
    ("phrase", "target"),
    [
        ("the red cup", "red cup"),
        ("a cup", "cup"),
        ("some water", "water"),
        ("that", "that"),
        ("it", "it"),
        ("my keys", "my keys"),
        ("this cup", "cup"),
        ("the 3rd box", "3rd box"),
        ("Bob's mug", "bob's mug"),
    ],
)
def test_noun_phrases_lose_one_determiner(phrase: str, target: str) -> None:
    assert fields(f"- pick up {phrase}")["target"] == target


# Each action's patterns


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("go to the kitchen", {"action": "navigate_to", "target": "kitchen"}),
        ("walk over to the door", {"action": "navigate_to", "target": "door"}),
        ("go back to the kitchen", {"action": "navigate_to", "target": "kitchen"}),
        ("navigate to the kitchen table", {"action": "navigate_to", "target": "kitchen table"}),
        ("approach the person", {"action": "navigate_to", "target": "person"}),
        ("go home", {"action": "navigate_to", "target": "home"}),
        (
            "go to the kitchen at 0.3 m/s",
            {"action": "navigate_to", "target": "kitchen", "parameters": {"speed": "0.3 m/s"}},
        ),
        (
            "head to the door at a speed of 0.5 meters per second",
            {"action": "navigate_to", "target": "door", "parameters": {"speed": "0.5 meters per second"}},
        ),
        ("pick up the red cup", {"action": "pick", "target": "red cup"}),
        ("grab the cup from the counter", {"action": "pick", "target": "cup", "target_location": "counter"}),
        ("pick the book up off the shelf", {"action": "pick", "target": "book", "target_location": "shelf"}),
        ("take the cup out of the box", {"action": "pick", "target": "cup", "target_location": "box"}),
        ("grasp the cup from above", {"action": "pick", "target": "cup", "parameters": {"approach": "top"}}),
        ("grasp the cup from the side", {"action": "pick", "target": "cup", "parameters": {"approach": "side"}}),
        ("grab the box with a top grasp", {"action": "pick", "target": "box", "parameters": {"approach": "top"}}),
        ("put the cup on the table", {"action": "place", "target": "cup", "target_location": "table"}),
        ("place it onto the shelf", {"action": "place", "target": "it", "target_location": "shelf"}),
        ("put the cup down on the table", {"action": "place", "target": "cup", "target_location": "table"}),
        ("set down the cup on the tray", {"action": "place", "target": "cup", "target_location": "tray"}),
        ("drop the can into the bin", {"action": "place", "target": "can", "target_location": "bin"}),
        ("put the cup on top of the table", {"action": "place", "target": "cup", "target_location": "table"}),
        ("place on the counter", {"action": "place", "target_location": "counter"}),
        ("find the keys", {"action": "detect", "target": "keys"}),
        ("look for the keys in the kitchen", {"action": "detect", "target": "keys", "target_location": "kitchen"}),
        ("search the kitchen for the remote", {"action": "detect", "target": "remote", "target_location": "kitchen"}),
        ("look at the person", {"action": "look_at", "target": "person"}),
        ("face the door", {"action": "look_at", "target": "door"}),
        ("turn to face the window", {"action": "look_at", "target": "window"}),
        (
            "drive forward 1 meter",
            {"action": "drive", "parameters": {"direction": "forward", "distance": "1 meter"}},
        ),
        (
            "move backward 30 cm",
            {"action": "drive", "parameters": {"direction": "backward", "distance": "30 cm"}},
        ),
        ("go back 2 m", {"action": "drive", "parameters": {"direction": "back", "distance": "2 m"}}),
        (
            "drive 1.5 meters forward at 0.2 m/s",
            {"action": "drive", "parameters": {"distance": "1.5 meters", "direction": "forward", "speed": "0.2 m/s"}},
        ),
        ("back up 30 cm", {"action": "drive", "parameters": {"distance": "30 cm", "direction": "backward"}}),
        ("drive straight 1 m", {"action": "drive", "parameters": {"distance": "1 m", "direction": "forward"}}),
        ("move 50cm", {"action": "drive", "parameters": {"distance": "50cm"}}),
        ("turn left 90 degrees", {"action": "turn", "parameters": {"direction": "left", "angle": "90 degrees"}}),
        ("turn right by 45°", {"action": "turn", "parameters": {"direction": "right", "angle": "45°"}}),
        (
            "rotate 90 degrees to the left",
            {"action": "turn", "parameters": {"angle": "90 degrees", "direction": "left"}},
        ),
        (
            "turn 1.57 rad counter-clockwise",
            {"action": "turn", "parameters": {"angle": "1.57 rad", "direction": "counterclockwise"}},
        ),
        ("spin clockwise 180 deg", {"action": "turn", "parameters": {"direction": "clockwise", "angle": "180 deg"}}),
        ("turn around", {"action": "turn", "parameters": {"angle": "180 degrees"}}),
        ("stop", {"action": "stop"}),
        ("halt immediately", {"action": "stop"}),
        ('say "hello there"', {"action": "say", "parameters": {"text": "hello there"}}),
        ("say: Hello, how are you?", {"action": "say", "parameters": {"text": "Hello, how are you?"}}),
        ("announce 'Dinner is ready'", {"action": "say", "parameters": {"text": "Dinner is ready"}}),
        ("tell the user 'I am done'", {"action": "say", "parameters": {"text": "I am done"}}),
        ("tell the user that the cup is here", {"action": "say", "parameters": {"text": "the cup is here"}}),
        ("wave", {"action": "gesture", "parameters": {"gesture": "wave"}}),
        ("wave at the person", {"action": "gesture", "target": "person", "parameters": {"gesture": "wave"}}),
        ("wave hello to me", {"action": "gesture", "target": "me", "parameters": {"gesture": "wave"}}),
        ("nod your head", {"action": "gesture", "parameters": {"gesture": "nod"}}),
        ("bow", {"action": "gesture", "parameters": {"gesture": "bow"}}),
        ("point at the cup", {"action": "gesture", "target": "cup", "parameters": {"gesture": "point"}}),
        ("greet the guest", {"action": "gesture", "target": "guest", "parameters": {"gesture": "wave"}}),
        ("wait 5 seconds", {"action": "wait", "parameters": {"duration": "5 seconds"}}),
        ("wait for 2 s", {"action": "wait", "parameters": {"duration": "2 s"}}),
        ("pause for 500 ms", {"action": "wait", "parameters": {"duration": "500 ms"}}),
        ("open the gripper", {"action": "open_gripper"}),
        ("release the cup", {"action": "open_gripper"}),
        ("let go", {"action": "open_gripper"}),
        ("close your hand", {"action": "close_gripper"}),
        ("move the arm to the home position", {"action": "move_arm", "target": "home"}),
        ("move arm to ready pose", {"action": "move_arm", "target": "ready"}),
        ("stow the arm", {"action": "move_arm", "target": "stow"}),
    ],
)
def test_action_patterns(clause: str, expected: dict[str, Any]) -> None:
    assert fields("1. " + clause) == expected


@pytest.mark.parametrize(
    ("clause", "duration"),
    [
        ("wait 5 s", "5 s"),
        ("wait 5s", "5s"),
        ("wait 2.5 seconds", "2.5 seconds"),
        ("wait .5 sec", ".5 sec"),
        ("wait 1 minute", "1 minute"),
        ("wait 10", "10"),
        ("wait two seconds", "2 seconds"),
        ("wait for about ten seconds", "10 seconds"),
    ],
)
def test_quantities_are_kept_as_written(clause: str, duration: str) -> None:
    assert fields("- " + clause)["parameters"] == {"duration": duration}


@pytest.mark.parametrize(
    ("clause", "angle"),
    [("turn left 90°", "90°"), ("turn left ninety degrees", "90 degrees"), ("turn left forty-five deg", "45 deg")],
)
def test_angles(clause: str, angle: str) -> None:
    assert fields("- " + clause)["parameters"]["angle"] == angle


# Refusals


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("go to (3.5, 2.0)", {"action": "navigate_to", "parameters": {"point": ["3.5", "2.0"]}}),
        ("go to 3.5, 2.0", {"action": "navigate_to", "parameters": {"point": ["3.5", "2.0"]}}),
        ("navigate to x 3.5 y 2", {"action": "navigate_to", "parameters": {"point": ["3.5", "2"]}}),
        ("Go To X=3, Y=-2", {"action": "navigate_to", "parameters": {"point": ["3", "-2"]}}),
        ("go to [1, 2, 0.5]", {"action": "navigate_to", "parameters": {"point": ["1", "2", "0.5"]}}),
        ("go to the point (1 m, 250 cm)", {"action": "navigate_to", "parameters": {"point": ["1 m", "250 cm"]}}),
        (
            "drive to coordinates 1, 2 at 0.3 m/s",
            {"action": "navigate_to", "parameters": {"point": ["1", "2"], "speed": "0.3 m/s"}},
        ),
        (
            "go to the kitchen at (2.5, 2.5)",
            {"action": "navigate_to", "target": "kitchen", "parameters": {"point": ["2.5", "2.5"]}},
        ),
        ("look at (1, 2, 1.2)", {"action": "look_at", "parameters": {"point": ["1", "2", "1.2"]}}),
        (
            "pick up the cup at (2.6, 3.1, 0.9)",
            {"action": "pick", "target": "cup", "parameters": {"point": ["2.6", "3.1", "0.9"]}},
        ),
        (
            "put it on the table at (1, 2)",
            {"action": "place", "target": "it", "target_location": "table", "parameters": {"point": ["1", "2"]}},
        ),
        ("find the apple near 1, 2", {"action": "detect", "target": "apple", "parameters": {"point": ["1", "2"]}}),
        # Not points: a speed after a name, and one number is no point.
        ("go to the kitchen at 0.5", {"action": "navigate_to", "target": "kitchen", "parameters": {"speed": "0.5"}}),
    ],
)
def test_points(clause: str, expected: dict[str, Any]) -> None:
    assert fields("1. " + clause) == expected


def test_a_point_is_not_split_at_its_comma_but_a_step_after_it_is() -> None:
    steps = read("1. go to 3.5, 2.0, then pick up the cup and go to 1, 2 and look at (0, 0)")
    assert [s.fields for s in steps] == [
        {"action": "navigate_to", "parameters": {"point": ["3.5", "2.0"]}},
        {"action": "pick", "target": "cup"},
        {"action": "navigate_to", "parameters": {"point": ["1", "2"]}},
        {"action": "look_at", "parameters": {"point": ["0", "0"]}},
    ]


@pytest.mark.parametrize("clause", ["go to (1, 2, 3, 4)", "go to (1 2)", "go to (1, two)", "go to (1, 2"])
def test_what_is_not_a_point_is_refused(clause: str) -> None:
    error = refused("1. " + clause)
    assert at(error) == (1, 4)
    assert "cannot read" in error.error.message


def test_unknown_verb_is_refused_with_did_you_mean() -> None:
    error = refused("1. go to the kitchen\n2. plce the cup on the table")
    assert at(error) == (2, 4)
    assert error.error.kind is ErrorKind.UNKNOWN_ACTION
    assert error.error.candidates[0] == "place"
    message = str(error)
    assert message.startswith("line 2, column 4: cannot read 'plce the cup on the table'")
    assert "unknown verb 'plce' (did you mean 'place'?)" in message
    assert "expected a step such as 'go to the kitchen' or 'pick up the red cup'" in message


def test_an_unknown_verb_near_an_expansion_is_refused_with_did_you_mean() -> None:
    error = refused("- Brign me the red cup")
    assert at(error) == (1, 3)
    assert "unknown verb 'brign' (did you mean 'bring'?)" in str(error)


def test_the_column_of_a_refused_clause_is_where_it_starts() -> None:
    line = "  3) go to the kitchen, then fly to the moon"
    error = refused(line)
    assert at(error) == (1, line.index("fly") + 1)
    assert "unknown verb 'fly'" in str(error)


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("put the cup down", "'put the cup on the table'"),
        ("turn left", "'turn left 90 degrees'"),
        ("wait for the user", "'wait 5 seconds'"),
        ("pick up the", "'pick up the red cup'"),
        ("open the door", "'open the gripper'"),
        ("go to the kitchen quickly", "'go to the kitchen'"),
        ("go to the kitchen or the hall carefully", "'go to the kitchen'"),
        ("drive forward a bit", "'drive forward 1 meter'"),
        ("pick up the cup (the red one)", "'pick up the red cup'"),
    ],
)
def test_a_known_verb_in_an_unreadable_clause_is_refused_with_examples(clause: str, expected: str) -> None:
    error = refused("1. " + clause)
    assert at(error) == (1, 4)
    assert f"cannot read {clause!r}: expected a step such as" in str(error)
    assert expected in str(error)
    assert error.error.kind is ErrorKind.INVALID_REQUEST


# Expansions: one clause, the several steps a person means


def expansion(text: str) -> tuple[TextStep, list[dict[str, Any]]]:
    """The one group `text` reads as, and its steps' fields."""
    steps = read(text)
    assert len(steps) == 1 and steps[0].fields == {}, steps
    return steps[0], [s.fields for s in steps[0].substeps]


def pick_and_place(target: str, location: str, where: str | None = None) -> list[dict[str, Any]]:
    pick = {"action": "pick", "target": target, **({"target_location": where} if where else {})}
    return [pick, {"action": "place", "target": target, "target_location": location}]


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("bring me the red cup", pick_and_place("red cup", "me")),
        ("Bring me the red cup, please", pick_and_place("red cup", "me")),
        ("fetch the keys", pick_and_place("keys", "me")),
        ("fetch me the keys", pick_and_place("keys", "me")),
        ("get the blue book", pick_and_place("blue book", "me")),
        ("get me the blue book", pick_and_place("blue book", "me")),
        ("hand me the mug", pick_and_place("mug", "me")),
        ("give me the mug", pick_and_place("mug", "me")),
        ("bring it to me", pick_and_place("it", "me")),
        ("bring the cup here", pick_and_place("cup", "here")),
        ("bring the red cup to the user", pick_and_place("red cup", "user")),
        ("bring the red cup to the operator", pick_and_place("red cup", "operator")),
        ("bring the cup to the kitchen table", pick_and_place("cup", "kitchen table")),
        ("take the cup to the kitchen", pick_and_place("cup", "kitchen")),
        ("carry the plate over to the sink", pick_and_place("plate", "sink")),
        ("give the remote to the operator", pick_and_place("remote", "operator")),
        ("fetch the keys from the shelf", pick_and_place("keys", "me", "shelf")),
        ("bring me the cup from the kitchen counter", pick_and_place("cup", "me", "kitchen counter")),
        ("tidy up the cup onto the shelf", pick_and_place("cup", "shelf")),
        ("tidy the book away onto the bookshelf", pick_and_place("book", "bookshelf")),
        ("put away the book on the bookshelf", pick_and_place("book", "bookshelf")),
        ("put the book away in the drawer", pick_and_place("book", "drawer")),
    ],
)
def test_an_expansion_is_a_group_of_the_steps_a_person_means(clause: str, expected: list[dict[str, Any]]) -> None:
    group, steps = expansion("1. " + clause)
    assert steps == expected
    assert group.description == clause.removesuffix(", please")
    assert all((s.line, s.column) == (1, 4) for s in group.substeps)


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("go home", {"action": "navigate_to", "target": "home"}),
        ("return home", {"action": "navigate_to", "target": "home"}),
        ("go back home", {"action": "navigate_to", "target": "home"}),
        ("return to the dock", {"action": "navigate_to", "target": "dock"}),
        ("go back to the dock", {"action": "navigate_to", "target": "dock"}),
        ("dock", {"action": "navigate_to", "target": "dock"}),
        ("put it back", {"action": "place", "target": "it", "target_location": "where it was found"}),
        ("put the cup back", {"action": "place", "target": "cup", "target_location": "where it was found"}),
        ("put back the cup", {"action": "place", "target": "cup", "target_location": "where it was found"}),
        ("put it back where it was", {"action": "place", "target": "it", "target_location": "where it was found"}),
        (
            "return the mug to where it was",
            {"action": "place", "target": "mug", "target_location": "where it was found"},
        ),
        ("put it back on the shelf", {"action": "place", "target": "it", "target_location": "shelf"}),
        ("get to the kitchen", {"action": "navigate_to", "target": "kitchen"}),
        ("get back to the kitchen", {"action": "navigate_to", "target": "kitchen"}),
        ("take the cup", {"action": "pick", "target": "cup"}),
        ("take the cup from the counter", {"action": "pick", "target": "cup", "target_location": "counter"}),
    ],
)
def test_phrasings_of_one_step_stay_one_step(clause: str, expected: dict[str, Any]) -> None:
    assert fields("- " + clause) == expected


def test_an_expansion_takes_a_fallback_and_splits_like_any_step() -> None:
    go, bring = read("go to the kitchen and bring me the cup; if that fails, say sorry")
    assert go.fields == {"action": "navigate_to", "target": "kitchen"}
    assert [s.fields["action"] for s in bring.substeps] == ["pick", "place"]
    assert [s.fields for s in bring.on_failure] == [{"action": "say", "parameters": {"text": "sorry"}}]


def test_a_heading_that_names_its_sub_items_is_not_run_twice() -> None:
    (group,) = read("1. Fetch the cup:\n   - go to the kitchen\n   - pick up the cup\n   - bring it to me")
    assert group.fields == {} and group.description == "Fetch the cup:"
    assert [s.fields.get("action") for s in group.substeps] == ["navigate_to", "pick", None]
    # Over fallbacks only, the heading is the step they fall back from.
    (bring,) = read("1. Bring me the cup\n   - if that fails, say sorry")
    assert [s.fields["action"] for s in bring.substeps[0].substeps] == ["pick", "place"]


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        ("tidy up the cup", "tidy up needs a place to put cup: say 'tidy up cup onto the shelf'"),
        ("tidy up the cup carefully", "tidy up needs a place to put cup"),
        ("put the book away", "putting away needs a place to put book"),
        ("bring me the cup and the plate", "one thing at a time"),
        ("fetch", "expected a step such as 'bring me the red cup'"),
        ("bring me", "say what to bring, e.g. 'bring me the red cup'"),
        ("bring the", "expected a step such as"),
    ],
)
def test_an_expansion_never_invents_what_the_plan_did_not_name(clause: str, expected: str) -> None:
    error = refused("- " + clause)
    assert at(error) == (1, 3)
    assert expected in str(error)


# Hints: words at the end of a clause that the robot takes as hints, not commands


@pytest.mark.parametrize(
    ("clause", "expected"),
    [
        (
            "go to the kitchen carefully",
            {"action": "navigate_to", "target": "kitchen", "parameters": {"manner": "carefully"}},
        ),
        (
            "go to the kitchen, slowly",
            {"action": "navigate_to", "target": "kitchen", "parameters": {"manner": "slowly"}},
        ),
        (
            "go to the kitchen at 0.5 m/s gently",
            {"action": "navigate_to", "target": "kitchen", "parameters": {"speed": "0.5 m/s", "manner": "gently"}},
        ),
        (
            "drive forward 1 m with care",
            {"action": "drive", "parameters": {"direction": "forward", "distance": "1 m", "manner": "carefully"}},
        ),
        (
            "pick up the cup with a pinch grasp",
            {"action": "pick", "target": "cup", "parameters": {"approach": "pinch"}},
        ),
        ("grasp the mug using a power grip", {"action": "pick", "target": "mug", "parameters": {"approach": "power"}}),
        ("pick up the cup with a top grasp", {"action": "pick", "target": "cup", "parameters": {"approach": "top"}}),
        (
            "pick up the cup from 10 cm above carefully",
            {"action": "pick", "target": "cup", "parameters": {"approach_distance": "10 cm", "manner": "carefully"}},
        ),
        (
            "put it on the shelf at a height of 5 cm",
            {"action": "place", "target": "it", "target_location": "shelf", "parameters": {"placement_height": "5 cm"}},
        ),
        # Spoken words are never read as hints.
        ("say drive carefully", {"action": "say", "parameters": {"text": "drive carefully"}}),
    ],
)
def test_hints_at_the_end_of_a_clause_become_parameters(clause: str, expected: dict[str, Any]) -> None:
    assert fields("- " + clause) == expected


def test_a_hint_goes_to_every_step_of_an_expansion() -> None:
    _, steps = expansion("- bring me the cup gently")
    assert [s["parameters"] for s in steps] == [{"manner": "gently"}, {"manner": "gently"}]


@pytest.mark.parametrize(
    "clause",
    [
        "go to the kitchen quickly",
        "go to the kitchen fast",
        "go to the kitchen or the hall",
        "carefully",
        "go carefully",
    ],
)
def test_what_is_not_a_hint_is_still_refused(clause: str) -> None:
    assert "cannot read" in str(refused("- " + clause))


def test_refusal_entries_give_their_reason() -> None:
    error = refused("- bring me the cup and the plate")
    assert "one thing at a time" in str(error) and at(error) == (1, 3)


def test_long_clauses_are_cut_in_messages() -> None:
    error = refused("- fly " + "x" * 500)
    assert "'fly xxxx" in str(error) and "...'" in str(error)
    assert len(str(error)) < 1000


def test_odd_characters_are_read_or_refused_never_crash() -> None:
    assert fields("- say \ud800 h\u0130 \x00") == {"action": "say", "parameters": {"text": "\ud800 h\u0130 \x00"}}
    assert fields("- pick up the \u0130stanbul mug")["target"] == "i\u0307stanbul mug"
    assert refused("- \u0130 \x1b go").error.line == 1


def test_empty_and_non_text_input_is_refused() -> None:
    assert "empty" in str(refused(""))
    assert "empty" in str(refused(" \n\t\n"))
    assert "string" in str(refused(b"go home"))  # type: ignore[arg-type]


def test_an_item_with_no_step_is_refused() -> None:
    error = refused("1. go home\n2. then.")
    assert at(error) == (2, 4) and "has no step" in str(error)


def test_a_clause_over_the_limit_is_refused() -> None:
    error = refused("- say " + "a" * MAX_CLAUSE_CHARS)
    assert at(error) == (1, 3) and f"at most {MAX_CLAUSE_CHARS}" in str(error)


# Limits


def test_too_many_items_are_refused_at_the_first_one_over() -> None:
    error = refused("".join(f"{i}. stop\n" for i in range(1, 8)), max_steps=5)
    assert at(error) == (6, 4) and "more than 5 steps" in str(error)


def test_clauses_groups_and_fallbacks_count_as_steps() -> None:
    assert len(read("- stop and wave\n- go home", max_steps=3)) == 3
    error = refused("- stop and wave\n- go home\n- nod", max_steps=3)
    assert at(error) == (3, 3)
    error = refused("- Tidy up:\n  - stop\n  - wave", max_steps=2)
    assert at(error) == (3, 5)
    error = refused("- stop; if that fails, wave", max_steps=1)
    assert at(error) == (1, 24)


def test_nesting_deeper_than_max_depth_is_refused() -> None:
    nested = "".join("  " * level + f"- level {level}:\n" for level in range(4)) + "        - stop"
    assert read(nested, max_depth=4)[0].substeps[0].substeps[0].substeps[0].substeps[0].fields == {"action": "stop"}
    error = refused(nested, max_depth=3)
    assert at(error) == (5, 11) and "at most 3 levels" in str(error)


def test_fallback_chains_count_as_nesting() -> None:
    text = "- stop" + "; if that fails, wave" * 3
    assert read(text, max_depth=3)[0].on_failure[0].on_failure[0].on_failure[0].fields["action"] == "gesture"
    error = refused(text, max_depth=2)
    assert error.error.line == 1 and "at most 2 levels" in str(error)


# Fallbacks


def test_if_that_fails_attaches_to_the_step_before_in_the_same_item() -> None:
    (pick, home) = read("1. pick up the cup; if that fails, say sorry and wave; then go home")
    assert pick.fields["action"] == "pick"
    assert [s.fields["action"] for s in pick.on_failure] == ["say", "gesture"]
    assert pick.on_failure[0].column == 1 + len("1. pick up the cup; if that fails, ")
    assert pick.on_failure[0].description == "say sorry"
    assert home.fields["target"] == "home"


@pytest.mark.parametrize("marker", ["If that fails,", "if it fails", "Otherwise,", "If not,", "otherwise:"])
def test_fallback_markers_on_the_next_item(marker: str) -> None:
    steps = read(f"1. pick up the cup\n2. {marker} say sorry\n3. go home")
    assert [s.fields["action"] for s in steps] == ["pick", "navigate_to"]
    (fallback,) = steps[0].on_failure
    assert fallback.fields == {"action": "say", "parameters": {"text": "sorry"}}
    assert (fallback.line, fallback.column) == (2, 4 + len(marker) + 1)


def test_if_that_fails_then_attaches_to_the_step() -> None:
    (pick,) = read("- pick up the cup, if that fails then find the cup")
    assert pick.on_failure[0].fields["action"] == "detect"


def test_chained_fallbacks_nest() -> None:
    (cup,) = read("- pick up the cup; if that fails, pick up the mug; if that fails, say sorry")
    (mug,) = cup.on_failure
    assert mug.fields["target"] == "mug"
    assert mug.on_failure[0].fields["action"] == "say"


def test_a_fallback_heading_makes_its_sub_items_the_fallback() -> None:
    pick, home = read("1. pick up the cup\n2. If that fails:\n   - say sorry\n   - wave\n3. go home")
    assert [s.fields["action"] for s in pick.on_failure] == ["say", "gesture"]
    assert home.fields["action"] == "navigate_to"


def test_a_fallback_sub_item_belongs_to_the_readable_heading() -> None:
    (group,) = read("1. pick up the cup\n   - if that fails, find the cup")
    (pick,) = group.substeps
    assert pick.on_failure[0].fields["action"] == "detect"


def test_a_fallback_after_a_group_belongs_to_the_group() -> None:
    (group,) = read("1. Fetch:\n   - go to the kitchen\n   - pick up the cup\n2. otherwise say sorry")
    assert group.fields == {} and group.on_failure[0].fields["action"] == "say"


def test_a_fallback_with_nothing_before_it_is_refused() -> None:
    error = refused("1. if that fails, go home")
    assert at(error) == (1, 19) and "no step before it" in str(error)
    error = refused("1. Fetch:\n   - otherwise go home")
    assert at(error) == (2, 16)


def test_a_bare_fallback_marker_is_refused() -> None:
    error = refused("1. go home\n2. if that fails\n3. stop")
    assert at(error) == (2, 4) and "not followed by a step" in str(error)


# Hostile input


HOSTILE = {
    "long line": "1. go to " + " " * 262_000 + "x",
    "many ands": "1. pick up the cup" + " and" * 60_000,
    "deep indentation": "".join(" " * i + "- a\n" for i in range(700)),
    "many items": "- stop\n" * 37_000,
    "prose": "x" * 262_000,
    "prose between": "1. stop\n" + "blah\n" * 50_000 + "2. stop",
    "sentences": "stop. " * 43_000,
    "long clause of articles": "1. put " + "a " * 540 + "on",
    "long clause of prepositions": "1. find " + "a in " * 210 + "(",
    "long item of separators": "1. " + "pick up a and " * 280,
    "quotes": "1. say " + '"a' * 1_900,
    "fallback chain": "1. stop" + "; if that fails, stop" * 180,
    "nested fallbacks": "1. stop\n" + "2. if that fails, stop\n" * 10_000,
    "control characters": "1. go to \x00\x0b\x1b the kitchen\u2028" * 5_000,
}


@pytest.mark.parametrize("name", list(HOSTILE))
def test_hostile_input_is_refused_promptly(name: str) -> None:
    text = HOSTILE[name][: 256 * 1024]
    started = time.thread_time()  # the work done, whatever the scheduler does (make test runs these at low priority)
    with pytest.raises(ParseError):
        read_text(text, GRAMMAR)
    assert time.thread_time() - started < 1.0


WORDS = [
    "go", "to", "the", "kitchen", "pick", "up", "cup", "and", "then", "if", "that", "fails", "otherwise",
    "say", "'hi", '"', "turn", "left", "90", "degrees", "at", "0.5", "m/s", "wait", "5", "s", "1.", "-", "a)",
    "**", "Step", "2:", ",", ";", ".", ":", "\n", "\n  ", "\n    ", "\t", "(", ")", "please", "put", "on", "it",
]  # fmt: skip


@settings(max_examples=400, deadline=None)
@given(
    st.one_of(st.lists(st.sampled_from(WORDS), max_size=60).map(" ".join), st.text(max_size=300)),
    st.integers(0, 4),
    st.integers(0, 12),
)
def test_any_text_gives_steps_or_a_parse_error(text: str, max_depth: int, max_steps: int) -> None:
    try:
        steps, warnings = read_text(text, GRAMMAR, max_depth=max_depth, max_steps=max_steps)
    except ParseError as exc:
        assert exc.error.line is None or exc.error.line >= 1
        return
    assert all(isinstance(s, TextStep) for s in steps) and all(isinstance(w, str) for w in warnings)


# The grammar file


def test_the_bundled_grammar_is_the_default() -> None:
    assert default_grammar_path().is_file()
    assert isinstance(load_grammar(default_grammar_path()), TextGrammar)


def test_the_grammar_emits_only_parameters_and_choices_the_vocabulary_knows() -> None:
    vocabulary = yaml.safe_load((default_grammar_path().parent / "vocabulary.yaml").read_text())
    units = vocabulary["units"]
    hints = vocabulary["hints"]
    hint_params = {*hints["manner"]["params"], *(n for group in hints["ignored"] for n in group["params"])}
    for pattern in GRAMMAR.hints:
        for slot in pattern.slots:
            takers = [a for a in vocabulary["actions"].values() if slot.name in a.get("params", {})]
            assert slot.name in hint_params or takers, slot.name
            for value in slot.choices.values():
                if slot.name == "manner":
                    assert value.replace(" ", "_") in hints["manner"]["words"], value
                else:  # a grasp type, or a choice the parameter takes
                    assert (
                        any(value in a["params"][slot.name]["choices"] for a in takers)
                        or value in hints["grasp"]["types"]
                    ), value
            if slot.kind == "quantity":
                assert set(GRAMMAR.spec.quantities[slot.name]) <= set(units["m"]), slot.name
    for verb_patterns in GRAMMAR.patterns.values():
        for pattern in verb_patterns:
            if not pattern.action:  # an expansion: its steps' actions and parameters must be known
                for template in pattern.steps:
                    params = vocabulary["actions"][template.action.value].get("params", {})
                    assert set(template.set) <= set(params), template
                continue
            params = vocabulary["actions"][pattern.action].get("params", {})
            for slot in pattern.slots:
                if slot.name in ("target", "target_location"):
                    continue
                if slot.kind == "point":  # read like coordinates in JSON, by the actions that take them
                    assert slot.name in vocabulary["coordinates"]["points"], (pattern.action, slot.name)
                    assert pattern.action in vocabulary["coordinates"]["actions"], pattern.action
                    continue
                assert slot.name in params, (pattern.action, slot.name)
                for value in slot.choices.values():
                    assert value in params[slot.name]["choices"], (pattern.action, value)
                if slot.kind == "quantity":
                    for unit in GRAMMAR.spec.quantities[slot.name]:
                        known = {w for a in vocabulary["actions"].values() for p, s in a.get("params", {}).items()
                                 if p == slot.name and "unit" in s for w in units[s["unit"]]}  # fmt: skip
                        assert unit.lower() in known, (slot.name, unit)
            for name, value in pattern.fixed:
                if name not in ("target", "location"):
                    assert name in params, (pattern.action, name)
                    assert value in params[name].get("choices", [value]), (pattern.action, value)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "grammar.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("actions: {stop: {examples: [stop], patterns: ['stop {targt}']}}", "actions.stop.patterns[0]"),
        ("actions: {stop: {examples: [stop], patterns: ['{target} stop']}}", "must start with a word"),
        ("actions: {stop: {examples: [stop], patterns: ['stop [now']}}", "expected ']'"),
        ("actions: {stop: {examples: [stop], patterns: ['stop {target} {target}']}}", "used twice"),
        ("actions: {stop: {examples: [stop], patterns: ['stop (now|)']}}", "empty alternative"),
        ("actions: {stop: {examples: [stop], patterns: ['stop (now|']}}", "expected ')'"),
        ("actions: {stop: {examples: [stop], patterns: ['stop (a b)|c']}}", "'|' must stand between two words"),
        ("actions: {stop: {examples: [stop], patterns: ['stop {x']}}", "unbalanced"),
        (
            "actions: {stop: {examples: [stop], patterns: [{pattern: 'stop {target}', set: {target: x}}]}}",
            "also a slot",
        ),
        ("actions: {stop: {examples: [stop], patterns: [stop]}}\nverbs: []", "unknown field"),
        ("actions: {fly: {examples: [fly], patterns: [fly]}}", "fly"),
        ("point_quantity: length\nactions: {stop: {examples: [stop], patterns: [stop]}}", "point_quantity"),
        ("quantities: {point: [m]}\nactions: {stop: {examples: [stop], patterns: [stop]}}", "quantities.point"),
        ("actions: {stop: {examples: [], patterns: [stop]}}", "examples"),
        ("actions: [", "not valid YAML"),
        (
            "actions: {stop: {examples: [stop], patterns: [stop]}}\nexpansions: {x: {examples: [x], patterns: "
            "[{pattern: 'fetch {target}', steps: [{action: pick, target: '{location}'}]}]}}",
            "'{location}' is not a slot of the pattern",
        ),
        (
            "actions: {stop: {examples: [stop], patterns: [stop]}}\nexpansions: {x: {examples: [x], patterns: "
            "[{pattern: 'fetch {target}'}]}}",
            "either `steps` or a `reason`",
        ),
        (
            "actions: {stop: {examples: [stop], patterns: [stop]}}\nexpansions: {x: {examples: [x], patterns: "
            "[{pattern: 'fetch {target} {text}', steps: [{action: stop}]}]}}",
            "only have {target}, {location} and {_} slots",
        ),
        ("actions: {stop: {examples: [stop], patterns: [stop]}}\nhints: ['with {target}']", "hints[0]"),
        (
            "actions: {stop: {examples: [stop], patterns: [stop]}}\nhints: [{pattern: carefully, set: {target: x}}]",
            "never a target",
        ),
    ],
)
def test_a_bad_grammar_file_names_the_file_and_the_entry(tmp_path: Path, text: str, problem: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(VocabularyError) as caught:
        load_grammar(path)
    assert str(path) in str(caught.value)
    assert problem in str(caught.value)


def test_a_missing_grammar_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(VocabularyError, match="cannot read grammar file"):
        load_grammar(tmp_path / "missing.yaml")


def test_a_small_grammar_reads_only_its_own_words(tmp_path: Path) -> None:
    grammar = load_grammar(
        write(
            tmp_path,
            "fillers: [kindly]\nactions:\n  stop: {examples: [halt], patterns: [halt]}\n"
            "  say: {examples: [shout hi], patterns: ['shout {text}']}\n",
        )
    )
    steps, _ = read_text("- kindly halt and shout Hi", grammar)
    assert [s.fields for s in steps] == [{"action": "stop"}, {"action": "say", "parameters": {"text": "Hi"}}]
    with pytest.raises(ParseError, match="unknown verb 'stop'"):
        read_text("- stop", grammar)
