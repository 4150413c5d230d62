"""Editing a YAML file's text in place: new values spliced in at the node marks PyYAML gives.

A tool that writes into an engineer's file (``supervisor calibrate`` into an I/O map) must
leave every comment, blank line, quote style and key order as it was. Dumping the data again
loses all of that, so :class:`YamlText` composes the document's node graph (each node knows
where its text starts and ends, and whether it is written in flow ``{...}`` or block style)
and replaces only the text of the scalars concerned, or inserts one new entry:

* :meth:`YamlText.set_scalars`: set scalar values in the mapping at a document path; missing
  keys are added at the mapping's indent (block style) or inside its braces (flow style);
* :meth:`YamlText.add_mapping`: add ``key: {a: 1, b: 2}`` to a mapping, after a given key
  (on the line after that key's value, or just after it in a flow mapping);
* :meth:`YamlText.set_scalar`: replace one scalar (e.g. a ``null``) by new text, keeping
  its anchor.

Paths are mapping keys and list indexes, outermost first; only keys written in the mapping
itself are followed (not keys merged in with ``<<``). Deciding what may be edited (anchors
shared with other places, merge keys) is the caller's business: :meth:`YamlText.shared`
tells whether a node is reachable from more than one place.

Also here: :func:`yaml_float`, :func:`yaml_scalar` and :func:`yaml_comment`, to write new
values and comments that read back exactly.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from decimal import Decimal

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from supervisor.config.text import newline_of
from supervisor.config.yamlpos import Path_, load_yaml_text
from supervisor.core.errors import ConfigError

__all__ = [
    "YamlText",
    "flow_mapping",
    "yaml_comment",
    "yaml_float",
    "yaml_scalar",
]


# --------------------------------------------------------------------------------------------
# Writing scalars

_NOT_PRINTABLE = re.compile(
    "[^\x09\x0a\x0d\x20-\x7e\xa0-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]|[\u2028\u2029\ufeff]"
)


def _escape_nonprintable(text: str) -> str:
    return _NOT_PRINTABLE.sub(lambda m: f"\\u{ord(m.group()):04x}", text)


def yaml_float(value: float) -> str:
    """A float as a YAML 1.1 float literal PyYAML reads back exactly (``1e-05`` is a string
    to PyYAML; this writes ``0.00001``)."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{value!r} is not a finite number")
    text = repr(v)
    if "e" in text or "E" in text:
        text = format(Decimal(text), "f")
    if "." not in text:
        text += ".0"
    return text


def _round_trips(snippet: str, expected: object) -> bool:
    try:
        return bool(yaml.safe_load(snippet) == expected)
    except yaml.YAMLError:
        return False


def yaml_scalar(value: str | float | bool | None, *, key: bool = False) -> str:
    """``value`` as a block-context YAML scalar: plain when that reads back as the same
    string, double-quoted otherwise (``"true"``, ``"20:00"``, ``"a: b"``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return yaml_float(value)
    text = str(value)
    if (
        text
        and text == text.strip()
        and not _NOT_PRINTABLE.search(text)
        and "\t" not in text
        and "\n" not in text
        and "\r" not in text
    ):
        snippet, expected = (f"{text}: x\n", {text: "x"}) if key else (f"k: {text}\n", {"k": text})
        if _round_trips(snippet, expected):
            return text
    return _escape_nonprintable(json.dumps(text, ensure_ascii=False))


def yaml_comment(text: str) -> str:
    """Text safe inside a YAML comment (one line, printable)."""
    return _escape_nonprintable(text.replace("\r", " ").replace("\n", " "))


def flow_mapping(values: Mapping[str, str]) -> str:
    """``{a: 1, b: 2}`` from keys and the YAML text of their values."""
    return "{" + ", ".join(f"{k}: {v}" for k, v in values.items()) + "}"


# --------------------------------------------------------------------------------------------
# Editing

# Anchors and tags written before a scalar (``&cal !!float 1.0``): kept when it is replaced.
_PROPERTIES = re.compile(r"(?:[&!][^\s,\[\]{}]*[ \t]+)*")
_BREAK = re.compile(r"\r\n|\r|\n")


def _entry(mapping: MappingNode, key: str) -> tuple[Node, Node] | None:
    for k, v in mapping.value:
        if isinstance(k, ScalarNode) and k.value == key:
            return k, v
    return None


def _ref_counts(root: Node) -> dict[int, int]:
    """How many places refer to each node (more than one: an anchor used by an alias)."""
    counts: dict[int, int] = {}
    stack = [root]
    while stack:
        node = stack.pop()
        counts[id(node)] = counts.get(id(node), 0) + 1
        if counts[id(node)] > 1:
            continue
        if isinstance(node, MappingNode):
            for k, v in node.value:
                stack += [k, v]
        elif isinstance(node, SequenceNode):
            stack += list(node.value)
    return counts


class YamlText:
    """One YAML document's text, its composed nodes, and the edits to splice into it.

    The text is loaded like every configuration file first (:func:`load_yaml_text`), so a
    document that does not load is refused with the usual ConfigError (file:line:col).
    Edits refer to the original text; :meth:`edited` applies them all at once.
    """

    def __init__(self, text: str, file: str = "<string>") -> None:
        load_yaml_text(text, file)
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        assert root is not None  # load_yaml_text refuses an empty document
        self.text = text
        self.file = file
        self.root: Node = root
        self.newline = newline_of(text)
        self._refs = _ref_counts(root)
        self._splices: list[tuple[int, int, str]] = []  # (start, end, replacement)

    # --- looking ------------------------------------------------------------------------
    def error(self, node: Node, message: str) -> ConfigError:
        """A ConfigError at ``node``'s position in this file."""
        return ConfigError(message, self.file, node.start_mark.line + 1, node.start_mark.column + 1)

    def shared(self, node: Node) -> bool:
        """Whether ``node`` is reachable from more than one place (an anchor with aliases)."""
        return self._refs.get(id(node), 0) > 1

    def node(self, path: Path_) -> Node | None:
        """The node at ``path``, or None."""
        node: Node | None = self.root
        for element in path:
            node = self._child(node, element)
        return node

    def key(self, path: Path_) -> Node | None:
        """The KEY node of the mapping entry at ``path`` (not empty), or None."""
        parent = self.node(path[:-1])
        if not isinstance(parent, MappingNode) or not isinstance(path[-1], str):
            return None
        entry = _entry(parent, path[-1])
        return entry[0] if entry is not None else None

    @staticmethod
    def _child(node: Node | None, element: str | int) -> Node | None:
        if isinstance(node, MappingNode) and isinstance(element, str):
            entry = _entry(node, element)
            return entry[1] if entry is not None else None
        if isinstance(node, SequenceNode) and isinstance(element, int):
            items: list[Node] = node.value
            return items[element] if 0 <= element < len(items) else None
        return None

    def _mapping(self, path: Path_) -> MappingNode:
        node = self.node(path)
        if not isinstance(node, MappingNode):
            raise KeyError(f"no mapping at {path!r}")
        return node

    # --- editing ------------------------------------------------------------------------
    def set_scalar(self, path: Path_, value: str) -> None:
        """Replace the scalar at ``path`` by ``value`` (YAML text), keeping its anchor/tag.

        An empty value (``key:`` with nothing after it) gets a space after the colon.
        """
        node = self.node(path)
        if not isinstance(node, ScalarNode):
            raise KeyError(f"no scalar at {path!r}")
        start = self._value_start(node)
        end: int = node.end_mark.index
        if start == end and self.text[start - 1 : start] == ":":
            value = " " + value
        self._splice(start, end, value)

    def set_scalars(self, path: Path_, values: Mapping[str, str]) -> None:
        """Set ``values`` (key → YAML text) in the mapping at ``path``.

        Existing keys get their scalar's text replaced (comments after it stay); missing ones
        are added: in a block mapping one line each after its last entry, at the indent of its
        first key; in a flow mapping before the closing brace. Refuses (ConfigError at the
        value) a key whose value is not a scalar or is shared through an anchor.
        """
        mapping = self._mapping(path)
        missing: dict[str, str] = {}
        for key, value in values.items():
            entry = _entry(mapping, key)
            if entry is None:
                missing[key] = value
                continue
            node = entry[1]
            if not isinstance(node, ScalarNode) or self.shared(node):
                raise self.error(node, f"{key} is not a plain scalar; edit by hand")
            self._splice(self._value_start(node), node.end_mark.index, value)
        if missing and mapping.flow_style:
            self._add_in_braces(mapping, missing)
        elif missing:
            first_key: Node = mapping.value[0][0]
            last_value: Node = mapping.value[-1][1]
            self._add_lines(last_value.end_mark.index, first_key.start_mark.column, missing)

    def add_mapping(self, path: Path_, key: str, values: Mapping[str, str], *, after: str) -> None:
        """Add ``key: {values}`` to the mapping at ``path``, after its entry ``after``.

        Block style: on a new line after the line of ``after``'s value, at ``after``'s indent.
        Flow style: right after ``after``'s value (``{a: 1, key: {...}, b: 2}``).
        """
        mapping = self._mapping(path)
        entry = _entry(mapping, after)
        if entry is None:
            raise KeyError(f"no key {after!r} at {path!r}")
        after_key, after_value = entry
        if mapping.flow_style:
            at: int = after_value.end_mark.index
            self._splice(at, at, f", {key}: {flow_mapping(values)}")
        else:
            line = {key: flow_mapping(values)}
            self._add_lines(after_value.end_mark.index, after_key.start_mark.column, line)

    def edited(self) -> str:
        """The text with every edit applied."""
        text = self.text
        for start, end, new in sorted(self._splices, reverse=True):
            text = text[:start] + new + text[end:]
        return text

    # --- helpers ------------------------------------------------------------------------
    def _splice(self, start: int, end: int, text: str) -> None:
        self._splices.append((start, end, text))

    def _value_start(self, node: Node) -> int:
        """Where a scalar's own text starts (after an anchor or tag, which are kept)."""
        index: int = node.start_mark.index
        m = _PROPERTIES.match(self.text, index)
        return m.end() if m else index

    def _add_in_braces(self, mapping: MappingNode, values: Mapping[str, str]) -> None:
        if mapping.value:
            last: int = mapping.value[-1][1].end_mark.index
            self._splice(last, last, "".join(f", {k}: {v}" for k, v in values.items()))
        else:
            brace = self.text.index("{", mapping.start_mark.index) + 1
            self._splice(brace, brace, ", ".join(f"{k}: {v}" for k, v in values.items()))

    def _add_lines(self, index: int, indent: int, values: Mapping[str, str]) -> None:
        """``key: value`` lines at ``indent`` after the line holding ``index``."""
        m = _BREAK.search(self.text, index)
        at = m.end() if m else len(self.text)
        lead = self.newline if m is None else ""  # the last line had no line break
        pad = " " * indent
        lines = "".join(f"{pad}{k}: {v}{self.newline}" for k, v in values.items())
        self._splice(at, at, lead + lines)
