"""YAML plans: safe loading only, bounded so that anchors and aliases cannot blow up."""

from __future__ import annotations

from typing import Any

import yaml

from services.parser.errors import ParseError

# libyaml when the wheel has it: the same safe loader, ten times faster.
_Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class AliasBomb(ParseError):
    """Anchors and aliases that expand too far or refer to themselves: an attack, never a typo."""


def _where(mark: Any) -> str:
    return f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "an unknown place"


def load_yaml(text: str, *, max_nodes: int, max_depth: int) -> Any:
    """The value of a single YAML document, or ParseError naming the line.

    The node graph is composed first and measured with every alias expanded (without expanding
    it): more than `max_nodes` nodes, nesting deeper than `max_depth`, an alias that contains
    itself or a key given twice is refused before any Python object is built.
    """
    _check_depth(text, max_depth)  # before composing: libyaml's composer recurses in C
    try:
        node = yaml.compose(text, Loader=_Loader)
    except yaml.MarkedYAMLError as exc:
        raise ParseError(f"malformed YAML: {exc.problem} at {_where(exc.problem_mark)}") from None
    except yaml.YAMLError as exc:
        raise ParseError(f"malformed YAML: {exc}") from None
    except RecursionError:
        raise ParseError(f"YAML is nested more than {max_depth} levels deep") from None
    if node is None:
        raise ParseError("the YAML document is empty")
    _Measure(max_nodes, max_depth).size(node, 0)
    try:
        return _Loader("").construct_document(node)
    except yaml.YAMLError as exc:
        raise ParseError(f"YAML could not be read: {exc}") from None
    except (ValueError, OverflowError) as exc:  # a 5000-digit integer, for one
        raise ParseError(f"YAML could not be read: {str(exc)[:200]}") from None


_OPEN = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
_CLOSE = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


def _check_depth(text: str, max_depth: int) -> None:
    """Refuse nesting deeper than `max_depth` from the event stream, which is read without recursion."""
    depth = 0
    try:
        for event in yaml.parse(text, Loader=_Loader):
            if isinstance(event, _OPEN):
                depth += 1
                if depth > max_depth:
                    raise ParseError(
                        f"YAML is nested more than {max_depth} levels deep at {_where(event.start_mark)}; "
                        "a plan needs only a few levels"
                    )
            elif isinstance(event, _CLOSE):
                depth -= 1
    except yaml.MarkedYAMLError as exc:
        raise ParseError(f"malformed YAML: {exc.problem} at {_where(exc.problem_mark)}") from None
    except yaml.YAMLError as exc:
        raise ParseError(f"malformed YAML: {exc}") from None


class _Measure:
    def __init__(self, max_nodes: int, max_depth: int) -> None:
        self.max_nodes = max_nodes
        self.max_depth = max_depth
        self.sizes: dict[int, int] = {}
        self.open: set[int] = set()
        self.aliased = False

    def size(self, node: yaml.Node, depth: int) -> int:
        """Nodes under `node` with aliases expanded; memoised per node, so a bomb costs its size in nodes."""
        if depth > self.max_depth:
            raise ParseError(f"YAML is nested more than {self.max_depth} levels deep at {_where(node.start_mark)}")
        key = id(node)
        if key in self.sizes:
            count = self.sizes[key]
            self.aliased = True
        elif key in self.open:
            raise AliasBomb(f"a YAML alias at {_where(node.start_mark)} refers to a node that contains it")
        else:
            self.open.add(key)
            count = 1 + self._children(node, depth)
            self.open.discard(key)
            self.sizes[key] = count
        if count > self.max_nodes:
            if self.aliased:
                raise AliasBomb(
                    f"YAML anchors and aliases expand to more than {self.max_nodes} nodes "
                    f"(at {_where(node.start_mark)}); a plan needs far fewer: write it out without aliases"
                )
            raise ParseError(f"the YAML has more than {self.max_nodes} nodes; a plan needs far fewer")
        return count

    def _children(self, node: yaml.Node, depth: int) -> int:
        if isinstance(node, yaml.SequenceNode):
            return sum(self.size(child, depth + 1) for child in node.value)
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            count = 0
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    if k.value in seen:
                        raise ParseError(f"the key {k.value[:60]!r} appears twice at {_where(k.start_mark)}")
                    seen.add(k.value)
                count += self.size(k, depth + 1) + self.size(v, depth + 1)
            return count
        return 0
