"""YAML loading that remembers where every node came from, and pydantic errors mapped to it.

``load_yaml`` / ``load_yaml_text`` compose PyYAML's node graph with the *safe* resolver and
build plain Python data from it themselves (dict, list, str, int, float, bool, None), so that:

* every mapping key and every value keeps its 1-based ``line:col`` (:class:`Positions`);
* duplicate keys are errors instead of "last one wins";
* YAML 1.1 timestamps stay strings (no ``datetime`` surprises), ``!!binary``/``!!set``/
  ``!!python/...`` and custom tags are refused, and so are the YAML 1.1 numbers nobody
  means (``010`` octal, ``1:30`` base 60) and strings with a lone surrogate;
* aliases and merge keys are counted as they expand (README "Input limits");
* every failure is a :class:`~supervisor.core.errors.ConfigError` naming file, line and column.

``validate`` runs a pydantic model over the data and turns every validation error into a
``ConfigError`` at the right place (the key for unknown keys, the parent mapping for missing
keys, the value otherwise), all collected in one :class:`~supervisor.core.errors.ConfigErrors`.
"""

from __future__ import annotations

import difflib
import re
import time
import types
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

import pydantic
import yaml
from pydantic_core import ErrorDetails
from yaml.constructor import SafeConstructor
from yaml.error import MarkedYAMLError
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode
from yaml.reader import ReaderError

from supervisor.config.limits import (
    MAX_YAML_BYTES,
    MAX_YAML_TEXT_CHARS,
    MAX_YAML_VALUES,
    TooLarge,
    read_limited,
)
from supervisor.config.limits import size_text as _size_text
from supervisor.config.text import decode_yaml, line_col
from supervisor.core.errors import ConfigError, ConfigErrors

__all__ = [
    "Mark",
    "Path_",
    "Positions",
    "format_validation_error",
    "load_yaml",
    "load_yaml_text",
    "validate",
]

Path_ = tuple[str | int, ...]
"""A location in the document: mapping keys and list indexes, outermost first."""

M = TypeVar("M", bound=pydantic.BaseModel)

_YAML_TAG = "tag:yaml.org,2002:"
_STR = _YAML_TAG + "str"
_INT = _YAML_TAG + "int"
_FLOAT = _YAML_TAG + "float"
_BOOL = _YAML_TAG + "bool"
_NULL = _YAML_TAG + "null"
_TIMESTAMP = _YAML_TAG + "timestamp"
_VALUE = _YAML_TAG + "value"  # the YAML 1.1 "=" scalar; SafeLoader itself cannot construct it
_MERGE = _YAML_TAG + "merge"
_SEQ = _YAML_TAG + "seq"
_MAP = _YAML_TAG + "map"

_PLAIN_DATA = "only plain data is allowed: mappings, lists, strings, numbers, booleans, null"


@dataclass(frozen=True)
class Mark:
    """A 1-based position in the source text."""

    line: int
    col: int

    def __str__(self) -> str:
        return f"{self.line}:{self.col}"


def _mark(node: Node) -> Mark:
    # PyYAML marks are 0-based.
    return Mark(node.start_mark.line + 1, node.start_mark.column + 1)


def _line_col_of(node: Node) -> tuple[int, int]:
    m = _mark(node)
    return m.line, m.col


_Entry = tuple[Node, Node]  # (key node, value node)


class Positions:
    """Where every node of a loaded document starts.

    Lookups walk the composed node graph, so anchors/aliases cost nothing (an aliased node
    reports the position where its anchor was defined) and merge keys (``<<: *base``) resolve
    to the position of the merged-in key.
    """

    def __init__(
        self,
        root: Node | None = None,
        mappings: Mapping[int, Mapping[Hashable, _Entry]] | None = None,
    ) -> None:
        self._root = root
        # id(MappingNode) -> constructed key -> (key node, value node), merge keys included.
        self._mappings: Mapping[int, Mapping[Hashable, _Entry]] = mappings or {}

    def _child(self, node: Node | None, element: str | int) -> _Entry | None:
        if isinstance(node, MappingNode):
            index = self._mappings.get(id(node), {})
            try:
                return index.get(element)
            except TypeError:  # pragma: no cover - Path_ elements are always hashable
                return None
        if (
            isinstance(node, SequenceNode)
            and isinstance(element, int)
            and not isinstance(element, bool)
            and 0 <= element < len(node.value)
        ):
            item: Node = node.value[element]
            return (item, item)
        return None

    def _node(self, path: Path_) -> Node | None:
        node = self._root
        for element in path:
            entry = self._child(node, element)
            if entry is None:
                return None
            node = entry[1]
        return node

    def key(self, path: Path_) -> Mark | None:
        """Position of the mapping KEY at ``path`` (None for list items and unknown paths)."""
        if not path:
            return None
        parent = self._node(path[:-1])
        if not isinstance(parent, MappingNode):
            return None
        entry = self._child(parent, path[-1])
        return _mark(entry[0]) if entry is not None else None

    def value(self, path: Path_) -> Mark | None:
        """Position of the VALUE at ``path`` (``()`` is the whole document)."""
        node = self._node(path)
        return _mark(node) if node is not None else None

    def nearest(self, path: Path_) -> Mark:
        """Position of the deepest existing prefix of ``path`` (its value, else its key)."""
        for end in range(len(path), -1, -1):
            prefix = path[:end]
            found = self.value(prefix) or self.key(prefix)
            if found is not None:
                return found
        return Mark(1, 1)

    def __repr__(self) -> str:
        return f"Positions(root={'None' if self._root is None else type(self._root).__name__})"

    def release_gradually(self) -> None:
        """Forget the node graph, freeing it a batch of nodes at a time and letting other
        threads run in between (lookups find nothing afterwards).

        Freed at once, a megabyte document's graph (hundreds of thousands of nodes and
        marks) holds the interpreter lock for a tenth of a second or more, every thread
        stopped: a worker thread that compiled a recipe would stall the scan as it ends.
        """
        mappings, self._mappings = self._mappings, {}
        stack: list[Any] = [self._root]
        self._root = None
        freed = 0
        if isinstance(mappings, dict):
            while mappings:
                mappings.popitem()
                freed += 1
                if freed % _RELEASE_BATCH == 0:
                    time.sleep(0)  # releases the interpreter lock: the event loop's turn
        del mappings
        while stack:
            node = stack.pop()
            value = getattr(node, "value", None)
            if isinstance(value, list):
                for item in value:
                    if isinstance(item, tuple):
                        stack.extend(item)  # a mapping's (key node, value node) pairs
                    else:
                        stack.append(item)
                value.clear()  # an alias's node comes again, empty
            del node
            freed += 1
            if freed % _RELEASE_BATCH == 0:
                time.sleep(0)


_RELEASE_BATCH = 2_000
"""Nodes freed between two turns of the other threads (well under a millisecond's work)."""


# --------------------------------------------------------------------------------------------
# Reading and decoding


def load_yaml(path: str | Path) -> tuple[Any, Positions]:
    """Read ``path`` (UTF-8, BOM allowed: :func:`supervisor.config.text.decode_yaml`) and
    parse it; see :func:`load_yaml_text`. A file over ``MAX_YAML_BYTES`` is refused before
    it is read in full (``supervisor.config.limits``)."""
    file = str(path)
    return load_yaml_text(decode_yaml(read_yaml_bytes(path), file).text, file)


def read_yaml_bytes(path: str | Path) -> bytes:
    """The bytes of a recipe or an I/O map (``load_yaml``'s reading, its refusals)."""
    file = str(path)
    try:
        data = read_limited(path, MAX_YAML_BYTES, "a recipe or an I/O map")
    except FileNotFoundError as exc:
        raise ConfigError("file not found", file) from exc
    except IsADirectoryError as exc:
        raise ConfigError("is a directory, not a file", file) from exc
    except PermissionError as exc:
        raise ConfigError("cannot read file: permission denied", file) from exc
    except OSError as exc:
        raise ConfigError(f"cannot read file: {exc.strerror or exc}", file) from exc
    return data


def load_yaml_text(text: str, file: str = "<string>") -> tuple[Any, Positions]:
    """Parse one YAML document into plain data plus the position of every node.

    Raises ConfigError for syntax errors, duplicate keys, unsupported tags, recursive aliases,
    empty documents, lone surrogates, YAML 1.1 octal and base-60 numbers, a text longer than
    ``MAX_YAML_BYTES`` characters, and a document of more than ``MAX_YAML_VALUES`` values or
    ``MAX_YAML_TEXT_CHARS`` characters of text once its aliases and merge keys are expanded
    (counted while it is built: refused after at most that much work).
    """
    if text.startswith("\ufeff"):
        text = text[1:]
    if len(text) > MAX_YAML_BYTES:
        # Characters, not bytes: a text within the byte limit always passes (UTF-8 takes
        # at least one byte a character).
        raise TooLarge(
            f"text is too large: {len(text):,} characters; a recipe or an I/O map may have"
            f" at most {_size_text(MAX_YAML_BYTES)} (README: Input limits)",
            file,
        )
    try:
        root = _compose(text)
    except ConfigError:
        raise
    except ReaderError as exc:
        raise _reader_error(exc, text, file) from exc
    except yaml.YAMLError as exc:
        raise _yaml_error(exc, file) from exc
    except RecursionError as exc:
        raise ConfigError("document is nested too deeply", file, 1, 1) from exc
    if root is None:
        raise ConfigError(
            "file is empty" if not text.strip() else "file is empty (no YAML document)", file, 1, 1
        )
    builder = _Builder(file)
    try:
        data = builder.build(root)
    except RecursionError as exc:
        raise ConfigError("document is nested too deeply", file, 1, 1) from exc
    return data, Positions(root, builder.mappings)


def _compose(text: str) -> Node | None:
    loader = yaml.SafeLoader(text)
    try:
        node: Node | None = loader.get_single_node()
        return node
    finally:
        loader.dispose()


def _reader_error(exc: ReaderError, text: str, file: str) -> ConfigError:
    line, col = line_col(text, exc.position, yaml=True)
    char = exc.character
    what = f"U+{char:04X}" if isinstance(char, int) else repr(char)
    return ConfigError(f"character {what} is not allowed in YAML ({exc.reason})", file, line, col)


def _yaml_error(exc: yaml.YAMLError, file: str) -> ConfigError:
    if not isinstance(exc, MarkedYAMLError):
        return ConfigError(f"YAML error: {exc}", file)
    problem = exc.problem or exc.context or "invalid YAML"
    message = f"YAML syntax error: {problem}"
    mark = exc.problem_mark or exc.context_mark
    if exc.problem and exc.context:
        where = ""
        if exc.context_mark is not None:
            where = f" at line {exc.context_mark.line + 1}, column {exc.context_mark.column + 1}"
        if exc.problem.startswith("but "):  # "expected a single document ..., but found ..."
            message = f"YAML syntax error: {exc.context}{where}, {exc.problem}"
        else:
            message += f" ({exc.context}{where})"
    if "'\\t'" in problem:
        message += "; tabs are not allowed for indentation in YAML, use spaces"
    if mark is None:
        return ConfigError(message, file)
    return ConfigError(message, file, mark.line + 1, mark.column + 1)


# --------------------------------------------------------------------------------------------
# Node graph -> plain data


def _short_tag(tag: str) -> str:
    return "!!" + tag[len(_YAML_TAG) :] if tag.startswith(_YAML_TAG) else tag


_SURROGATE = re.compile("[\ud800-\udfff]")

_OCTAL = re.compile(r"[-+]?0[0-7_]+\Z")
_SEXAGESIMAL = re.compile(r"[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?\Z")


def _yaml11_surprise(text: str) -> str | None:
    """Why a plain number that YAML 1.1 reads unlike what it shows is refused, or None.

    YAML 1.1 (PyYAML) reads ``010`` as octal (8) and ``1:30`` as base 60 (90): ``cycles:
    010`` would run 8 cycles, ``cycles: 1:30`` 90. Nobody writes either on purpose in a
    recipe or an I/O map, so both are refused with what to write instead (docs/recipes.md
    "Recipes"). ``0x1F``, ``0b101`` and ``1_000`` say what they are and stay numbers.
    """
    if _OCTAL.match(text) and text.strip("-+_0"):
        digits = ("-" if text.startswith("-") else "") + text.lstrip("-+").lstrip("0_")
        return (
            f"the number {text} has a leading zero, which YAML 1.1 reads as octal"
            f" ({int(text.replace('_', ''), 8)}): write {digits} without the leading zero, or"
            f" quote it ('{text}') for text"
        )
    if _OCTAL.match(text):
        return None  # 00, 0_0: zero either way
    if _SEXAGESIMAL.match(text):
        return (
            f"{text} is a base-60 number in YAML 1.1 ({_sexagesimal(text):g}), not a time:"
            f" quote it ('{text}') for a time of day or text, or write the number itself"
        )
    return None


def _sexagesimal(text: str) -> float:
    sign = -1.0 if text.startswith("-") else 1.0
    value = 0.0
    for part in text.lstrip("-+").replace("_", "").split(":"):
        value = value * 60 + float(part)
    return sign * value


class _Builder:
    """Constructs plain data from a composed node graph, checking what SafeLoader does not."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.mappings: dict[int, dict[Hashable, _Entry]] = {}
        self._done: dict[int, Any] = {}
        # Values and characters of text under each built node once its aliases are
        # expanded (what a model validates, what the compiler reads); an alias adds its
        # node's again each time it is used.
        self._sizes: dict[int, tuple[int, int]] = {}
        self.values = 0
        """Values built so far, aliases and merge keys expanded (refused over the limit)."""
        self.chars = 0
        """Characters of text (keys and scalars) built so far, aliases expanded."""
        self._building: list[Node] = []
        self._active: set[int] = set()
        self._scalars = SafeConstructor()
        self._scalar_kinds: dict[str, tuple[str, Callable[[SafeConstructor, ScalarNode], Any]]] = {
            _INT: ("integer", SafeConstructor.construct_yaml_int),
            _FLOAT: ("float", SafeConstructor.construct_yaml_float),
            _BOOL: ("boolean", SafeConstructor.construct_yaml_bool),
        }

    def error(self, message: str, node: Node) -> ConfigError:
        mark = _mark(node)
        return ConfigError(message, self.file, mark.line, mark.col)

    def build(self, node: Node) -> Any:
        nid = id(node)
        if nid in self._done:  # an alias: share the value, like PyYAML
            values, chars = self._sizes[nid]
            # Located where it is used (the container being built), not at its anchor.
            self._grow(values, chars, self._building[-1] if self._building else node)
            return self._done[nid]
        if nid in self._active:
            raise self.error("recursive alias: a node cannot contain itself", node)
        start_values, start_chars = self.values, self.chars
        self._active.add(nid)
        self._building.append(node)
        try:
            if isinstance(node, ScalarNode):
                self._grow(1, len(node.value), node)
                value = self._scalar(node)
            elif isinstance(node, SequenceNode):
                if node.tag != _SEQ:
                    raise self._bad_tag(node, "a list")
                self._grow(1, 0, node)
                value = [self.build(item) for item in node.value]
            elif isinstance(node, MappingNode):
                if node.tag != _MAP:
                    raise self._bad_tag(node, "a mapping")
                self._grow(1, 0, node)
                value = self._mapping(node)
            else:  # pragma: no cover - the composer only makes these three
                raise self.error(f"unsupported YAML node {type(node).__name__}", node)
        finally:
            self._active.discard(nid)
            self._building.pop()
        self._done[nid] = value
        self._sizes[nid] = (self.values - start_values, self.chars - start_chars)
        return value

    def _grow(self, values: int, chars: int, where: Node) -> None:
        """Count what the document holds so far, aliases and merge keys expanded, and refuse
        it at ``where`` the moment it passes a limit: while it is built, not after (an
        alias repeats its whole anchored node each time, a merge key its whole mapping: a
        few lines can stand for 10⁹ values, a 100 kB condition used 100 times for 10 MB of
        text to compile; README "Input limits")."""
        self.values += values
        self.chars += chars
        if self.values > MAX_YAML_VALUES:
            raise TooLarge(
                f"document is too large: more than {MAX_YAML_VALUES:,} values once its aliases"
                " and merge keys are expanded (each use of an alias counts the whole node it"
                f" names); a recipe or an I/O map may have at most {MAX_YAML_VALUES:,}"
                " (README: Input limits)",
                self.file,
                *_line_col_of(where),
            )
        if self.chars > MAX_YAML_TEXT_CHARS:
            raise TooLarge(
                f"document is too large: more than {MAX_YAML_TEXT_CHARS:,} characters of text"
                " once its aliases and merge keys are expanded (each use of an alias counts the"
                " whole text it names); a recipe or an I/O map may hold at most"
                f" {_size_text(MAX_YAML_TEXT_CHARS)} of text (README: Input limits)",
                self.file,
                *_line_col_of(where),
            )

    def _bad_tag(self, node: Node, kind: str) -> ConfigError:
        tag = _short_tag(node.tag)
        if node.tag in (_STR, _INT, _FLOAT, _BOOL, _NULL, _TIMESTAMP, _SEQ, _MAP):
            return self.error(f"YAML tag '{tag}' cannot be used on {kind}", node)
        return self.error(f"unsupported YAML tag '{tag}' ({_PLAIN_DATA})", node)

    def _scalar(self, node: ScalarNode) -> Any:
        tag = node.tag
        if tag in (_STR, _TIMESTAMP, _VALUE, _MERGE):
            surrogate = _SURROGATE.search(node.value)
            if surrogate is not None:
                # "\ud800" in a double-quoted string: a str no file, log or socket can
                # take (every writer encodes UTF-8); refused here, where it is written.
                raise self.error(
                    "a string that cannot be encoded as UTF-8: it holds the lone surrogate"
                    f" U+{ord(surrogate[0]):04X} (an escape such as \\ud800 is half of a"
                    " character; write the character itself, or \\U0001F600 for one above"
                    " U+FFFF)",
                    node,
                )
            # Timestamps stay text: configuration wants str, not datetime.
            return str(node.value)
        if tag == _NULL:
            return None
        kind = self._scalar_kinds.get(tag)
        if kind is None:
            raise self._bad_tag(node, "a scalar")
        name, construct = kind
        surprise = _yaml11_surprise(node.value) if tag in (_INT, _FLOAT) else None
        if surprise is not None:
            raise self.error(surprise, node)
        try:
            return construct(self._scalars, node)
        except (ValueError, KeyError, IndexError, TypeError, ArithmeticError) as exc:
            raise self.error(f"invalid {name} value {node.value!r}", node) from exc

    def _mapping(self, node: MappingNode) -> dict[Any, Any]:
        index: dict[Hashable, _Entry] = {}
        merges: list[Node] = []
        merge_keys: list[Node] = []
        merge_key: Node | None = None
        for key_node, value_node in node.value:
            if isinstance(key_node, ScalarNode) and key_node.tag == _MERGE:
                if merge_key is not None:
                    raise self._duplicate("<<", key_node, merge_key)
                merge_key = key_node
                merge_keys.append(key_node)
                merges.append(value_node)
                continue
            key = self.build(key_node)
            if isinstance(key, (dict, list)):
                kind = "a mapping" if isinstance(key, dict) else "a list"
                raise self.error(f"mapping keys must be scalars, not {kind}", key_node)
            if key in index:
                raise self._duplicate(key, key_node, index[key][0])
            index[key] = (key_node, value_node)
        for merge_node, value_node in zip(merge_keys, merges, strict=True):
            for source in self._merge_sources(value_node):
                if id(source) not in self._done:
                    self.build(source)  # an inline mapping (an alias is built already)
                source_index = self.mappings[id(source)]
                # Its keys count before they are copied (each source in full, even keys
                # this mapping overrides: the copying is the work); the values count as
                # they are built below, like any alias.
                values = chars = 0
                for key_node, _ in source_index.values():
                    key_values, key_chars = self._sizes[id(key_node)]
                    values += key_values
                    chars += key_chars
                self._grow(values, chars, merge_node)
                for key, entry in source_index.items():
                    index.setdefault(key, entry)  # explicit keys and earlier sources win
        self.mappings[id(node)] = index
        return {key: self.build(entry[1]) for key, entry in index.items()}

    def _merge_sources(self, node: Node) -> list[MappingNode]:
        if isinstance(node, MappingNode):
            return [node]
        if isinstance(node, SequenceNode) and all(isinstance(n, MappingNode) for n in node.value):
            return list(node.value)
        raise self.error("merge key '<<' needs a mapping or a list of mappings", node)

    def _duplicate(self, key: object, node: Node, first: Node) -> ConfigError:
        shown = f"'{key}'" if isinstance(key, str) else repr(key)
        return self.error(
            f"duplicate key {shown} (first defined at line {first.start_mark.line + 1})", node
        )


# --------------------------------------------------------------------------------------------
# pydantic errors -> positions


def validate(model: type[M], data: Any, positions: Positions, file: str) -> M:
    """``model.model_validate(data)``; on failure raise ConfigErrors, one per pydantic error."""
    try:
        return model.model_validate(data)
    except pydantic.ValidationError as exc:
        raise format_validation_error(exc, positions, file, model=model) from exc


def format_validation_error(
    exc: pydantic.ValidationError,
    positions: Positions,
    file: str,
    *,
    model: type[pydantic.BaseModel] | None = None,
) -> ConfigErrors:
    """Convert every error of ``exc`` into a positioned ConfigError, sorted by line and column.

    ``model`` (the validated model) is optional; with it, unknown-key errors list the allowed
    keys and suggest the nearest one.
    """
    located: list[tuple[Mark, str]] = []
    for err in exc.errors(include_url=False):
        located.append(_convert(err, positions, model))
    located.sort(key=lambda item: (item[0].line, item[0].col))
    return ConfigErrors([ConfigError(msg, file, mark.line, mark.col) for mark, msg in located])


_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*\Z")


def _fmt_path(path: Path_) -> str:
    """``devices.chadeche.boards[2].address``; the empty path is the top level."""
    out = ""
    for element in path:
        if isinstance(element, int) and not isinstance(element, bool):
            out += f"[{element}]"
        elif isinstance(element, str) and _WORD.match(element):
            out += f".{element}" if out else element
        else:
            out += f"[{str(element)!r}]"
    return out or "top level"


def _in(path: Path_) -> str:
    return f"in {_fmt_path(path)}" if path else "at the top level"


def _received(value: Any) -> str:
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _resolve(positions: Positions, loc: tuple[str | int, ...], keep_last: bool) -> Path_:
    """Turn a pydantic ``loc`` into a document path.

    pydantic inserts elements that are not keys of the data (the tag of a discriminated union,
    ``function-after[...]``, a union member's name, ``[key]``): they are dropped.  The last
    element is kept even if absent from the document when ``keep_last`` (a missing key).
    """
    path: list[str | int] = []
    node = positions._root
    for i, element in enumerate(loc):
        entry = positions._child(node, element)
        if entry is not None:
            path.append(element)
            node = entry[1]
        elif keep_last and i == len(loc) - 1:
            path.append(element)
    return tuple(path)


def _convert(
    err: ErrorDetails, positions: Positions, model: type[pydantic.BaseModel] | None
) -> tuple[Mark, str]:
    loc: tuple[str | int, ...] = tuple(err["loc"])
    kind: str = err["type"]
    ctx: dict[str, Any] = err.get("ctx") or {}
    path = _resolve(positions, loc, keep_last=kind == "missing")

    if kind == "extra_forbidden" and path:
        key = path[-1]
        message = f"unknown key '{key}' {_in(path[:-1])}"
        allowed = _allowed_keys(model, loc[:-1]) if model is not None else None
        if allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            message += f" ({hint}expected one of: {', '.join(allowed)})"
        return positions.key(path) or positions.nearest(path), message

    if kind == "missing" and path:
        parent = path[:-1]
        message = f"missing required key '{path[-1]}' {_in(parent)}"
        return positions.value(parent) or positions.nearest(parent), message

    if kind in ("union_tag_not_found", "union_tag_invalid"):
        discriminator = str(ctx.get("discriminator", "")).strip("'\"")
        if kind == "union_tag_not_found" and discriminator:
            tags = _allowed_tags(model, loc, discriminator) if model is not None else []
            message = f"missing required key '{discriminator}' {_in(path)}"
            if tags:
                message += f" (expected one of: {', '.join(repr(t) for t in tags)})"
            return positions.value(path) or positions.nearest(path), message
        if kind == "union_tag_invalid" and discriminator:
            where = (*path, discriminator)
            message = (
                f"{_fmt_path(where)}: unknown value {_received(ctx.get('tag'))} "
                f"(expected one of: {ctx.get('expected_tags', '?')})"
            )
            return positions.value(where) or positions.nearest(path), message

    msg: str = err["msg"]
    value = err.get("input")
    if kind in ("value_error", "assertion_error"):
        # A custom ValueError/assert from a validator: keep its own words.
        msg = re.sub(r"^(Value error|Assertion failed), ", "", msg)
    if loc and loc[-1] == "[key]" and path:
        mark = positions.key(path) or positions.nearest(path)
        return mark, f"{_fmt_path(path[:-1])}: key {_received(path[-1])}: {msg}"
    message = f"{_fmt_path(path)}: {msg}"
    if kind not in ("value_error", "assertion_error") or not isinstance(value, (Mapping, list)):
        message += f" (received {_received(value)})"
    return positions.value(path) or positions.nearest(path), message


# --------------------------------------------------------------------------------------------
# Walking model types along a loc


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, pydantic.BaseModel)


def _expand(candidates: list[Any]) -> list[Any]:
    """Unwrap Annotated / Optional / Union into a flat list of concrete types."""
    out: list[Any] = []
    stack = list(reversed(candidates))
    while stack:
        tp = stack.pop()
        origin = get_origin(tp)
        if origin is Annotated:
            stack.append(get_args(tp)[0])
        elif origin is Union or origin is types.UnionType:
            stack.extend(reversed(get_args(tp)))
        elif tp is type(None) or tp is None:
            continue
        elif tp not in out:
            out.append(tp)
    return out


def _field_keys(field_name: str, info: Any) -> list[str]:
    """Input keys a field accepts, the preferred spelling first."""
    keys: list[str] = []
    alias = info.validation_alias
    if isinstance(alias, str):
        keys.append(alias)
    elif isinstance(alias, pydantic.AliasChoices):
        keys.extend(choice for choice in alias.choices if isinstance(choice, str))
    if isinstance(info.alias, str):
        keys.append(info.alias)
    keys.append(field_name)
    return list(dict.fromkeys(keys))


def _literal_values(tp: Any) -> list[Any]:
    return [value for arg in _expand([tp]) if get_origin(arg) is Literal for value in get_args(arg)]


def _is_member(model: Any, element: str | int) -> bool:
    """Does a loc element inserted by pydantic for a union select ``model``?"""
    if element == model.__name__:
        return True
    if isinstance(element, str) and element.endswith(f", {model.__name__}]"):
        return True  # function-after[validator(), Model]
    return any(element in _literal_values(info.annotation) for info in model.model_fields.values())


def _types_below(tp: Any, element: str | int) -> list[Any]:
    """The type one step below ``tp`` at ``element`` (a model's field, a mapping's value, a
    tuple's or a sequence's item), in a list; empty when ``element`` leads nowhere."""
    if _is_model(tp):
        for name, info in tp.model_fields.items():
            if element in _field_keys(name, info):
                return [info.annotation]
        return []
    origin = get_origin(tp)
    args = get_args(tp)
    if isinstance(origin, type) and issubclass(origin, Mapping) and len(args) == 2:
        return [args[1]]
    if origin is tuple and args and isinstance(element, int):
        if len(args) == 2 and args[1] is Ellipsis:
            return [args[0]]
        return [args[element]] if 0 <= element < len(args) else []
    if (
        isinstance(origin, type)
        and issubclass(origin, (Sequence, set, frozenset))
        and args
        and isinstance(element, int)
    ):
        return [args[0]]
    return []


def _types_at(model: type[pydantic.BaseModel], loc: Sequence[str | int]) -> list[Any]:
    candidates: list[Any] = [model]
    for element in loc:
        candidates = _expand(candidates)
        models = [tp for tp in candidates if _is_model(tp)]
        if len(candidates) > 1:
            chosen = [m for m in models if _is_member(m, element)]
            if chosen:
                candidates = chosen
                continue
        following = [below for tp in candidates for below in _types_below(tp, element)]
        if following:
            candidates = following
        # else: a marker pydantic inserted (e.g. function-after[...]); stay where we are.
    return _expand(candidates)


def _allowed_keys(model: type[pydantic.BaseModel], loc: Sequence[str | int]) -> list[str]:
    keys: list[str] = []
    for tp in _types_at(model, loc):
        if _is_model(tp):
            for name, info in tp.model_fields.items():
                preferred = _field_keys(name, info)[0]
                if preferred not in keys:
                    keys.append(preferred)
    return keys


def _allowed_tags(
    model: type[pydantic.BaseModel], loc: Sequence[str | int], discriminator: str
) -> list[Any]:
    tags: list[Any] = []
    for tp in _types_at(model, loc):
        if _is_model(tp):
            for name, info in tp.model_fields.items():
                if discriminator in _field_keys(name, info):
                    tags.extend(v for v in _literal_values(info.annotation) if v not in tags)
    return tags
