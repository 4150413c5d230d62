"""The project's own generator of mutated input files (issue 9, "Hardening").

The promise (docs/operator.md): every malformed file a user hands to ``supervisor check`` or
``supervisor import chadeche`` gets one clear message naming file, line and column, exit code
2, never a traceback and never a hang. This module makes the files that test it: from the
shipped ``io_maps/*.yaml``, ``recipes/*.yaml``, ``tests/data/chadeche/*.txt`` and ``*.prm``,
and the sources of ``tests/data/mutation_sources/`` (a recipe using every step kind the
shipped ones leave out, a load profile CSV), it derives seeded, deterministic variants, each
labelled with

* its class (``Variant.mutation``, e.g. ``yaml.bool_for_number``, ``chadeche.huge_number``),
* how it was made (``Variant.how``: which node, cell or line, what it was, what it became),
* whether it is certainly invalid (``expect="refuse"``: a typo'd key, a boolean where the
  file had a number, an unknown step id, a file over its documented size limit) or may still
  be a valid file (``"either"``: a dropped optional key, CRLF line ends, a zero),
* ``whole_file``: the refusal is about the whole file, which has no line to name (a file over
  its byte limit, README "Input limits", is refused before it is read); every other refusal
  must name file, line and column,
* ``pending``: the fix is another branch's (zero-time loops, count limits of issue 9); its
  failures are listed apart until that branch is merged.

Variant ``index`` of ``seed`` depends on nothing else (it has its own ``random.Random``), so a
failure is reproduced from its index alone (``python -m tests.mutation_run --show INDEX``).

:func:`classify` is the one definition of the outcomes (accepted, located refusal, file-only
refusal, unlocated refusal, traceback, timeout), shared by the subprocess runner
(``tests/mutation_run.py``) and the in-process property test
(``tests/unit/test_mutation_corpus.py``).

YAML variants are made on PyYAML's composed node graph (so a mutation lands on one node and
the rest of the document is unchanged) and written back with ``yaml.serialize``, which keeps
flow/block style and quoting but not comments; the text-level mutations (tabs, BOM, invalid
UTF-8, truncation, line ends) work on the original bytes, comments included.
"""

from __future__ import annotations

import codecs
import copy
import itertools
import math
import random
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode
from yaml.resolver import Resolver

from supervisor.config.limits import (
    MAX_CYCLES,
    MAX_INITIAL_CHARGE_AH,
    MAX_IO_MAP_TAGS,
    MAX_PROFILE_CSV_BYTES,
    MAX_PROFILE_ROWS,
    MAX_RECIPE_GROUPS,
    MAX_RECIPE_STEPS,
    MAX_SEQUENCE_ROWS,
    MAX_TEXT_BYTES,
    MAX_YAML_BYTES,
)

__all__ = [
    "DEFAULT_SEED",
    "FAILURES",
    "MUTATIONS",
    "ROOT",
    "SOURCES",
    "Made",
    "Mutator",
    "Outcome",
    "Source",
    "Variant",
    "Verdict",
    "classify",
    "generate",
    "make_variant",
]

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SEED = 9  # issue 9
CHADECHE_DIR = "tests/data/chadeche"
SOURCES_DIR = "tests/data/mutation_sources"
SEQUENCE = f"{CHADECHE_DIR}/figure10.txt"  # the valid sequence a .prm variant is imported with
PRM = f"{CHADECHE_DIR}/chadeche0.prm"  # the valid .prm some sequence variants are given
RECIPE_MAP = "io_maps/sim.yaml"
"""The I/O map a shipped recipe's variants are checked with, as a user checks a recipe that
names bench tags (``bms.cell_max``): ``supervisor check io_maps/sim.yaml RECIPE``."""

Expect = Literal["refuse", "either"]
Target = Literal["check", "chadeche", "prm", "profile"]

REFUSE: Expect = "refuse"
EITHER: Expect = "either"

# The byte limit of each kind of file (README "Input limits"): a variant above it is refused
# as a whole, before it is read.
BYTE_LIMIT: dict[Target, int] = {
    "check": MAX_YAML_BYTES,
    "chadeche": MAX_TEXT_BYTES,
    "prm": MAX_TEXT_BYTES,
    "profile": MAX_PROFILE_CSV_BYTES,
}

# Fixes on other branches of issue 9 (their classes are labelled, expected to fail until
# merged, and listed apart by the runner; remove the label's use when the branch lands).
PENDING_ZERO_TIME = (
    "harden-zero: a cycle of steps that can all complete in zero time is refused by check"
)
PENDING_COUNTS = (
    "harden-stall: recipe steps, groups and initial_charge limits"
    " (declared in supervisor/config/limits.py, not yet enforced)"
)


# --------------------------------------------------------------------------------------------
# Sources and variants


@dataclass(frozen=True)
class Source:
    """A valid or deliberately broken file mutations start from."""

    path: str  # relative to ROOT
    target: Target
    data: bytes

    @property
    def encoding(self) -> str:
        """``utf-8`` or ``cp1252`` (Chadèche files may be either, seed 000 §III.D)."""
        try:
            self.data.decode("utf-8")
        except UnicodeDecodeError:
            return "cp1252"
        return "utf-8"

    @property
    def text(self) -> str:
        return self.data.decode(self.encoding)


def _sources() -> tuple[Source, ...]:
    out: list[Source] = []
    patterns: tuple[tuple[str, Target], ...] = (
        ("io_maps/*.yaml", "check"),
        ("recipes/*.yaml", "check"),
        (f"{SOURCES_DIR}/*.yaml", "check"),
        (f"{CHADECHE_DIR}/*.txt", "chadeche"),
        (f"{CHADECHE_DIR}/*.prm", "prm"),
        (f"{SOURCES_DIR}/*.csv", "profile"),
    )
    for pattern, target in patterns:
        for path in sorted(ROOT.glob(pattern)):
            out.append(Source(str(path.relative_to(ROOT)), target, path.read_bytes()))
    return tuple(out)


SOURCES: tuple[Source, ...] = _sources()

# The valid shipped files are picked more often than the bad-* corpus files (a mutation of a
# file that is already refused shows less).
_VALID_SOURCE_WEIGHT = 4


def _source_weight(src: Source) -> int:
    return 1 if Path(src.path).name.startswith("bad") else _VALID_SOURCE_WEIGHT


@dataclass(frozen=True)
class Made:
    """What one mutator made of a source."""

    content: bytes
    how: str
    expect: Expect
    pending: str = ""  # the branch whose fix this variant waits for (see PENDING_*)
    whole_file: bool = False  # a refusal may name the file alone (no line to name)


# The recipe a profile variant (a CSV) is checked through: a load profile is read for a
# recipe's ``profile: {file: ...}`` (seed 002 §2.3), relative to the recipe's folder.
_PROFILE_RECIPE = "recipe: profile\nsteps:\n  - {{id: p, profile: {{file: {name}}}}}\n"


@dataclass(frozen=True)
class Feed:
    """A variant written to disk: the ``supervisor`` arguments, the path a refusal must
    locate (``files``) and, for a profile, the recipe whose position may come first."""

    argv: list[str]
    files: list[str]
    via: list[str]


_SUFFIX: dict[Target, str] = {
    "check": ".yaml",
    "chadeche": ".txt",
    "prm": ".prm",
    "profile": ".csv",
}


@dataclass(frozen=True)
class Variant:
    """One mutated file and how to feed it to the real command."""

    index: int
    seed: int
    mutation: str
    how: str
    source: str
    target: Target
    content: bytes
    expect: Expect
    with_prm: bool = False  # a sequence variant imported with --prm chadeche0.prm
    pending: str = ""
    whole_file: bool = False

    @property
    def suffix(self) -> str:
        return _SUFFIX[self.target]

    @property
    def file_name(self) -> str:
        return f"v{self.index:05d}{self.suffix}"

    def write(self, folder: Path, root: Path = ROOT) -> Feed:
        """Write the variant (and the recipe of a profile) into ``folder``; how to run it.

        Paths are given relative to ``root`` when they are under it (as a user types them),
        so that a message naming them can be matched as printed."""

        def shown(p: Path) -> str:
            return str(p.relative_to(root)) if p.is_relative_to(root) else str(p)

        path = folder / self.file_name
        path.write_bytes(self.content)
        if self.target == "check":
            with_map = [str(root / RECIPE_MAP)] if self.source.startswith("recipes/") else []
            return Feed(["check", *with_map, shown(path)], [shown(path)], [])
        if self.target == "profile":
            recipe = path.with_suffix(".yaml")
            recipe.write_text(_PROFILE_RECIPE.format(name=path.name), encoding="utf-8")
            return Feed(["check", shown(recipe)], [shown(path)], [shown(recipe)])
        if self.target == "prm":
            argv = ["import", "chadeche", str(root / SEQUENCE), "--prm", shown(path)]
            return Feed(argv, [shown(path)], [])
        extra = ["--prm", str(root / PRM)] if self.with_prm else []
        return Feed(["import", "chadeche", shown(path), *extra], [shown(path)], [])

    def label(self) -> str:
        return f"#{self.index} {self.mutation} of {self.source}: {self.how}"


Make = Callable[[random.Random, Source, bool], Made | None]


@dataclass(frozen=True)
class Mutator:
    """A class of mutation: a name, the targets it applies to, how often it is picked."""

    name: str
    targets: frozenset[Target]
    make: Make
    weight: int = 2
    large: bool = False  # makes files of megabytes: not in the small (in-process) sample
    refuses: bool = True  # some of its variants are certainly invalid (expect "refuse")


MUTATIONS: dict[str, Mutator] = {}


def _mutator(
    name: str, *targets: Target, weight: int = 2, large: bool = False, refuses: bool = True
) -> Callable[[Make], Make]:
    def register(fn: Make) -> Make:
        MUTATIONS[name] = Mutator(name, frozenset(targets), fn, weight, large, refuses)
        return fn

    return register


def make_variant(
    index: int,
    seed: int = DEFAULT_SEED,
    *,
    mutation: str | None = None,
    small: bool = False,
) -> Variant:
    """Variant ``index`` of ``seed`` (``mutation``: only that class; ``small``: no files of
    megabytes and bounded alias expansion, for the in-process sample)."""
    rng = random.Random(f"mutation:{seed}:{index}:{mutation or ''}:{int(small)}")
    if mutation is not None:
        mutators = [MUTATIONS[mutation]]
    else:
        mutators = [m for m in MUTATIONS.values() if not (small and m.large)]
    for _attempt in range(200):
        mut = rng.choices(mutators, [m.weight for m in mutators])[0]
        sources = [s for s in SOURCES if s.target in mut.targets]
        # A class that applies to few sources (goto targets are in one recipe) tries several
        # before another class is drawn, so that it is not under-represented.
        for _source_attempt in range(8):
            src = rng.choices(sources, [_source_weight(s) for s in sources])[0]
            made = mut.make(rng, src, small)
            if made is not None and made.content != src.data:
                break
        if made is None or made.content == src.data:
            continue
        if len(made.content) > BYTE_LIMIT[src.target]:
            # Over the documented byte limit: certainly refused, before anything is parsed.
            made = replace(made, expect=REFUSE, whole_file=True, pending="")
        return Variant(
            index=index,
            seed=seed,
            mutation=mut.name,
            how=made.how,
            source=src.path,
            target=src.target,
            content=made.content,
            expect=made.expect,
            with_prm=src.target == "chadeche" and rng.random() < 0.3,
            pending=made.pending,
            whole_file=made.whole_file,
        )
    raise RuntimeError(f"no {mutation or 'mutation'} applies (seed {seed}, index {index})")


def generate(
    count: int, seed: int = DEFAULT_SEED, *, start: int = 0, mutation: str | None = None
) -> Iterator[Variant]:
    """Variants ``start`` … ``start + count - 1`` of ``seed``."""
    for index in range(start, start + count):
        yield make_variant(index, seed, mutation=mutation)


# --------------------------------------------------------------------------------------------
# Outcomes


Outcome = Literal[
    "accepted",  # exit 0 (a "refuse" variant accepted is a miss: see Verdict.miss)
    "located",  # exit 2, every stderr line "file:line:col: message"
    "file_only",  # exit 2, "file: message" lines too, for a whole-file refusal only
    "unlocated",  # exit 2, a line that names no file:line:col of the mutated file
    "traceback",  # "Traceback" in the output, exit 1, or any exit code but 0 and 2
    "timeout",  # still running at the time limit
    "import_invalid",  # an accepted import whose recipe `supervisor check` refuses
]
FAILURES: frozenset[Outcome] = frozenset({"unlocated", "traceback", "timeout", "import_invalid"})


@dataclass(frozen=True)
class Verdict:
    outcome: Outcome
    why: str = ""

    @property
    def failed(self) -> bool:
        return self.outcome in FAILURES


def classify(
    code: int | None,
    stderr: str,
    files: list[str],
    *,
    via: list[str] | None = None,
    whole_file: bool = False,
) -> Verdict:
    """What a run of the command did.

    ``code`` None is a timeout. ``files`` are the paths a refusal must name, as given on
    the command line: every stderr line of an exit 2 must start ``FILE:LINE:COL: `` (a
    message about the mutated file where it is wrong). ``via`` are files that refer to it
    (the recipe of a profile CSV), whose position may come first (``r.yaml:4:21:
    p.csv:3:1: ...``). ``whole_file``: the variant's refusal is about the whole file (over
    its byte limit), so ``FILE: message`` is located enough; anywhere else it is not.
    """
    if code is None:
        return Verdict("timeout")
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    if "Traceback (most recent call last)" in stderr or code not in (0, 2):
        return Verdict("traceback", f"exit {code}: {(lines or ['(no output)'])[-1][:300]}")
    if code == 0:
        return Verdict("accepted")
    names = "|".join(re.escape(f) for f in files)
    lead = "|".join(re.escape(f) for f in via or [])
    prefix = rf"(?:(?:{lead}):\d+:\d+: )?" if lead else ""
    located = re.compile(rf"^{prefix}(?:{names}):\d+:\d+: \S")
    file_only = re.compile(rf"^{prefix}(?:{names}): \S")
    if not lines:
        return Verdict("unlocated", "exit 2 without any message")
    some_file_only = False
    for ln in lines:
        if located.match(ln):
            continue
        if file_only.match(ln):
            if not whole_file:
                return Verdict("unlocated", f"names the file but no line and column: {ln[:300]}")
            some_file_only = True
            continue
        return Verdict("unlocated", ln[:300])
    return Verdict("file_only" if some_file_only else "located")


# --------------------------------------------------------------------------------------------
# YAML on the node graph

_TAG = "tag:yaml.org,2002:"
_STR, _INT, _FLOAT, _BOOL, _NULL, _MERGE = (
    _TAG + t for t in ("str", "int", "float", "bool", "null", "merge")
)
_RESOLVER = Resolver()
_RAW = "MUTATION_RAW_FRAGMENT"  # a scalar replaced by raw YAML text after serialising

Path_ = tuple[str | int, ...]


@dataclass
class _Site:
    """A node of the graph and where it hangs (``slot`` in its parent's ``value`` list)."""

    path: Path_
    node: Node
    parent: Node | None
    slot: int
    is_key: bool = False

    def where(self) -> str:
        text = ""
        for part in self.path:
            text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
        mark = self.node.start_mark
        what = "key " if self.is_key else ""
        return f"{what}{text or '(document)'} (line {mark.line + 1}:{mark.column + 1})"

    @property
    def parent_key(self) -> str | int | None:
        """The mapping key this site's parent hangs under (``steps`` for a step's keys)."""
        keys = [p for p in self.path[:-1] if not isinstance(p, int)]
        return keys[-1] if keys else None

    @property
    def key(self) -> str | int | None:
        return self.path[-1] if self.path else None


def _scalar(text: str, *, quoted: bool = False) -> ScalarNode:
    """A scalar node that serialises as ``text`` (plain, resolved like a loader would)."""
    if quoted:
        return ScalarNode(_STR, text, style='"')
    return ScalarNode(_RESOLVER.resolve(ScalarNode, text, (True, False)), text)  # type: ignore[no-untyped-call]


def _key_text(node: Node) -> str | int:
    if isinstance(node, ScalarNode):
        value = str(node.value)
        return int(value) if node.tag == _INT and value.isdigit() else value
    return "?"


class _Doc:
    """A composed YAML document, its sites, and how to write it back."""

    def __init__(self, text: str) -> None:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        if root is None:
            raise ValueError("empty document")
        self.root: Node = root
        self.raw: dict[str, str] = {}

    def sites(self) -> list[_Site]:
        out: list[_Site] = []
        stack: list[_Site] = [_Site((), self.root, None, -1)]
        seen: set[int] = set()
        while stack:
            site = stack.pop()
            out.append(site)
            node = site.node
            if id(node) in seen:  # an alias of a node already listed
                continue
            seen.add(id(node))
            children: list[_Site] = []
            if isinstance(node, MappingNode):
                for i, (k, v) in enumerate(node.value):
                    name = _key_text(k)
                    children.append(_Site((*site.path, name), k, node, i, is_key=True))
                    children.append(_Site((*site.path, name), v, node, i))
            elif isinstance(node, SequenceNode):
                for i, item in enumerate(node.value):
                    children.append(_Site((*site.path, i), item, node, i))
            stack.extend(reversed(children))
        return out

    @staticmethod
    def walk(node: Node) -> Iterator[Node]:
        """Every node under ``node`` (itself first), each once."""
        stack, seen = [node], set()
        while stack:
            n = stack.pop()
            if id(n) in seen:
                continue
            seen.add(id(n))
            yield n
            if isinstance(n, MappingNode):
                for k, v in n.value:
                    stack += [k, v]
            elif isinstance(n, SequenceNode):
                stack += n.value

    def values(self) -> list[_Site]:
        return [s for s in self.sites() if not s.is_key]

    def replace(self, site: _Site, new: Node) -> None:
        parent = site.parent
        if parent is None:
            self.root = new
        elif isinstance(parent, MappingNode):
            k, v = parent.value[site.slot]
            parent.value[site.slot] = (new, v) if site.is_key else (k, new)
        elif isinstance(parent, SequenceNode):
            parent.value[site.slot] = new

    def replace_raw(self, site: _Site, fragment: str) -> None:
        """Put raw YAML text (any size, any depth) where ``site`` is."""
        placeholder = f"{_RAW}{len(self.raw)}"
        self.raw[placeholder] = fragment
        self.replace(site, ScalarNode(_STR, placeholder))

    def emit(self) -> str:
        text = yaml.serialize(self.root, Dumper=yaml.SafeDumper, allow_unicode=True, width=1 << 20)
        for placeholder, fragment in self.raw.items():
            text = text.replace(placeholder, fragment, 1)
        return text


def _doc(src: Source) -> _Doc | None:
    try:
        return _Doc(src.text)
    except (yaml.YAMLError, ValueError):
        return None


def _made(doc: _Doc, how: str, expect: Expect, pending: str = "") -> Made:
    return Made(doc.emit().encode("utf-8"), how, expect, pending)


def _number_sites(doc: _Doc) -> list[_Site]:
    return [
        s
        for s in doc.values()
        if isinstance(s.node, ScalarNode) and s.node.tag in (_INT, _FLOAT) and not s.node.style
    ]


_QUANTITY = re.compile(
    r"^(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)(?P<sp>\s*)(?P<unit>[A-Za-zΩ°µ/]+)$"
)


_FREE_TEXT = {"comment", "description", "recipe", "bench", "name", "id"}  # text, not quantities


def _quantity_sites(doc: _Doc) -> list[_Site]:
    return [
        s
        for s in doc.values()
        if isinstance(s.node, ScalarNode)
        and s.node.tag == _STR
        and s.key not in _FREE_TEXT
        and _QUANTITY.match(s.node.value)
    ]


def _collections(doc: _Doc, kind: type[Node]) -> list[_Site]:
    return [s for s in doc.values() if isinstance(s.node, kind) and s.parent is not None]


def _pick(rng: random.Random, items: list[_Site]) -> _Site | None:
    return rng.choice(items) if items else None


# Mappings whose keys are names the user chooses (renaming one is not an unknown key).
_FREE_KEYS = {"parameters", "devices", "modules"}


@_mutator("yaml.drop_key", "check", weight=3, refuses=False)
def _drop_key(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.sites() if s.is_key])
    if site is None or not isinstance(site.parent, MappingNode):
        return None
    del site.parent.value[site.slot]
    return _made(doc, f"dropped {site.where()}", EITHER)


@_mutator("yaml.duplicate_key", "check")
def _duplicate_key(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.sites() if s.is_key])
    if site is None or not isinstance(site.parent, MappingNode):
        return None
    k, v = site.parent.value[site.slot]
    site.parent.value.insert(site.slot + 1, (copy.deepcopy(k), copy.deepcopy(v)))
    return _made(doc, f"duplicated {site.where()}", REFUSE)


def _typo(rng: random.Random, word: str) -> str:
    how = rng.randrange(4)
    if how == 0 and len(word) > 2:
        i = rng.randrange(len(word) - 1)
        swapped = word[:i] + word[i + 1] + word[i] + word[i + 2 :]
        if swapped != word:
            return swapped
    if how == 1:
        return word.upper() if word != word.upper() else word.lower()
    if how == 2 and len(word) > 1:
        return word[:-1]
    return word + "_x"


@_mutator("yaml.rename_key", "check", weight=3)
def _rename_key(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.sites() if s.is_key and isinstance(s.node, ScalarNode)])
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new = _typo(rng, old)
    if new == old:
        return None
    doc.replace(site, _scalar(new))
    free = site.parent_key in _FREE_KEYS
    return _made(doc, f"renamed {site.where()} {old!r} → {new!r}", EITHER if free else REFUSE)


@_mutator("yaml.bool_for_number", "check", weight=3)
def _bool_for_number(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _number_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    new = rng.choice(["true", "false", "yes", "on"])
    old = site.node.value
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()}: number {old} → boolean {new}", REFUSE)


@_mutator("yaml.string_for_number", "check")
def _string_for_number(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _number_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new, expect = rng.choice(
        [
            (old, EITHER),  # the same digits, quoted: "5025"
            ("twelve", REFUSE),
            (f"{old} apples", REFUSE),
            ("", REFUSE),
            (f"{old},5", REFUSE),
        ]
    )
    doc.replace(site, _scalar(new, quoted=True))
    return _made(doc, f"{site.where()}: number {old} → string {new!r}", expect)


@_mutator("yaml.list_for_mapping", "check")
def _list_for_mapping(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _collections(doc, MappingNode))
    if site is None or not isinstance(site.node, MappingNode):
        return None
    items = [v for _, v in site.node.value] if rng.random() < 0.7 else []
    doc.replace(site, SequenceNode(_TAG + "seq", items, flow_style=site.node.flow_style))
    return _made(doc, f"{site.where()}: mapping → list of {len(items)} values", REFUSE)


@_mutator("yaml.mapping_for_list", "check")
def _mapping_for_list(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _collections(doc, SequenceNode))
    if site is None or not isinstance(site.node, SequenceNode):
        return None
    pairs = (
        [(_scalar(str(i)), item) for i, item in enumerate(site.node.value)]
        if rng.random() < 0.7
        else []
    )
    doc.replace(site, MappingNode(_TAG + "map", pairs, flow_style=site.node.flow_style))
    return _made(doc, f"{site.where()}: list → mapping of {len(pairs)} entries", REFUSE)


@_mutator("yaml.scalar_for_collection", "check")
def _scalar_for_collection(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(
        rng,
        [s for s in doc.values() if s.parent is not None and not isinstance(s.node, ScalarNode)],
    )
    if site is None:
        return None
    new, expect = rng.choice([("3", REFUSE), ("text", REFUSE), ("true", REFUSE), ("null", EITHER)])
    doc.replace(site, _scalar(new))
    kind = "mapping" if isinstance(site.node, MappingNode) else "list"
    return _made(doc, f"{site.where()}: {kind} → {new}", expect)


@_mutator("yaml.collection_for_scalar", "check")
def _collection_for_scalar(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(
        rng,
        [
            s
            for s in doc.values()
            if isinstance(s.node, ScalarNode) and s.parent is not None and s.node.tag != _NULL
        ],
    )
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = site.node
    if rng.random() < 0.5:
        new: Node = SequenceNode(_TAG + "seq", [copy.deepcopy(old)], flow_style=True)
        what = f"[{old.value}]"
    else:
        new = MappingNode(_TAG + "map", [(_scalar("value"), copy.deepcopy(old))], flow_style=True)
        what = f"{{value: {old.value}}}"
    doc.replace(site, new)
    return _made(doc, f"{site.where()}: {old.value!r} → {what}", REFUSE)


@_mutator("yaml.null_value", "check", refuses=False)
def _null_value(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(
        rng,
        [s for s in doc.values() if s.parent is not None and getattr(s.node, "tag", "") != _NULL],
    )
    if site is None:
        return None
    new = rng.choice(["null", "~", ""])
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()} → null ({new!r})", EITHER)


# Keys of I/O maps and recipes whose number must be more than zero, or at least zero: a
# period, a timeout, a capacity, a count, a port (docs/deployment.md "I/O maps", the models'
# own text).
_POSITIVE_KEYS = {
    "period_s",
    "poll_period_s",
    "timeout_s",
    "capacity_ah",
    "cycles",
    "count",
    "port",
    "max_speed_hz",
    "cells_series",
}
_NONNEGATIVE_KEYS = {
    "stale_after_s",
    "delay_s",
    "watchdog_s",
    "host_watchdog_s",
    "tolerance_v",
    "current_tolerance_a",
    "address",
    "board",
    "bus",
    "device",
    "soc",
}
_INTEGER_KEYS = {"cycles", "count", "port", "address", "board", "bus", "device", "cells_series"}


def _sign_rule(key: object, value: float) -> Expect:
    """``refuse`` where the key's number cannot be ``value`` (zero, negative)."""
    if key in _POSITIVE_KEYS and value <= 0:
        return REFUSE
    if key in _NONNEGATIVE_KEYS and value < 0:
        return REFUSE
    return EITHER


# (YAML text of the number, is it certainly invalid, what it is). PyYAML resolves a float
# only with a dot and a signed exponent, so "1e309" would be a string: "1.0e+309" is a float.
_EXTREME_NUMBERS: tuple[tuple[str, Expect, str], ...] = (
    (".nan", REFUSE, "NaN"),
    (".inf", REFUSE, "+infinity"),
    ("-.inf", REFUSE, "-infinity"),
    ("1.0e+309", REFUSE, "a float beyond the double range (reads as infinity)"),
    ("1.0e+308", EITHER, "a float near the largest double"),
    ("1e308", EITHER, "the string '1e308' (not a YAML float)"),
    ("1.0e-400", EITHER, "a float below the double range (reads as 0)"),
    ("0", EITHER, "zero"),
    ("-0.0", EITHER, "minus zero"),
    ("-1", EITHER, "minus one"),
    ("-1000000", EITHER, "a large negative number"),
    ("9" * 400, EITHER, "a 400-digit integer"),
    ("9" * 5000, EITHER, "a 5000-digit integer (beyond Python's 4300-digit int-str limit)"),
    ("0x7fffffffffffffff", EITHER, "the largest int64, in hex"),
    ("1_000", EITHER, "1_000 (YAML 1.1 reads 1000)"),
    ("0o17", EITHER, "an octal integer"),
    ("1:30", EITHER, "a YAML 1.1 sexagesimal integer (90)"),
    ("2.5", EITHER, "a fraction"),
)


def _yaml_number(text: str) -> float | None:
    """The number YAML reads in ``text`` (beyond Python's int-str limit: infinite)."""
    try:
        value = yaml.safe_load(text)
    except ValueError:  # "Exceeds the limit (4300 digits) for integer string conversion"
        return math.inf
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        return float(value)
    except OverflowError:  # a 400-digit integer
        return math.inf if value > 0 else -math.inf


@_mutator("yaml.number_extreme", "check", weight=4)
def _number_extreme(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _number_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    text, expect, what = rng.choice(_EXTREME_NUMBERS)
    old = site.node.value
    value = _yaml_number(text)
    if expect == EITHER and value is not None:
        expect = _sign_rule(site.key, value)
        if site.key in _INTEGER_KEYS and math.isfinite(value) and not value.is_integer():
            expect = REFUSE  # 2.5 cycles, port 2.5
        if site.key == "soc" and value > 1:
            expect = REFUSE  # a state of charge is 0..1
    doc.replace_raw(site, text)
    shown = text if len(text) < 20 else f"{text[:8]}…({len(text)} chars)"
    return _made(doc, f"{site.where()}: {old} → {shown}: {what}", expect)


# Number parts of a quantity ("60 s" → "nan s").
_EXTREME_QUANTITY: tuple[tuple[str, Expect, str], ...] = (
    ("nan", REFUSE, "NaN"),
    ("inf", REFUSE, "infinity"),
    ("1e309", REFUSE, "beyond the double range"),
    ("9" * 400, REFUSE, "400 digits (infinite as a double)"),
    ("9" * 5000, REFUSE, "5000 digits"),
    ("1e308", EITHER, "near the largest double"),
    # docs/recipes.md "Recipes": a non-zero literal that reads as 0 is refused (issue 9, 1e-400 A).
    ("1e-400", REFUSE, "below the double range (reads as 0)"),
    ("0", EITHER, "zero"),
    ("-0", EITHER, "minus zero"),
    ("NEG", EITHER, "negated"),
    ("0.000001", EITHER, "a millionth"),
)

# Recipe keys whose quantity must be more than zero, or at least zero (the recipe model:
# "a logging period must be greater than zero", "a duration cannot be negative", "give a
# positive magnitude; the step kind says the direction").
_POSITIVE_QUANTITIES = {"period", "delta_v", "delta_i", "max_time", "on_time", "capacity"}
_NONNEGATIVE_QUANTITIES = {"rest", "duration", "sleep", "delay", "off_time", "charge", "discharge"}


@_mutator("yaml.quantity_extreme", "check", weight=4)
def _quantity_extreme(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _quantity_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    m = _QUANTITY.match(site.node.value)
    assert m is not None
    num, expect, what = rng.choice(_EXTREME_QUANTITY)
    if num == "NEG":
        num = m["num"][1:] if m["num"].startswith("-") else "-" + m["num"]
    if expect == EITHER:
        value = float(num)
        if site.key in _POSITIVE_QUANTITIES and value <= 0:
            expect = REFUSE
        if site.key in _NONNEGATIVE_QUANTITIES and value < 0:
            expect = REFUSE
    new = f"{num}{m['sp'] or ' '}{m['unit']}"
    old = site.node.value
    doc.replace(site, _scalar(new))
    shown = new if len(new) < 24 else f"{new[:8]}…({len(num)} digits) {m['unit']}"
    return _made(doc, f"{site.where()}: {old!r} → {shown!r}: {what}", expect)


@_mutator("yaml.deep_nesting", "check")
def _deep_nesting(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.values() if s.parent is not None])
    if site is None:
        return None
    depth = rng.choice([30, 200] if small else [30, 200, 1000, 20000, 100000])
    if rng.random() < 0.5:
        fragment = "[" * depth + "1" + "]" * depth
        what = "lists"
    else:
        fragment = "{a: " * depth + "1" + "}" * depth
        what = "mappings"
    doc.replace_raw(site, fragment)
    return _made(doc, f"{site.where()} → {depth} nested flow {what}", REFUSE)


@_mutator("yaml.alias_share", "check", refuses=False)
def _alias_share(rng: random.Random, src: Source, small: bool) -> Made | None:
    """One node used twice: an anchor on the first, an alias in place of the second."""
    doc = _doc(src)
    if doc is None:
        return None
    kind = rng.choice([MappingNode, SequenceNode, ScalarNode])
    sites = [s for s in doc.values() if isinstance(s.node, kind) and s.parent is not None]
    if len(sites) < 2:
        return None
    a, b = rng.sample(sites, 2)
    doc.replace(b, a.node)
    return _made(doc, f"{b.where()} → an alias of {a.where()}", EITHER)


@_mutator("yaml.alias_bomb", "check")
def _alias_bomb(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A 'billion laughs' list: each level ten aliases of the one below (10**levels items)."""
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _collections(doc, SequenceNode))
    if site is None or not isinstance(site.node, SequenceNode) or not site.node.value:
        return None
    levels = rng.choice([2, 3, 4] if small else [3, 5, 7, 9])
    leaf: Node = copy.deepcopy(rng.choice(site.node.value))
    node: Node = SequenceNode(_TAG + "seq", [leaf] * 10, flow_style=True)
    for _ in range(levels - 1):
        node = SequenceNode(_TAG + "seq", [node] * 10, flow_style=True)
    doc.replace(site, node)
    return _made(
        doc, f"{site.where()} → {levels} levels of 10 aliases (10**{levels} copies)", REFUSE
    )


@_mutator("yaml.merge_key", "check")
def _merge_key(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    maps = [s for s in doc.values() if isinstance(s.node, MappingNode) and s.parent is not None]
    if len(maps) < 2:
        return None
    a, b = rng.sample(maps, 2)
    assert isinstance(a.node, MappingNode) and isinstance(b.node, MappingNode)
    merge = ScalarNode(_MERGE, "<<")
    how = rng.randrange(5)
    if how == 0:  # b = {<<: *a, <b's first key>: ...}: a legitimate use
        b.node.value[1:] = []
        b.node.value.insert(0, (merge, a.node))
        return _made(doc, f"{b.where()} → {{<<: *{a.where()}, its first key}}", EITHER)
    if how == 1:  # merge a list of two mappings
        c = rng.choice(maps)
        b.node.value.insert(0, (merge, SequenceNode(_TAG + "seq", [a.node, c.node])))
        return _made(doc, f"{b.where()}: added <<: [*{a.where()}, *{c.where()}]", EITHER)
    if how == 2:  # merge itself: a recursive alias
        b.node.value.append((merge, b.node))
        return _made(doc, f"{b.where()}: added <<: (itself)", REFUSE)
    if how == 3:  # merge a scalar
        b.node.value.append((merge, _scalar("3")))
        return _made(doc, f"{b.where()}: added <<: 3", REFUSE)
    b.node.value.append((merge, a.node))
    b.node.value.append((ScalarNode(_MERGE, "<<"), a.node))
    return _made(doc, f"{b.where()}: two merge keys", REFUSE)


@_mutator("yaml.unsupported_tag", "check")
def _unsupported_tag(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.values() if s.parent is not None])
    if site is None:
        return None
    fragment, expect = rng.choice(
        [
            ("!!python/object/apply:os.system ['echo pwned']", REFUSE),
            ("!!python/name:os.system", REFUSE),
            ("!!binary aGVsbG8=", REFUSE),
            ("!!set {a, b}", REFUSE),
            ("!!omap [a: 1]", REFUSE),
            ("!custom 3", REFUSE),
            # yamlpos: a YAML 1.1 timestamp stays a string ("2001-12-14"), a valid text
            ("!!timestamp 2001-12-14", EITHER),
            ("!!int 3.5", REFUSE),
            ("!!float abc", REFUSE),
            ("!!bool maybe", REFUSE),
        ]
    )
    doc.replace_raw(site, fragment)
    return _made(doc, f"{site.where()} → {fragment}", expect)


# --------------------------------------------------------------------------------------------
# Units in quantity strings

_UNIT_GROUPS: tuple[tuple[str, ...], ...] = (
    ("V", "mV"),
    ("A", "mA", "uA"),
    ("s", "ms", "min", "h"),
    ("Ah", "mAh"),
    ("Wh",),
    ("W", "mW"),
    ("degC",),
    ("ohm",),
    ("C",),  # a C-rate, an alternative to a current where a current is asked
)
_CURRENT_LIKE = {"A", "mA", "uA", "C"}


def _wrong_unit(rng: random.Random, unit: str) -> str:
    others = [
        u
        for group in _UNIT_GROUPS
        if unit not in group
        for u in group
        if not (unit in _CURRENT_LIKE and u in _CURRENT_LIKE)
    ]
    return rng.choice(others)


@_mutator("units.wrong_unit", "check", weight=3)
def _units_wrong(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _quantity_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    m = _QUANTITY.match(site.node.value)
    assert m is not None
    new = f"{m['num']}{m['sp']}{_wrong_unit(rng, m['unit'])}"
    old = site.node.value
    # A parameter's dimension is what it is declared with: wrong only where it is used.
    expect = REFUSE if site.parent_key != "parameters" or _used(doc, site) else EITHER
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()}: {old!r} → {new!r} (another dimension)", expect)


def _used(doc: _Doc, declared: _Site) -> bool:
    """Whether the parameter declared at ``declared`` is named anywhere else in ``doc``."""
    name = re.compile(rf"\b{re.escape(str(declared.key))}\b")
    return any(
        isinstance(s.node, ScalarNode) and name.search(str(s.node.value))
        for s in doc.sites()
        if s.path[:1] != ("parameters",)
    )


@_mutator("units.missing_unit", "check")
def _units_missing(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _quantity_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    m = _QUANTITY.match(site.node.value)
    assert m is not None
    old = site.node.value
    quoted = rng.random() < 0.5
    doc.replace(site, _scalar(m["num"], quoted=quoted))
    expect = EITHER if site.parent_key == "parameters" else REFUSE
    form = "a string" if quoted else "a number"
    return _made(doc, f"{site.where()}: {old!r} → {m['num']} ({form}, no unit)", expect)


_UNICODE_DIGITS: tuple[tuple[int, str], ...] = (
    (0x0660, "Arabic-Indic"),
    (0xFF10, "fullwidth"),
    (0x0966, "Devanagari"),
    (0x1D7CE, "mathematical bold"),
)


def _unicode_digits(rng: random.Random, text: str) -> tuple[str, str]:
    zero, name = rng.choice(_UNICODE_DIGITS)
    positions = [i for i, ch in enumerate(text) if ch.isascii() and ch.isdigit()]
    if not positions:
        return text, name
    if rng.random() < 0.5:  # one digit only
        positions = [rng.choice(positions)]
    chars = list(text)
    for i in positions:
        chars[i] = chr(zero + int(chars[i]))
    return "".join(chars), name


@_mutator("units.unicode_digits", "check", weight=3)
def _units_unicode_digits(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _quantity_sites(doc) + _number_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new, name = _unicode_digits(rng, old)
    if new == old:
        return None
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()}: {old!r} → {new!r} ({name} digits)", REFUSE)


_UNIT_GARBAGE: tuple[tuple[str, Expect], ...] = (
    ("{num} {unit}x", REFUSE),
    ("{num} furlong", REFUSE),
    ("{num} {upper}", REFUSE),
    ("{num} {unit} {unit}", REFUSE),
    ("{num}{unit}", EITHER),
    ("{num},5 {unit}", REFUSE),
    ("--{num} {unit}", REFUSE),
    ("0x10 {unit}", REFUSE),
    ("1_000 {unit}", REFUSE),
    ("{num}e2 {unit}", EITHER),
    ("+{num} {unit}", EITHER),
    (" {num} {unit} ", EITHER),
    ("{num}\u00a0{unit}", EITHER),  # a no-break space, as word processors write it
    ("{unit}", REFUSE),
    ("{num} {unit}/s", EITHER),
)


@_mutator("units.garbage", "check", weight=3)
def _units_garbage(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _quantity_sites(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    m = _QUANTITY.match(site.node.value)
    assert m is not None
    pattern, expect = rng.choice(_UNIT_GARBAGE)
    unit = m["unit"]
    upper = unit.upper() if unit != unit.upper() else unit.lower()
    new = pattern.format(num=m["num"], unit=unit, upper=upper)
    if pattern == "{num} {unit}/s" and f"{unit}/s" not in ("V/s", "mV/s"):
        expect = REFUSE
    old = site.node.value
    doc.replace(site, _scalar(new, quoted=True))
    return _made(doc, f"{site.where()}: {old!r} → {new!r}", expect)


# --------------------------------------------------------------------------------------------
# References: step ids, device and tag names


def _ids(doc: _Doc) -> dict[str, _Site]:
    """Defined names: ``id``/``name`` values, the keys of ``devices`` and ``parameters``."""
    out: dict[str, _Site] = {}
    for s in doc.sites():
        if not isinstance(s.node, ScalarNode):
            continue
        named = not s.is_key and s.key in ("id", "name")
        keyed = s.is_key and s.parent_key in ("devices", "parameters") and len(s.path) == 2
        if named or keyed:
            out.setdefault(str(s.node.value), s)
    return out


def _references(doc: _Doc) -> list[_Site]:
    ids = _ids(doc)
    return [
        s
        for s in doc.values()
        if isinstance(s.node, ScalarNode)
        and s.node.tag == _STR
        and str(s.node.value) in ids
        and s.key not in ("id", "name", "recipe", "bench", "driver", "description", "comment")
    ]


@_mutator("refs.unknown", "check", weight=3)
def _refs_unknown(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _references(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new = rng.choice([f"no_such_{old}", _typo(rng, old)])
    if new == old or new in _ids(doc):
        return None
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()}: reference {old!r} → unknown {new!r}", REFUSE)


def _steps(doc: _Doc) -> list[_Site]:
    return [
        s
        for s in doc.values()
        if isinstance(s.node, MappingNode) and len(s.path) == 2 and s.path[0] == "steps"
    ]


def _entry(node: MappingNode, key: str) -> int | None:
    for i, (k, _) in enumerate(node.value):
        if isinstance(k, ScalarNode) and k.value == key:
            return i
    return None


@_mutator("refs.goto_self", "check", weight=3)
def _refs_goto_self(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A step that jumps to itself: at once (``goto``, ``true``) or on a condition."""
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _steps(doc))
    if site is None or not isinstance(site.node, MappingNode):
        return None
    i = _entry(site.node, "id")
    if i is None:
        return None
    own = str(site.node.value[i][1].value)
    how = rng.randrange(4)
    g = _entry(site.node, "goto")
    if how == 0 or g is not None:  # the step becomes {id: X, goto: X}
        site.node.value[:] = [site.node.value[i], (_scalar("goto"), _scalar(own))]
        return _made(doc, f"{site.where()} → {{id: {own}, goto: {own}}}", REFUSE)
    if how == 1:  # until: [true: <self>] (the issue's zero-time loop)
        u = _entry(site.node, "until")
        # A step named like an action ("hold", "end") is reached by "goto <id>": the bare
        # word is the action (every-feature.yaml has a step 'hold'; [true: hold] holds).
        jump = f"goto {own}" if own in ("next", "next_cycle", "end", "hold") else own
        until = SequenceNode(
            _TAG + "seq",
            [MappingNode(_TAG + "map", [(_scalar("true"), _scalar(jump))], flow_style=True)],
        )
        if u is None:
            site.node.value.append((_scalar("until"), until))
        else:
            site.node.value[u] = (site.node.value[u][0], until)
        how_ = f"{site.where()}: until: [true: {jump}] (jumps to itself at once)"
        return _made(doc, how_, REFUSE, PENDING_ZERO_TIME)
    if how == 2:  # an existing condition jumps to the step itself
        u = _entry(site.node, "until")
        if u is None or not isinstance(site.node.value[u][1], SequenceNode):
            return None
        conds = site.node.value[u][1].value
        if not conds or not isinstance(conds[0], MappingNode) or not conds[0].value:
            return None
        k, _ = conds[0].value[0]
        conds[0].value[0] = (k, _scalar(own))
        return _made(doc, f"{site.where()}: until[0] → {own} (itself)", EITHER)
    # the operator's advance jumps to the step itself
    a = _entry(site.node, "advance")
    entry = (_scalar("advance"), _scalar(own))
    if a is None:
        site.node.value.append(entry)
    else:
        site.node.value[a] = entry
    return _made(doc, f"{site.where()}: advance: {own} (itself)", EITHER)


@_mutator("refs.duplicate_id", "check", weight=2)
def _refs_duplicate_id(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    names = [
        s
        for s in doc.values()
        if isinstance(s.node, ScalarNode)
        and s.key in ("id", "name")
        and isinstance(s.path[-2], int)
    ]
    if len(names) < 2:
        return None
    a, b = rng.sample(names, 2)
    if a.path[:-2] != b.path[:-2] or a.node.value == b.node.value:  # same list: steps, tags…
        return None
    old = b.node.value
    doc.replace(b, _scalar(str(a.node.value)))
    return _made(doc, f"{b.where()}: {old!r} → {a.node.value!r} (the name of {a.where()})", REFUSE)


# --------------------------------------------------------------------------------------------
# Loops that let no time pass, and the documented bounds of a recipe (issue 9)

# Step lists put first in a recipe (so that they run): the issue's zero-time loops, each a
# cycle of steps that can all complete in no time; the last one lets time pass.
_ZERO_TIME_LOOPS: tuple[tuple[str, str, Expect], ...] = (
    ("[{id: zt_a, rest: 0 s}, {id: zt_b, goto: zt_a}]", "rest: 0 s then a goto back", REFUSE),
    ("[{id: zt_a, sleep: 0 s}, {id: zt_b, goto: zt_a}]", "sleep: 0 s then a goto back", REFUSE),
    ("[{id: zt_a, rest: 1 h, until: [{true: zt_a}]}]", "until: [true: <itself>]", REFUSE),
    (
        "[{id: zt_a, rest: 0 s}, {id: zt_b, goto: zt_c}, {id: zt_c, goto: zt_a}]",
        "a goto chain into a 0 s step",
        REFUSE,
    ),
    ("[{id: zt_a, rest: 1 s}, {id: zt_b, goto: zt_a}]", "a loop of 1 s steps", EITHER),
)


def _raw_name(what: str) -> str:
    return f"{_RAW}_{what}"


def _raw(doc: _Doc, what: str) -> ScalarNode:
    """A placeholder scalar that ``doc.emit()`` replaces by ``doc.raw[_raw_name(what)]``."""
    return ScalarNode(_STR, _raw_name(what))


def _recipe(src: Source) -> tuple[_Doc, dict[str, int]] | None:
    """The recipe's document and the index of each top-level key (None for an I/O map)."""
    doc = _doc(src)
    if doc is None or not isinstance(doc.root, MappingNode):
        return None
    top = {str(k.value): i for i, (k, _) in enumerate(doc.root.value) if isinstance(k, ScalarNode)}
    if "recipe" not in top or "steps" not in top:
        return None
    return doc, top


@_mutator("loops.zero_time", "check", weight=3)
def _loops_zero_time(rng: random.Random, src: Source, small: bool) -> Made | None:
    found = _recipe(src)
    if found is None:
        return None
    doc, top = found
    steps = doc.root.value[top["steps"]][1]
    if not isinstance(steps, SequenceNode):
        return None
    group = None
    if rng.random() < 0.2:  # a group of duration 0 s around a step, and a goto back to it
        loop = "[{id: zt_a, rest: 1 h}, {id: zt_b, goto: zt_a}]"
        group = "[{id: zt_g, steps: [zt_a], duration: 0 s}]"
        what, expect = "a group with duration: 0 s and a goto back", REFUSE
    else:
        loop, what, expect = rng.choice(_ZERO_TIME_LOOPS)
    # The loop's text, then the recipe's own steps (flow style so that one fragment fits).
    for node in _Doc.walk(steps):
        if isinstance(node, MappingNode | SequenceNode):
            node.flow_style = True
    own = yaml.serialize(steps, Dumper=yaml.SafeDumper, allow_unicode=True, width=1 << 20)
    own = own.strip().removesuffix("...").strip()
    doc.root.value[top["steps"]] = (doc.root.value[top["steps"]][0], _raw(doc, "STEPS"))
    doc.raw[_raw_name("STEPS")] = loop[:-1] + ", " + own[1:]
    if group is not None:  # after the steps: an insertion moves the steps' index
        pair = (_scalar("groups"), _raw(doc, "GROUPS"))
        if "groups" in top:
            doc.root.value[top["groups"]] = pair
        else:
            doc.root.value.insert(top["steps"], pair)
        doc.raw[_raw_name("GROUPS")] = group
    pending = PENDING_ZERO_TIME if expect == REFUSE else ""
    return _made(doc, f"steps: first {what}", expect, pending)


@_mutator("recipe.bounds", "check", weight=2)
def _recipe_bounds(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A value at or just past a documented bound (README "Input limits", the model)."""
    found = _recipe(src)
    if found is None:
        return None
    doc, top = found
    choices: list[tuple[str, str, Expect, str]] = [
        ("cycles", str(MAX_CYCLES + 1), REFUSE, ""),
        ("cycles", str(MAX_CYCLES), EITHER, ""),
        ("cycles", "0", REFUSE, ""),
        ("initial_charge", "1e300 Ah", REFUSE, PENDING_COUNTS),
        ("initial_charge", f"{MAX_INITIAL_CHARGE_AH * 10:g} Ah", REFUSE, PENDING_COUNTS),
        ("initial_charge", "1 Ah", EITHER, ""),
    ]
    key, value, expect, pending = rng.choice(choices)
    pair = (_scalar(key), _scalar(value))
    if key in top:
        doc.root.value[top[key]] = pair
    else:
        doc.root.value.insert(top["steps"], pair)
    return _made(doc, f"{key}: {value}", expect, pending)


# Keys whose value is a [low, high] pair (recipe limits, I/O map channel limits), and the
# min/max keys of a profile row (seed 002 §2.3: a per-row V/I/T window).
_WINDOW_KEYS = {"voltage", "current", "temperature", "voltage_v", "current_a"}
_ROW_WINDOWS = (("v_min", "v_max"), ("i_min", "i_max"), ("t_min", "t_max"))


@_mutator("limits.inverted", "check", "profile", weight=2)
def _limits_inverted(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A window written high first: [4.2 V, 2.5 V], v_min above v_max."""
    if src.target == "profile":
        t = _Csv(src)
        cells = [(i, k) for i in t.data_rows() for k, c in enumerate(t.rows[i]) if "/" in c]
        if not cells:
            return None
        i, k = rng.choice(cells)
        low, high = t.rows[i][k].split("/", 1)
        if low.strip() == high.strip():
            return None
        t.rows[i][k] = f"{high}/{low}"
        return t.made(f"line {i + 1}: window {low}/{high} → {high}/{low}", REFUSE)
    doc = _doc(src)
    if doc is None:
        return None
    pairs = [
        s
        for s in doc.values()
        if isinstance(s.node, SequenceNode)
        and s.key in _WINDOW_KEYS
        and len(s.node.value) == 2
        and all(isinstance(n, ScalarNode) and n.tag != _NULL for n in s.node.value)
        and s.node.value[0].value != s.node.value[1].value
    ]
    rows = [
        (s, lo, hi)
        for s in doc.values()
        if isinstance(s.node, MappingNode) and "rows" in s.path  # not `parameters: {v_min: …}`
        for lo, hi in _ROW_WINDOWS
        if _entry(s.node, lo) is not None and _entry(s.node, hi) is not None
    ]
    if rows and (not pairs or rng.random() < 0.5):
        site, lo, hi = rng.choice(rows)
        assert isinstance(site.node, MappingNode)
        a, b = _entry(site.node, lo), _entry(site.node, hi)
        assert a is not None and b is not None
        (ka, va), (kb, vb) = site.node.value[a], site.node.value[b]
        if va.value == vb.value:
            return None
        site.node.value[a], site.node.value[b] = (ka, vb), (kb, va)
        how = f"{site.where()}: {lo} {va.value} and {hi} {vb.value} swapped"
        return _made(doc, how, REFUSE)
    pair = _pick(rng, pairs)
    if pair is None or not isinstance(pair.node, SequenceNode):
        return None
    low, high = pair.node.value
    pair.node.value[:] = [high, low]
    return _made(
        doc, f"{pair.where()}: [{low.value}, {high.value}] → [{high.value}, {low.value}]", REFUSE
    )


# --------------------------------------------------------------------------------------------
# Expressions in recipes (until conditions, interlock, supervision error)


def _expressions(doc: _Doc) -> list[_Site]:
    out: list[_Site] = []
    for s in doc.sites():
        if not isinstance(s.node, ScalarNode) or s.node.tag != _STR:
            continue
        in_until = "until" in [p for p in s.path if isinstance(p, str)]
        if (s.is_key and in_until) or (not s.is_key and s.key in ("interlock", "error")):
            out.append(s)
    return out


_KEYWORDS = {"and", "or", "not", "true", "false", "abs", "min", "max"}


def _expr_mutations(rng: random.Random, text: str, small: bool) -> tuple[str, str, Expect]:
    names = [
        m
        for m in re.finditer(r"\b[a-z_][a-z0-9_]*\b", text)
        if m[0] not in _KEYWORDS and not re.fullmatch(r"m?[AVWhs]|min|degC|mAh|Ah|C", m[0])
    ]
    depth = rng.choice([50, 200] if small else [50, 1000, 100000])
    terms = rng.choice([20, 200] if small else [200, 20000])
    choices: list[tuple[str, str, Expect]] = [
        (text.replace("<=", "=<", 1), "operator <= → =<", REFUSE),
        (text.replace(">=", "=>", 1), "operator >= → =>", REFUSE),
        (text + " and", "a dangling 'and'", REFUSE),
        ("(" + text, "an unclosed parenthesis", REFUSE),
        (text + " and 1 / 0 > 0", "a division by zero", EITHER),
        (f"{text} and {'9' * 5000} > 0", "a 5000-digit literal", EITHER),
        ("__import__('os').system('true')", "Python code", REFUSE),
        ("voltage.__class__", "an attribute access", REFUSE),
        ("(" * depth + text + ")" * depth, f"{depth} nested parentheses", EITHER),
        (" and ".join([text] * terms), f"{terms} terms joined by 'and'", EITHER),
        ("not " * depth + text, f"'not' {depth} times", EITHER),
        ("", "an empty condition", REFUSE),
    ]
    if names:
        m = rng.choice(names)
        choices.append(
            (text[: m.start()] + m[0] + "x" + text[m.end() :], f"name {m[0]} → {m[0]}x", REFUSE)
        )
    qty = list(re.finditer(r"(\d+(?:\.\d+)?)\s*([A-Za-z]+)", text))
    if qty:
        m = rng.choice(qty)
        if m[2] in {u for g in _UNIT_GROUPS for u in g}:
            new_unit = _wrong_unit(rng, m[2])
            choices.append(
                (
                    text[: m.start(2)] + new_unit + text[m.end(2) :],
                    f"unit {m[2]} → {new_unit}",
                    REFUSE,
                )
            )
    if any(ch.isdigit() for ch in text):
        uni, name = _unicode_digits(rng, text)
        choices.append((uni, f"{name} digits", REFUSE))
    new, what, expect = rng.choice(choices)
    if new == text:
        return new, what, EITHER
    return new, what, expect


@_mutator("expr.condition", "check", weight=4)
def _expr_condition(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _expressions(doc))
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new, what, expect = _expr_mutations(rng, old, small)
    if new == old:
        return None
    doc.replace(site, _scalar(new, quoted=True))
    return _made(doc, f"{site.where()}: {old!r}: {what}", expect)


# --------------------------------------------------------------------------------------------
# Text-level mutations of YAML files (comments kept)


def _lines(text: str) -> list[str]:
    return text.splitlines(keepends=True)


@_mutator("text.tabs", "check", weight=2)
def _text_tabs(rng: random.Random, src: Source, small: bool) -> Made | None:
    lines = _lines(src.text)
    indented = [
        i for i, ln in enumerate(lines) if ln.startswith("  ") and not ln.lstrip().startswith("#")
    ]
    colon = [i for i, ln in enumerate(lines) if ": " in ln and not ln.lstrip().startswith("#")]
    if rng.random() < 0.7 and indented:
        i = rng.choice(indented)
        lines[i] = "\t" + lines[i][2:]
        how, expect = f"line {i + 1}: two indentation spaces → a tab", REFUSE
    elif colon:
        i = rng.choice(colon)
        lines[i] = lines[i].replace(": ", ":\t", 1)
        how, expect = f"line {i + 1}: the space after ':' → a tab", EITHER
    else:
        return None
    return Made("".join(lines).encode("utf-8"), how, expect)


@_mutator("text.bom", "check", "chadeche", "prm", "profile", weight=2)
def _text_bom(rng: random.Random, src: Source, small: bool) -> Made | None:
    how = rng.randrange(4)
    if how == 0:
        return Made(codecs.BOM_UTF8 + src.data, "a UTF-8 byte order mark added", EITHER)
    if how == 1:
        return Made(codecs.BOM_UTF8 * 2 + src.data, "two UTF-8 byte order marks", EITHER)
    if how == 2:
        data = codecs.BOM_UTF16_LE + src.text.encode("utf-16-le")
        return Made(data, "the whole file as UTF-16 LE with its BOM (Notepad's 'Unicode')", REFUSE)
    lines = src.data.splitlines(keepends=True)
    i = rng.randrange(len(lines))
    lines[i] = codecs.BOM_UTF8 + lines[i]
    return Made(b"".join(lines), f"a UTF-8 BOM at the start of line {i + 1}", EITHER)


# Byte sequences that are not UTF-8 (the first is also not CP1252).
_BAD_UTF8: tuple[tuple[bytes, str], ...] = (
    (b"\x81", "0x81 (undefined in CP1252 too)"),
    (b"\xff", "0xFF"),
    (b"\xc3\x28", "a broken 2-byte sequence"),
    (b"\x80", "a lone continuation byte"),
    (b"\xc0\xaf", "an overlong '/'"),
    (b"\xed\xa0\x80", "a UTF-16 surrogate"),
    (b"\xf4\x90\x80\x80", "a code point beyond U+10FFFF"),
    (b"\xe9", "a CP1252 'é'"),
    (b"\x92", "a CP1252 right quote"),
)


@_mutator("text.invalid_utf8", "check", "prm", "profile", weight=2)
def _text_invalid_utf8(rng: random.Random, src: Source, small: bool) -> Made | None:
    bad, what = rng.choice(_BAD_UTF8)
    at = rng.randrange(len(src.data) + 1)
    data = src.data[:at] + bad + src.data[at:]
    line = src.data[:at].count(b"\n") + 1
    # YAML is UTF-8 only; a parameter file or a profile may be CP1252 (Excel, Notepad), so
    # there only a byte CP1252 leaves undefined is certainly wrong.
    expect = REFUSE if src.target == "check" or bad == b"\x81" else EITHER
    return Made(data, f"{what} inserted at byte {at} (line {line})", expect)


@_mutator("text.truncate", "check", "chadeche", "prm", "profile", weight=3)
def _text_truncate(rng: random.Random, src: Source, small: bool) -> Made | None:
    at = rng.randrange(len(src.data))
    line = src.data[:at].count(b"\n") + 1
    return Made(src.data[:at], f"truncated at byte {at} of {len(src.data)} (line {line})", EITHER)


_CONTROL: tuple[tuple[str, Expect], ...] = (
    ("\x00", REFUSE),
    ("\x07", REFUSE),
    ("\x1b", REFUSE),
    ("\x7f", REFUSE),
    ("\ufffe", REFUSE),
    ("\u2028", EITHER),
    ("\x85", EITHER),
    ("\u200b", EITHER),
    ("\r", EITHER),
    ("\u202e", EITHER),  # right-to-left override
)


@_mutator("text.control_char", "check", weight=2)
def _text_control(rng: random.Random, src: Source, small: bool) -> Made | None:
    text = src.text
    ch, expect = rng.choice(_CONTROL)
    at = rng.randrange(len(text) + 1)
    line = text[:at].count("\n") + 1
    new = text[:at] + ch + text[at:]
    return Made(new.encode("utf-8"), f"U+{ord(ch):04X} inserted at line {line}", expect)


def _newlines(rng: random.Random, src: Source) -> tuple[bytes, str]:
    text = src.data.replace(b"\r\n", b"\n")
    how = rng.randrange(3)
    if how == 0:
        return text.replace(b"\n", b"\r\n"), "line ends → CRLF"
    if how == 1:
        return text.replace(b"\n", b"\r"), "line ends → CR only (classic Mac)"
    lines = text.split(b"\n")
    return (
        b"".join(ln + rng.choice([b"\n", b"\r\n", b"\r"]) for ln in lines[:-1]) + lines[-1],
        "line ends → a random mix of LF, CRLF and CR",
    )


@_mutator("text.line_ends", "check", "prm", "profile", weight=1, refuses=False)
def _text_line_ends(rng: random.Random, src: Source, small: bool) -> Made | None:
    data, how = _newlines(rng, src)
    return Made(data, how, EITHER)


@_mutator("text.document", "check", weight=2)
def _text_document(rng: random.Random, src: Source, small: bool) -> Made | None:
    text = src.text
    new, how, expect = rng.choice(
        [
            ("", "empty file", REFUSE),
            ("   \n\n", "only blank lines", REFUSE),
            ("# only a comment\n", "only a comment", REFUSE),
            ("---\n", "only a document start", REFUSE),
            ("null\n", "a null document", REFUSE),
            ("[]\n", "an empty list", REFUSE),
            ("42\n", "a number", REFUSE),
            ('"a string"\n', "a string", REFUSE),
            (f"{text}\n---\n{text}", "two documents", REFUSE),
            (f"---\n{text}", "an explicit document start", EITHER),
            (f"{text}\n...\n", "an explicit document end", EITHER),
            (f"%YAML 1.1\n---\n{text}", "a %YAML directive", EITHER),
            (f"%YAML 9.9\n---\n{text}", "a %YAML 9.9 directive", REFUSE),
        ]
    )
    return Made(new.encode("utf-8"), how, expect)


@_mutator("text.lines", "check", weight=3, refuses=False)
def _text_lines(rng: random.Random, src: Source, small: bool) -> Made | None:
    lines = _lines(src.text)
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if len(body) < 2:
        return None
    i = rng.choice(body)
    how = rng.randrange(4)
    if how == 0:
        del lines[i]
        what = f"line {i + 1} deleted"
    elif how == 1:
        lines.insert(i, lines[i])
        what = f"line {i + 1} duplicated"
    elif how == 2:
        j = body[(body.index(i) + 1) % len(body)]
        lines[i], lines[j] = lines[j], lines[i]
        what = f"lines {i + 1} and {j + 1} swapped"
    else:
        lines[i] = " " + lines[i]
        what = f"line {i + 1} indented by one more space"
    return Made("".join(lines).encode("utf-8"), what, EITHER)


# --------------------------------------------------------------------------------------------
# Sizes (megabytes: the full run only)


def _count_choices(limit: int) -> list[int]:
    """Below, just above and far above a documented count limit."""
    return [limit * 9 // 10, limit + 1, limit * 3]


def _flow_items(site: _Site | None, count: int, minimal: str | None) -> str:
    """``count`` items for the list at ``site`` in flow style, as text (a deep copy of the
    node graph per item would take minutes): copies of its own items with unique ids or
    names, or ``minimal`` with ``{k}`` for the number."""
    if minimal is not None:
        return "[" + ", ".join(minimal.format(k=k) for k in range(count)) + "]"
    assert site is not None and isinstance(site.node, SequenceNode)
    templates: list[str] = []
    for item in site.node.value:
        item = copy.deepcopy(item)
        for node in _Doc.walk(item):
            if isinstance(node, MappingNode | SequenceNode):
                node.flow_style = True
        if isinstance(item, MappingNode):
            for key in ("id", "name", "description"):
                e = _entry(item, key)
                if e is not None and key == "description":
                    del item.value[e]  # shorter copies: more items under the byte limit
                elif e is not None:
                    name = item.value[e][1].value
                    item.value[e] = (item.value[e][0], ScalarNode(_STR, f"{name}_MUTID"))
        one = yaml.serialize(item, Dumper=yaml.SafeDumper, allow_unicode=True, width=1 << 20)
        templates.append(one.strip().removesuffix("...").strip())
    return (
        "["
        + ", ".join(templates[k % len(templates)].replace("MUTID", str(k)) for k in range(count))
        + "]"
    )


@_mutator("size.many_items", "check", weight=2, large=True)
def _size_many_items(rng: random.Random, src: Source, small: bool) -> Made | None:
    """More steps, groups or tags than README "Input limits" allows, or just fewer."""
    doc = _doc(src)
    if doc is None or not isinstance(doc.root, MappingNode):
        return None
    top = {str(k.value): i for i, (k, _) in enumerate(doc.root.value) if isinstance(k, ScalarNode)}
    kinds = [
        k for k in ("steps", "tags", "groups") if k in top or (k == "groups" and "steps" in top)
    ]
    if not kinds:
        return None
    kind = rng.choice(kinds)
    limit = {"steps": MAX_RECIPE_STEPS, "tags": MAX_IO_MAP_TAGS, "groups": MAX_RECIPE_GROUPS}[kind]
    count = rng.choice(_count_choices(limit))
    expect = REFUSE if count > limit else EITHER
    pending = PENDING_COUNTS if kind in ("steps", "groups") and count > limit else ""
    if kind == "groups":
        steps = doc.root.value[top["steps"]][1]
        first = steps.value[0] if isinstance(steps, SequenceNode) and steps.value else None
        e = _entry(first, "id") if isinstance(first, MappingNode) else None
        if first is None or e is None or not isinstance(first, MappingNode):
            return None
        step_id = first.value[e][1].value
        fragment = _flow_items(None, count, "{{id: g{k}, steps: [" + str(step_id) + "]}}")
        pair = (_scalar("groups"), _raw(doc, "GROUPS"))
        if "groups" in top:
            doc.root.value[top["groups"]] = pair
        else:
            doc.root.value.insert(top["steps"], pair)
        doc.raw[_raw_name("GROUPS")] = fragment
        return _made(doc, f"groups: {count} groups (limit {limit:,})", expect, pending)
    site = next(s for s in doc.values() if s.path == (kind,))
    if not isinstance(site.node, SequenceNode) or not site.node.value:
        return None
    minimal = "{{id: s{k}, rest: 1 s}}" if kind == "steps" else None
    doc.replace_raw(site, _flow_items(site, count, minimal))
    what = "minimal steps" if minimal else "copies with unique names"
    return _made(doc, f"{site.where()}: {count:,} items, {what} (limit {limit:,})", expect, pending)


@_mutator("size.huge_text", "check", "chadeche", "prm", "profile", weight=2, large=True)
def _size_huge_text(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A long comment, description or value: half the byte limit, or above it."""
    limit = BYTE_LIMIT[src.target]
    size = rng.choice([limit // 2, limit + 1, 4 * limit if limit <= MAX_YAML_BYTES else limit + 1])
    if src.target == "check":
        if rng.random() < 0.5:
            data = src.data + b"# " + b"x" * size + b"\n"
            return Made(data, f"a comment of {size:,} bytes appended", EITHER)
        doc = _doc(src)
        if doc is None or not isinstance(doc.root, MappingNode):
            return None
        i = _entry(doc.root, "description")
        pair = (_scalar("description"), _scalar("x" * size))
        if i is None:
            doc.root.value.append(pair)
        else:
            doc.root.value[i] = pair
        return _made(doc, f"description of {size:,} bytes", EITHER)
    if src.target == "prm":
        data = src.data + b"-f " + b"x" * size + b"\n"
        return Made(data, f"an -f value of {size:,} bytes", EITHER)
    if src.target == "profile":
        data = src.data + b"# " + b"x" * size + b"\n"
        return Made(data, f"a comment line of {size:,} bytes appended", EITHER)
    rows = src.text.splitlines(keepends=True)
    if len(rows) < 2:
        return None
    i = rng.randrange(1, len(rows))
    cells = rows[i].rstrip("\r\n").split("\t")
    end = rows[i][len(rows[i].rstrip("\r\n")) :]
    cells[-1] = "#" + "x" * size
    rows[i] = "\t".join(cells) + end
    return Made(_encode(src, "".join(rows)), f"line {i + 1}: a comment of {size:,} bytes", EITHER)


# --------------------------------------------------------------------------------------------
# Chadèche sequence files (seed 000 §III.D): tab-separated, a header, eleven columns

_COLS = ("ADR", "C/D", "mA", "SD", "TL", "TH", "LmAh", "HmAh", "TRUE", "CTRLZ", "COMMENT")
_ACTION_COLS = range(4, 10)


def _encode(src: Source, text: str) -> bytes:
    """``text`` in the source's encoding (UTF-8 when that cannot hold it)."""
    try:
        return text.encode(src.encoding)
    except UnicodeEncodeError:
        return text.encode("utf-8")


class _Table:
    """A sequence file as lines of cells, with each line's own line end."""

    def __init__(self, src: Source) -> None:
        self.src = src
        self.rows: list[list[str]] = []
        self.ends: list[str] = []
        for line in src.text.splitlines(keepends=True):
            body = line.rstrip("\r\n")
            self.rows.append(body.split("\t"))
            self.ends.append(line[len(body) :])

    def data_rows(self) -> list[int]:
        """Indexes of the rows with eleven fields or more, after the header."""
        return [i for i, r in enumerate(self.rows) if i > 0 and len(r) >= len(_COLS)]

    def text(self) -> str:
        return "".join("\t".join(r) + e for r, e in zip(self.rows, self.ends, strict=True))

    def made(self, how: str, expect: Expect, pending: str = "") -> Made:
        return Made(_encode(self.src, self.text()), how, expect, pending)


def _cell(table: _Table, i: int, k: int) -> str:
    return f"line {i + 1} {_COLS[k]} {table.rows[i][k]!r}"


@_mutator("chadeche.field_count", "chadeche", weight=3)
def _ch_field_count(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    how = rng.randrange(4)
    if how == 0:
        k = rng.randrange(10)
        where = _cell(t, i, k)
        del t.rows[i][k]
        return t.made(f"{where}: field removed", REFUSE)
    if how == 1:
        k = rng.randrange(1, 11)
        t.rows[i].insert(k, "0")
        return t.made(f"line {i + 1}: a field '0' inserted before {_COLS[k]}", REFUSE)
    if how == 2:
        t.rows[i].append("")
        return t.made(f"line {i + 1}: an empty field after the comment", EITHER)
    n = rng.randrange(1, 10)
    t.rows[i][n:] = []
    return t.made(f"line {i + 1}: only the first {n} fields kept", REFUSE)


@_mutator("chadeche.letter", "chadeche", weight=2)
def _ch_letter(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    new, expect = rng.choice(
        [("Z", REFUSE), ("c", EITHER), ("d", EITHER), ("", REFUSE), ("CD", REFUSE), ("0", REFUSE)]
    )
    where = _cell(t, i, 1)
    t.rows[i][1] = new
    return t.made(f"{where} → {new!r}", expect)


@_mutator("chadeche.action", "chadeche", weight=3)
def _ch_action(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    k = rng.choice(list(_ACTION_COLS))
    new, expect = rng.choice(
        [
            ("X", REFUSE),
            ("s", EITHER),
            ("i", EITHER),
            ("", REFUSE),
            ("SS", REFUSE),
            ("0", REFUSE),
            ("-1", REFUSE),
            ("S I", REFUSE),
        ]
    )
    where = _cell(t, i, k)
    t.rows[i][k] = new
    return t.made(f"{where} → {new!r}", expect)


_NUMERIC = (0, 2, 3)  # ADR, mA, SD


@_mutator("chadeche.huge_number", "chadeche", weight=4)
def _ch_huge_number(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    # a number cell, or an action cell made a goto (TRUE is column 8)
    k = rng.choice([*_NUMERIC, 8, rng.choice(list(_ACTION_COLS))])
    digits = rng.choice([400, 5000, 20000])
    new = rng.choice(["9", "1"]) + "0" * (digits - 1)
    where = _cell(t, i, k)
    t.rows[i][k] = new
    return t.made(f"{where} → a {digits}-digit number", REFUSE if k != 3 else EITHER)


@_mutator("chadeche.number_format", "chadeche", weight=3)
def _ch_number_format(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    k = rng.choice(_NUMERIC)
    old = t.rows[i][k].strip()
    new, expect = rng.choice(
        [
            (f"-{old}", REFUSE if old.strip("0") else EITHER),
            (f"{old}.5", REFUSE),
            (f"{old},5", REFUSE),
            (f"{old}e1", REFUSE),
            (f"0{old}", EITHER),
            (f"+{old}", EITHER),
            (f" {old} ", EITHER),
            (f"{old}\u00a0", EITHER),  # a no-break space: blank to strip() and to atoi
            ("1_000", REFUSE),
            ("0x10", REFUSE),
            (f"{old} mA", REFUSE),
            ("", REFUSE),
        ]
    )
    where = _cell(t, i, k)
    t.rows[i][k] = new
    return t.made(f"{where} → {new!r}", expect)


@_mutator("chadeche.unicode_digits", "chadeche", weight=3)
def _ch_unicode_digits(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    cells = [k for k in range(10) if any(c.isdigit() for c in t.rows[i][k])]
    if not cells:
        return None
    k = rng.choice(cells)
    where = _cell(t, i, k)
    new, name = _unicode_digits(rng, t.rows[i][k])
    t.rows[i][k] = new
    return t.made(f"{where} → {new!r} ({name} digits)", REFUSE)


@_mutator("chadeche.line_ends", "chadeche", weight=2, refuses=False)
def _ch_line_ends(rng: random.Random, src: Source, small: bool) -> Made | None:
    data, how = _newlines(rng, src)
    return Made(data, how, EITHER)


@_mutator("chadeche.encoding", "chadeche", weight=3)
def _ch_encoding(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    how = rng.randrange(5)
    if how == 0:  # the whole file as CP1252, with accents in a comment
        t.rows[i][10] = t.rows[i][10] + " é à ç €"
        try:
            data = t.text().encode("cp1252")
        except UnicodeEncodeError:  # the source holds a character CP1252 has not (٣)
            return None
        return Made(data, f"line {i + 1}: accents in the comment, CP1252", EITHER)
    if how == 1:
        t.rows[i][10] = t.rows[i][10] + " é"
        return Made(t.text().encode("utf-8"), f"line {i + 1}: 'é' in the comment, UTF-8", EITHER)
    bad, what = rng.choice(
        [(b"\x81", "0x81 (undefined in CP1252)"), (b"\x00", "NUL"), (b"\xe9", "CP1252 'é'")]
    )
    k = 10 if how == 2 else rng.choice(_NUMERIC)
    lines = src.data.splitlines(keepends=True)
    if i >= len(lines):
        return None
    cells = lines[i].split(b"\t")
    if k >= len(cells):
        return None
    cells[k] = cells[k] + bad
    lines[i] = b"\t".join(cells)
    expect = REFUSE if k != 10 or bad == b"\x81" else EITHER
    return Made(b"".join(lines), f"line {i + 1} {_COLS[k]}: byte {what} appended", expect)


@_mutator("chadeche.goto", "chadeche", weight=3)
def _ch_goto(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    own = t.rows[i][0].strip()
    k = rng.choice([8, rng.choice(list(_ACTION_COLS))])
    new, expect, what = rng.choice(
        [
            (own, REFUSE if k == 8 else EITHER, "its own ADR"),
            ("99", REFUSE, "a missing ADR"),
            ("0", REFUSE, "ADR 0"),
        ]
    )
    pending = ""
    if k == 8 and new == own:
        # a jump to itself on TRUE, at 0 mA: the row ends at its first evaluation, forever
        t.rows[i][2] = "0"
        pending = PENDING_ZERO_TIME
    where = _cell(t, i, k)
    t.rows[i][k] = new
    return t.made(f"{where} → goto {new} ({what})", expect, pending)


@_mutator("chadeche.time", "chadeche", weight=2)
def _ch_time(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    new, expect = rng.choice(
        [
            ("25:99", REFUSE),
            ("24:00", EITHER),
            ("20:60", REFUSE),
            ("+999:99", REFUSE),
            ("20:0", REFUSE),
            ("20:00:00", REFUSE),
            ("+00:00", EITHER),
            ("+999:59", EITHER),
            ("7:05", EITHER),
            ("-01:00", REFUSE),
            ("٢٠:٠٠", REFUSE),
        ]
    )
    where = _cell(t, i, 8)
    t.rows[i][8] = new
    return t.made(f"{where} → {new!r}", expect)


@_mutator("chadeche.rows", "chadeche", weight=3)
def _ch_rows(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if len(rows) < 2:
        return None
    i = rng.choice(rows)
    how = rng.randrange(8)
    if how == 0:
        t.rows.insert(i, list(t.rows[i]))
        t.ends.insert(i, t.ends[i] or "\n")
        return t.made(f"line {i + 1} duplicated (the same ADR twice)", REFUSE)
    if how == 1:
        j = rows[(rows.index(i) + 1) % len(rows)]
        t.rows[i], t.rows[j] = t.rows[j], t.rows[i]
        return t.made(f"lines {i + 1} and {j + 1} swapped", REFUSE)
    if how == 2:
        del t.rows[i], t.ends[i]
        return t.made(f"line {i + 1} deleted", EITHER)
    if how == 3:
        t.rows.insert(i, [""])
        t.ends.insert(i, t.ends[i] or "\n")
        return t.made(f"an empty line before line {i + 1}", EITHER)
    if how == 4:
        del t.rows[0], t.ends[0]
        return t.made("header line deleted", REFUSE)
    if how == 5:
        t.rows[1:], t.ends[1:] = [], []
        return t.made("only the header line kept", REFUSE)
    if how == 6:
        t.rows.insert(i, list(t.rows[0]))
        t.ends.insert(i, t.ends[0] or "\n")
        return t.made(f"the header repeated before line {i + 1}", REFUSE)
    t.rows[0][rng.randrange(len(t.rows[0]))] = "XYZ"
    return t.made("a column title changed to 'XYZ'", EITHER)


@_mutator("chadeche.separators", "chadeche", weight=2)
def _ch_separators(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    sep, what = rng.choice(
        [(" ", "spaces"), (";", "semicolons"), (",", "commas"), ("\t\t", "two tabs")]
    )
    line = sep.join(t.rows[i])
    t.rows[i] = [line]
    return t.made(f"line {i + 1}: fields separated by {what}", REFUSE)


@_mutator("chadeche.comment", "chadeche", weight=2)
def _ch_comment(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    old = t.rows[i][10]
    new, expect = rng.choice(
        [
            (old.lstrip("#"), REFUSE if old.lstrip("#").strip() else EITHER),
            (old + "\tmore", EITHER),
            ("#" + "é" * 2000, EITHER),
            ("", REFUSE),
            ("#", EITHER),
            ("# ' \" \\ {} [] : - &a *a !tag", EITHER),
        ]
    )
    where = _cell(t, i, 10)
    t.rows[i][10] = new
    return t.made(f"{where} → {new[:40]!r}", expect)


@_mutator("size.many_rows", "chadeche", weight=2, large=True)
def _ch_many_rows(rng: random.Random, src: Source, small: bool) -> Made | None:
    """More rows than README "Input limits" allows, or just fewer (all like one row)."""
    t = _Table(src)
    rows = t.data_rows()
    if not rows:
        return None
    count = rng.choice([*_count_choices(MAX_SEQUENCE_ROWS), 100_000])
    template = t.rows[rows[0]]
    end = t.ends[rows[0]] or "\n"
    t.rows[1:] = [[str(k + 1), *template[1:]] for k in range(count)]
    t.ends[1:] = [end] * count
    expect = REFUSE if count > MAX_SEQUENCE_ROWS else EITHER
    return t.made(f"{count:,} rows like line {rows[0] + 1} (limit {MAX_SEQUENCE_ROWS:,})", expect)


# --------------------------------------------------------------------------------------------
# .prm parameter files: one option a line ("-M 1.70", seed 000 §III.D.4)

_PRM_LINE = re.compile(r"^(?P<lead>\s*)-(?P<letter>\S)(?P<sep>\s*)(?P<value>.*?)(?P<trail>\s*)$")
_PRM_POSITIVE = set("mMcCinp1s")  # a negative value is nonsense (offsets -2 -o may be < 0)
_PRM_NONZERO = set("Mnp1s")


def _prm_value(rng: random.Random, letter: str) -> tuple[str, Expect, str]:
    choices: list[tuple[str, Expect, str]] = [
        ("9" * 5000, REFUSE, "5000 digits"),
        ("9" * 400, REFUSE, "400 digits"),
        ("-5", REFUSE if letter in _PRM_POSITIVE else EITHER, "negative"),
        ("0", REFUSE if letter in _PRM_NONZERO else EITHER, "zero"),
        ("nan", REFUSE, "NaN"),
        ("inf", REFUSE, "infinity"),
        ("-inf", REFUSE, "-infinity"),
        ("1e308", REFUSE, "1e308"),
        ("1e-320", REFUSE if letter == "p" else EITHER, "a denormal"),
        ("1_000", REFUSE, "1_000 (Python reads 1000, the C program's atof 1)"),
        ("0x10", REFUSE, "hex"),
        ("abc", REFUSE, "a word"),
        ("1,7", REFUSE, "a decimal comma"),
        ("1.7.2", REFUSE, "two dots"),
        ("1.7abc", REFUSE, "a number and letters"),
        ("٣", REFUSE, "an Arabic-Indic digit"),
        ("１.７", REFUSE, "fullwidth digits"),
        ("+1.7", EITHER, "a plus sign"),
        (".5", EITHER, "no leading zero"),
    ]
    if letter == "n":
        choices += [
            ("1.5", REFUSE, "a fraction of a cycle"),
            ("1000001", REFUSE, "a million cycles"),
        ]
    return rng.choice(choices)


class _Prm:
    def __init__(self, src: Source) -> None:
        self.src = src
        self.lines = src.text.splitlines(keepends=True)

    def options(self) -> list[tuple[int, re.Match[str]]]:
        out = []
        for i, ln in enumerate(self.lines):
            m = _PRM_LINE.match(ln.rstrip("\r\n"))
            if m:
                out.append((i, m))
        return out

    def made(self, how: str, expect: Expect) -> Made:
        return Made(_encode(self.src, "".join(self.lines)), how, expect)

    def end(self, i: int) -> str:
        ln = self.lines[i]
        return ln[len(ln.rstrip("\r\n")) :] or "\n"


# Options a parameter file ignores (board address) or that are no recipe matter (-f file name).
_PRM_IGNORED = set("ahvtfgl")


@_mutator("prm.value", "prm", weight=5)
def _prm_value_mutation(rng: random.Random, src: Source, small: bool) -> Made | None:
    p = _Prm(src)
    opts = [(i, m) for i, m in p.options() if m["value"] and m["letter"] not in _PRM_IGNORED]
    if not opts:
        return None
    i, m = rng.choice(opts)
    new, expect, what = _prm_value(rng, m["letter"])
    p.lines[i] = f"{m['lead']}-{m['letter']}{m['sep'] or ' '}{new}{p.end(i)}"
    shown = new if len(new) < 20 else f"{new[:6]}…"
    return p.made(f"line {i + 1}: -{m['letter']} {m['value']} → {shown} ({what})", expect)


@_mutator("prm.inverted", "prm", weight=2)
def _prm_inverted(rng: random.Random, src: Source, small: bool) -> Made | None:
    p = _Prm(src)
    low, _high, value, what = rng.choice(
        [("m", "M", "5", "TL 5 V above TH"), ("c", "C", "5000", "LmAh above HmAh")]
    )
    line = f"-{low} {value}\n"
    p.lines.append(line if not p.lines or p.lines[-1].endswith(("\n", "\r")) else "\n" + line)
    return p.made(f"added -{low} {value}: {what} (inverted thresholds)", REFUSE)


@_mutator("prm.structure", "prm", weight=4)
def _prm_structure(rng: random.Random, src: Source, small: bool) -> Made | None:
    p = _Prm(src)
    opts = p.options()
    how = rng.randrange(10)
    if how == 0:
        p.lines.insert(rng.randrange(len(p.lines) + 1), "-x 3\n")
        return p.made("an unknown option -x 3 inserted", REFUSE)
    if how == 1 and opts:
        i, m = rng.choice(opts)
        p.lines[i] = p.lines[i].replace("-", "", 1)
        return p.made(f"line {i + 1}: the '-' of -{m['letter']} removed", REFUSE)
    if how == 2 and opts:
        i, _ = rng.choice(opts)
        p.lines.insert(i, p.lines[i])
        return p.made(f"line {i + 1} duplicated (the option given twice)", EITHER)
    if how == 3:
        p.lines.insert(rng.randrange(len(p.lines) + 1), "-v 3\n")
        return p.made("a flag with a value: -v 3", EITHER)
    if how == 4 and opts:
        valued = [(i, m) for i, m in opts if m["value"] and m["letter"] not in _PRM_IGNORED]
        if not valued:
            return None
        i, m = rng.choice(valued)
        p.lines[i] = f"-{m['letter']}{p.end(i)}"
        return p.made(f"line {i + 1}: -{m['letter']} without its value", REFUSE)
    if how == 5 and len(opts) >= 2:
        (i, _), (_, b) = rng.sample(opts, 2)
        p.lines[i] = p.lines[i].rstrip("\r\n") + " " + b.group(0).strip() + p.end(i)
        return p.made(f"line {i + 1}: a second option on the same line", EITHER)
    if how == 6:
        p.lines.insert(rng.randrange(len(p.lines) + 1), rng.choice(["\n", "# comment\n", "  \n"]))
        return p.made("a blank or comment line inserted", EITHER)
    if how == 7 and opts:
        i, m = rng.choice(opts)
        p.lines[i] = f"--{m['letter']} {m['value']}{p.end(i)}"
        return p.made(f"line {i + 1}: --{m['letter']} (two dashes)", REFUSE)
    if how == 8:
        p.lines.insert(rng.randrange(len(p.lines) + 1), "-n 1000001\n")
        return p.made("-n 1000001 inserted (a million cycles)", REFUSE)
    if how == 9 and opts:
        i, m = rng.choice(opts)
        p.lines[i] = f"-{m['letter']}\t{m['value']}   {p.end(i)}"
        return p.made(f"line {i + 1}: a tab before the value and trailing spaces", EITHER)
    return None


# --------------------------------------------------------------------------------------------
# Load profiles in CSV (seed 002 §2.3): time, current, then optional V/I/T min/max columns


class _Csv:
    """A profile as lines of cells (``,``-separated, as the source is), each line's end kept."""

    def __init__(self, src: Source) -> None:
        self.src = src
        self.rows: list[list[str]] = []
        self.ends: list[str] = []
        for line in src.text.splitlines(keepends=True):
            body = line.rstrip("\r\n")
            self.rows.append(body.split(","))
            self.ends.append(line[len(body) :] or "\n")

    def data_rows(self) -> list[int]:
        return [i for i, r in enumerate(self.rows) if i > 0 and len(r) >= 2]

    def text(self, sep: str = ",") -> str:
        return "".join(sep.join(r) + e for r, e in zip(self.rows, self.ends, strict=True))

    def made(self, how: str, expect: Expect, sep: str = ",") -> Made:
        return Made(_encode(self.src, self.text(sep)), how, expect)


_PROFILE_COLS = ("time", "current", "V window")


def _times_increase(t: _Csv, i: int, new_t: float) -> bool:
    """Whether the data rows' times still increase strictly with ``new_t`` on line ``i``."""
    times = [new_t if j == i else float(t.rows[j][0]) for j in t.data_rows()]
    return all(a < b for a, b in itertools.pairwise(times))


# (cell text, certainly invalid as a time or current, what it is)
_PROFILE_NUMBERS: tuple[tuple[str, Expect, str], ...] = (
    ("nan", REFUSE, "NaN"),
    ("inf", REFUSE, "infinity"),
    ("-inf", REFUSE, "-infinity"),
    ("1e309", REFUSE, "beyond the double range"),
    ("9" * 5000, REFUSE, "5000 digits (infinite as a double)"),
    ("1_000", REFUSE, "1_000 (Python's float reads 1000)"),
    ("0x10", REFUSE, "hex"),
    ("abc", REFUSE, "a word"),
    ("1.5.2", REFUSE, "two dots"),
    ("1e-400", EITHER, "below the double range (reads as 0)"),
    ("1e308", EITHER, "near the largest double"),
    (" 60 ", EITHER, "blanks around"),
    ("+1", EITHER, "a plus sign"),
)


@_mutator("profile.cell", "profile", weight=4)
def _profile_cell(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Csv(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    k = rng.randrange(min(3, len(t.rows[i])))
    old = t.rows[i][k]
    if rng.random() < 0.25 and any(c.isdigit() for c in old):
        new, name = _unicode_digits(rng, old)
        expect, what = REFUSE, f"{name} digits"
    elif rng.random() < 0.15:
        new, expect, what = "", REFUSE if k < 2 else EITHER, "emptied"
    else:
        new, expect, what = rng.choice(_PROFILE_NUMBERS)
        if k == 2 and "/" in old:  # a limit pair "2.8/4.2": the number replaces the low one
            new = f"{new}/{old.split('/')[-1]}"
        if k == 0 and expect == EITHER and not _times_increase(t, i, float(new)):
            expect = REFUSE  # times must increase strictly (read_profile_csv)
    t.rows[i][k] = new
    shown = new if len(new) < 20 else f"{new[:6]}…({len(new)} chars)"
    return t.made(f"line {i + 1} {_PROFILE_COLS[k]} {old!r} → {shown!r} ({what})", expect)


@_mutator("profile.rows", "profile", weight=3)
def _profile_rows(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Csv(src)
    rows = t.data_rows()
    if len(rows) < 2:
        return None
    i = rng.choice(rows[:-1])
    j = rows[rows.index(i) + 1]
    how = rng.randrange(7)
    if how == 0:
        t.rows[i], t.rows[j] = t.rows[j], t.rows[i]
        return t.made(f"lines {i + 1} and {j + 1} swapped (time goes back)", REFUSE)
    if how == 1:
        t.rows.insert(i, list(t.rows[i]))
        t.ends.insert(i, t.ends[i])
        return t.made(f"line {i + 1} duplicated (the same time twice)", REFUSE)
    if how == 2:
        del t.rows[i], t.ends[i]
        return t.made(f"line {i + 1} deleted", EITHER)
    if how == 3:
        t.rows[1:], t.ends[1:] = [], []
        return t.made("only the header line kept", REFUSE)
    if how == 4:
        del t.rows[0], t.ends[0]
        return t.made("header line deleted", EITHER)
    if how == 5:
        t.rows[i] = t.rows[i][:1]
        return t.made(f"line {i + 1}: the time alone, no current", REFUSE)
    t.rows[i] = [*t.rows[i], "1", "2", "3", "4", "5", "6", "7"]
    return t.made(f"line {i + 1}: seven more cells than the columns", EITHER)


@_mutator("profile.layout", "profile", weight=2)
def _profile_layout(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Csv(src)
    rows = t.data_rows()
    if not rows:
        return None
    how = rng.randrange(4)
    if how == 0:
        sep = rng.choice([";", "\t"])
        # with ; or a tab a comma is a decimal comma (read_profile_csv): still the same file
        return t.made(f"cells separated by {sep!r} instead of ','", EITHER, sep)
    i = rng.choice(rows)
    if how == 1:
        t.rows[i] = [";".join(t.rows[i])]
        return t.made(f"line {i + 1}: cells separated by ';' in a ',' file", REFUSE)
    if how == 2:
        t.rows[i][0] = t.rows[i][0].replace(".", ",") + ",5"
        return t.made(f"line {i + 1}: a decimal comma in a ',' file (one cell more)", EITHER)
    t.rows.insert(i, ["# a comment"])
    t.ends.insert(i, t.ends[i])
    return t.made(f"a comment line before line {i + 1}", EITHER)


@_mutator("size.profile_rows", "profile", weight=1, large=True)
def _profile_many_rows(rng: random.Random, src: Source, small: bool) -> Made | None:
    """More rows than README "Input limits" allows in a profile, or just fewer."""
    t = _Csv(src)
    count = rng.choice(_count_choices(MAX_PROFILE_ROWS))
    t.rows[1:] = [[str(k), "0.1"] for k in range(count)]
    t.ends[1:] = ["\n"] * count
    expect = REFUSE if count > MAX_PROFILE_ROWS else EITHER
    return t.made(f"{count:,} rows (limit {MAX_PROFILE_ROWS:,})", expect)


# --------------------------------------------------------------------------------------------
# Wiring (issue 28, finding 5): an I/O map's safety references rewired to signals of the wrong
# kind, direction or unit, outputs given two owners, alarm limits out of order, interlock ids
# that are the bench's own: well-formed, and certainly refused (supervisor/config/wiring.py).
#
# The kinds of the map's tags are read from the file itself, not from the code under test: an
# output is a relay (``slotN.doK``) or a source's setpoint/switch point, a boolean input has a
# ``threshold:``, a measurement has a ``unit:`` of V, A or degC.

_OUTPUT_POINT = re.compile(r"^(?:slot\d+\.do\d+|output|current_set|voltage_set|b\d+\.\w+_set)$")
_MEASURED_UNITS = ("V", "A", "degC")
# A channel's measurement references and the unit each must be in.
_MEASUREMENTS = (
    (("voltage_tag",), "V"),
    (("current_tag",), "A"),
    (("temperature_tag",), "degC"),
    (("bms", "cell_max_tag"), "V"),
    (("bms", "cell_min_tag"), "V"),
    (("bms", "temperature_tag"), "degC"),
)
_RESERVED_INTERLOCK_IDS = ("estop", "EStop", "heartbeat", "stall", "scan")


@dataclass
class _Wiring:
    """An I/O map's node graph and its tags by kind."""

    doc: _Doc
    data: dict[str, object]
    outputs: list[tuple[str, str, str]]  # (tag, device, point)
    booleans: list[str]
    analog: dict[str, str]  # tag -> unit

    def node(self, *path: str | int) -> Node | None:
        node: Node | None = self.doc.root
        for part in path:
            if isinstance(part, int):
                if not isinstance(node, SequenceNode) or not 0 <= part < len(node.value):
                    return None
                node = node.value[part]
            else:
                i = _entry(node, part) if isinstance(node, MappingNode) else None
                if i is None or not isinstance(node, MappingNode):
                    return None
                node = node.value[i][1]
        return node

    def value(self, *path: str | int) -> str | None:
        node = self.node(*path)
        return str(node.value) if isinstance(node, ScalarNode) else None

    def put(self, path: Path_, key: str, value: Node) -> bool:
        """Set ``key`` of the mapping at ``path`` (added when absent)."""
        node = self.node(*path)
        if not isinstance(node, MappingNode):
            return False
        i = _entry(node, key)
        if i is None:
            node.value.append((_scalar(key), value))
        else:
            node.value[i] = (node.value[i][0], value)
        return True

    def wrong_for(self, unit: str) -> list[tuple[str, str]]:
        """Tags that are certainly not a measurement in ``unit``: (tag, what it is)."""
        out = [(t, "an output") for t, _, _ in self.outputs]
        out += [(t, "a boolean") for t in self.booleans]
        out += [(t, f"a tag in {u}") for t, u in self.analog.items() if u != unit]
        return out

    def channels(self) -> list[int]:
        node = self.node("channels")
        return list(range(len(node.value))) if isinstance(node, SequenceNode) else []

    def made(self, how: str) -> Made:
        return _made(self.doc, how, REFUSE)


def _wiring(src: Source) -> _Wiring | None:
    doc = _doc(src)
    try:
        data = yaml.safe_load(src.text)
    except yaml.YAMLError:
        return None
    if doc is None or not isinstance(data, dict) or not isinstance(data.get("devices"), dict):
        return None
    outputs: list[tuple[str, str, str]] = []
    booleans: list[str] = []
    analog: dict[str, str] = {}
    names: set[str] = set()
    for t in data.get("tags") or []:
        if not isinstance(t, dict) or not isinstance(t.get("name"), str):
            continue
        name, point = t["name"], str(t.get("point"))
        if name in names:
            continue  # a duplicate name: its kind is the first's
        names.add(name)
        if _OUTPUT_POINT.match(point):
            outputs.append((name, str(t.get("device")), point))
        elif t.get("threshold") is not None:
            booleans.append(name)
        elif t.get("unit") in _MEASURED_UNITS:
            analog[name] = str(t["unit"])
    return _Wiring(doc, data, outputs, booleans, analog)


@_mutator("wiring.estop", "check", weight=2)
def _wiring_estop(rng: random.Random, src: Source, small: bool) -> Made | None:
    """The e-stop reads an analog value or an output instead of its sense input."""
    w = _wiring(src)
    if w is None or w.value("safety", "estop", "tag") is None:
        return None
    old = w.value("safety", "estop", "tag")
    choices = [(t, "an output") for t, _, _ in w.outputs]
    choices += [(t, f"an analog tag in {u}") for t, u in w.analog.items()]
    if not choices:
        return None
    new, what = rng.choice(choices)
    w.put(("safety", "estop"), "tag", _scalar(new))
    return w.made(f"safety.estop.tag {old!r} → {new!r} ({what})")


@_mutator("wiring.feedback", "check", weight=2)
def _wiring_feedback(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A contactor feedback that reads the contactor's own command, an output or a number."""
    w = _wiring(src)
    if w is None:
        return None
    sites = [i for i in w.channels() if w.value("channels", i, "contactor_feedback_tag")]
    if not sites:
        return None
    i = rng.choice(sites)
    cmd = w.value("channels", i, "contactor_tag")
    choices = [(cmd, "the contactor's own command")] if cmd else []
    choices += [(t, "an output") for t, _, _ in w.outputs]
    choices += [(t, f"an analog tag in {u}") for t, u in w.analog.items()]
    new, what = rng.choice([c for c in choices if c[0] is not None])
    w.put(("channels", i), "contactor_feedback_tag", _scalar(new))
    return w.made(f"channels[{i}].contactor_feedback_tag → {new!r} ({what})")


@_mutator("wiring.owner", "check", weight=3)
def _wiring_owner(rng: random.Random, src: Source, small: bool) -> Made | None:
    """An output given two owners: the heartbeat on a contactor coil, the e-stop relay on the
    heartbeat, two channels on one contactor, a second tag on a coil or heartbeat output."""
    w = _wiring(src)
    if w is None:
        return None
    contactors = {
        i: c for i in w.channels() if (c := w.value("channels", i, "contactor_tag")) is not None
    }
    heartbeat = w.value("safety", "heartbeat", "tag")
    estop = w.node("safety", "estop")
    owned = {t: (d, p) for t, d, p in w.outputs if t in {*contactors.values(), heartbeat}}
    ways: list[str] = []
    if heartbeat is not None and contactors:
        ways.append("heartbeat_on_coil")
    if heartbeat is not None and isinstance(estop, MappingNode):
        ways.append("relay_on_heartbeat")
    if contactors and len(w.channels()) > 1:
        ways.append("shared_contactor")
    if owned:
        ways.append("second_tag")
    if not ways:
        return None
    way = rng.choice(ways)
    if way == "heartbeat_on_coil":
        coil = rng.choice(sorted(contactors.values()))
        w.put(("safety", "heartbeat"), "tag", _scalar(coil))
        return w.made(f"safety.heartbeat.tag → {coil!r}, a channel's contactor coil")
    if way == "relay_on_heartbeat":
        assert heartbeat is not None
        w.put(("safety", "estop"), "relay_tag", _scalar(heartbeat))
        return w.made(f"safety.estop.relay_tag → the heartbeat {heartbeat!r}")
    if way == "shared_contactor":
        i, coil = rng.choice(sorted(contactors.items()))
        other = rng.choice([k for k in w.channels() if k != i])
        w.put(("channels", other), "contactor_tag", _scalar(coil))
        return w.made(f"channels[{other}].contactor_tag → {coil!r}, channels[{i}]'s contactor")
    tag = rng.choice(sorted(owned))
    device, point = owned[tag]
    tags = w.node("tags")
    assert isinstance(tags, SequenceNode)
    pairs = [("name", "coil.copy"), ("device", device), ("point", point)]
    entry = MappingNode(_TAG + "map", [(_scalar(k), _scalar(v)) for k, v in pairs], flow_style=True)
    tags.value.insert(rng.randrange(len(tags.value) + 1), entry)
    return w.made(f"a second tag 'coil.copy' on {tag!r}'s output {device}.{point}")


@_mutator("wiring.measurement", "check", weight=3)
def _wiring_measurement(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A channel's voltage, current or temperature (or BMS) tag rewired to a boolean, an
    output or a measurement in another unit."""
    w = _wiring(src)
    if w is None or not w.channels():
        return None
    i = rng.choice(w.channels())
    fields = [(f, u) for f, u in _MEASUREMENTS if len(f) == 1 or w.node("channels", i, *f)]
    checks = w.node("channels", i, "voltage_checks")
    if isinstance(checks, SequenceNode):
        fields += [((k, "tag"), "V") for k in range(len(checks.value))]
    path, unit = rng.choice(fields)
    wrong = w.wrong_for(unit)
    if not wrong:
        return None
    new, what = rng.choice(wrong)
    *parent, key = path
    if parent and parent[0] != "bms":
        parent = ["voltage_checks", *parent]
    if not w.put(("channels", i, *parent), str(key), _scalar(new)):
        return None
    where = ".".join(str(p) for p in (*parent, key))
    return w.made(f"channels[{i}].{where} → {new!r} ({what}, not {unit})")


@_mutator("wiring.alarm_order", "check", weight=2)
def _wiring_alarm_order(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A measurement's alarm limits out of order (``hh: 10, ll: 50``)."""
    w = _wiring(src)
    tags = w.node("tags") if w is not None else None
    if w is None or not isinstance(tags, SequenceNode):
        return None
    sites = [
        k
        for k, t in enumerate(tags.value)
        if isinstance(t, MappingNode) and w.value("tags", k, "name") in w.analog
    ]
    if not sites:
        return None
    k = rng.choice(sites)
    order = ["ll", "l", "h", "hh"]
    a, b = sorted(rng.sample(range(4), 2))
    low = rng.choice([10, 0.5, -5, 100])
    high = low - rng.choice([0, 1, 40])  # the upper key at or below the lower one
    pairs = [(order[b], high), (order[a], low)]
    rng.shuffle(pairs)
    alarms = MappingNode(
        _TAG + "map", [(_scalar(key), _scalar(f"{v:g}")) for key, v in pairs], flow_style=True
    )
    w.put(("tags", k), "alarms", alarms)
    shown = ", ".join(f"{key}: {v:g}" for key, v in pairs)
    return w.made(f"tags[{k}].alarms → {{{shown}}} ({order[b]} not above {order[a]})")


@_mutator("wiring.interlock_id", "check", weight=2)
def _wiring_interlock_id(rng: random.Random, src: Source, small: bool) -> Made | None:
    """An interlock under the name of one of the bench's own safety functions."""
    w = _wiring(src)
    if w is None or not w.analog:
        return None
    reserved = rng.choice(_RESERVED_INTERLOCK_IDS)
    tag = rng.choice(sorted(w.analog))
    fields = [("id", reserved), ("tag", tag), ("above", "60")]
    entry = MappingNode(
        _TAG + "map", [(_scalar(k), _scalar(v)) for k, v in fields], flow_style=True
    )
    interlocks = SequenceNode(_TAG + "seq", [entry], flow_style=False)
    if w.node("safety") is None:
        root = w.doc.root
        assert isinstance(root, MappingNode)
        root.value.append((_scalar("safety"), MappingNode(_TAG + "map", [])))
    old = w.node("safety", "interlocks")
    if isinstance(old, SequenceNode):
        old.value.insert(rng.randrange(len(old.value) + 1), entry)
    elif not w.put(("safety",), "interlocks", interlocks):
        return None
    return w.made(f"safety.interlocks: an interlock with the reserved id {reserved!r}")


# Issue 28, names and separators (findings 4 and 9): cells a ',' CSV would misread.


@_mutator("profile.separators", "profile", weight=2)
def _profile_separators(rng: random.Random, src: Source, small: bool) -> Made | None:
    t = _Csv(src)
    rows = t.data_rows()
    if not rows:
        return None
    i = rng.choice(rows)
    how = rng.randrange(4)
    if how == 0:  # decimal commas with ',' as the separator: "0,0,5" for 0 s and 0.5 A
        t.rows[i] = [t.rows[i][0], "0", "5"]
        return t.made(f"line {i + 1}: a decimal comma current in a ',' file", REFUSE)
    if how == 1:  # a 9th column
        t.rows[i] = [t.rows[i][0], "0.1", "1", "2", "0", "1", "0", "40", "9"]
        return t.made(f"line {i + 1}: nine columns", REFUSE)
    if how == 2:  # a min/max cell of three numbers
        t.rows[i] = [t.rows[i][0], "0.1", "1/2/3"]
        return t.made(f"line {i + 1}: '1/2/3' in a min/max cell", REFUSE)
    t.rows[i] = [t.rows[i][0], "1e-400"]
    return t.made(f"line {i + 1}: a current of 1e-400 (underflows to 0)", REFUSE)


# Issue 28, findings 2, 3 and 10 (branch yamlamp): aliases and merge keys that amplify, YAML
# 1.1 numbers that surprise, strings that cannot be encoded. The loader counts values and
# text while it builds the document (README "Input limits"): an amplifying file is refused
# after at most the limit's worth of work, at the place where it passes it.

_COND_TERM = "voltage >= 5 V"


def _step_sites(doc: _Doc) -> list[_Site]:
    """The step mappings of a recipe (``steps[i]``)."""
    return [
        s
        for s in doc.values()
        if isinstance(s.node, MappingNode) and len(s.path) == 2 and s.path[0] == "steps"
    ]


@_mutator("aliases.big_condition", "check", weight=3)
def _aliases_big_condition(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A long condition anchored once and used as the ``until`` of N steps (finding 2): its
    text counts at every use; over 1 MiB expanded it is certainly refused."""
    doc = _doc(src)
    if doc is None:
        return None
    steps = _step_sites(doc)
    if not steps:
        return None
    size = rng.choice([2_000, 20_000] if small else [20_000, 100_000, 300_000])
    condition = " or ".join([_COND_TERM] * (size // (len(_COND_TERM) + 4)))
    uses = rng.choice([1, 2, len(steps)] if small else [1, 5, 10, 11, 100, 1000])
    cond = ScalarNode(_STR, condition, style='"')  # one node: the serialiser anchors it
    used = 0
    for k in range(uses):
        site = steps[k % len(steps)]
        assert isinstance(site.node, MappingNode)
        entry = SequenceNode(_TAG + "seq", [MappingNode(_TAG + "map", [(cond, _scalar("next"))])])
        if k >= len(steps):  # more uses than steps: more items in the same until lists
            until = next(v for key, v in site.node.value if _key_text(key) == "until")
            assert isinstance(until, SequenceNode)
            until.value.extend(entry.value)
        else:
            site.node.value = [(k_, v) for k_, v in site.node.value if _key_text(k_) != "until"]
            site.node.value.append((_scalar("until"), entry))
        used += 1
    expanded = used * len(condition)
    expect = REFUSE if expanded > MAX_YAML_BYTES else EITHER
    return _made(
        doc,
        f"a {len(condition):,}-character condition anchored once, the until of {used} steps"
        f" ({expanded:,} characters expanded; limit {MAX_YAML_BYTES:,})",
        expect,
    )


@_mutator("aliases.chain", "check", weight=2)
def _aliases_chain(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A chain of anchors, each level a list of two aliases of the one below (2**depth
    values): over 500,000 it is certainly refused, wherever it stands."""
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, [s for s in doc.values() if s.parent is not None])
    if site is None:
        return None
    depth = rng.choice([4, 8, 12] if small else [12, 18, 19, 24, 40])
    node: Node = copy.deepcopy(site.node)
    for _ in range(depth):
        node = SequenceNode(_TAG + "seq", [node, node], flow_style=True)
    doc.replace(site, node)
    # A list site was a list before (still may be valid); anything else is now the wrong shape.
    expect = REFUSE if 2 ** (depth + 1) > 500_000 else EITHER
    return _made(doc, f"{site.where()} → a chain of {depth} anchors, 2 aliases each", expect)


@_mutator("merges.bomb", "check", weight=3)
def _merges_bomb(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A K-key mapping anchored once and merged M times (``{<<: *a}`` items, or one merge key
    with a list of M aliases): each merge counts its K keys (finding 3)."""
    doc = _doc(src)
    if doc is None:
        return None
    site = _pick(rng, _collections(doc, SequenceNode))
    if site is None:
        return None
    keys = rng.choice([10, 200] if small else [10, 2000])
    merges = rng.choice([10, 200] if small else [1000, 50_000, 200_000])
    mapping = "{" + ", ".join(f"k{i}: {i}" for i in range(keys)) + "}"
    if rng.random() < 0.5:
        fragment = f"[&mb {mapping}" + ", {<<: *mb}" * merges + "]"
        what = f"a list of {merges:,} {{<<: *a}} of a {keys}-key mapping"
    else:
        fragment = f"[&mb {mapping}, {{<<: [" + ", ".join(["*mb"] * merges) + "]}]"
        what = f"one merge key of {merges:,} aliases of a {keys}-key mapping"
    doc.replace_raw(site, fragment)
    expanded = 2 * keys * merges
    # Over the limit of values (each key and value) or of text: certainly refused.
    expect = REFUSE if expanded > 500_000 else EITHER
    return _made(doc, f"{site.where()} → {what} ({expanded:,} values merged)", expect)


@_mutator("yaml11.numbers", "check", weight=3)
def _yaml11_numbers(rng: random.Random, src: Source, small: bool) -> Made | None:
    """An integer written as YAML 1.1 reads it unlike it shows (finding 10): ``010`` (octal,
    8) or ``1:30`` (base 60, 90), refused; or ``0x..``/``1_000`` forms that say what they
    are and stay the same number."""
    doc = _doc(src)
    if doc is None:
        return None
    sites = [
        s
        for s in _number_sites(doc)
        if s.node.tag == _INT and re.fullmatch(r"[0-9]+", str(s.node.value))
    ]
    site = _pick(rng, sites)
    if site is None:
        return None
    value = int(str(site.node.value))
    how = rng.randrange(4)
    if how == 0:
        text, expect = "0" + str(value), REFUSE
    elif how == 1:
        text, expect = f"{value // 60 + 1}:{value % 60:02d}", REFUSE
    elif how == 2:
        text, expect = hex(value), EITHER
    else:
        text, expect = (f"{value:_}" if value >= 1000 else f"+{value}"), EITHER
    if text == "00":  # zero with a leading zero: zero either way
        expect = EITHER
    doc.replace(site, _scalar(text))
    return _made(doc, f"{site.where()}: {value} → {text}", expect)


@_mutator("text.surrogate", "check", weight=2)
def _text_surrogate(rng: random.Random, src: Source, small: bool) -> Made | None:
    """A double-quoted string with a lone surrogate escape (``"\\ud800"``): a str that no
    file, log or socket can take, certainly refused where it is written."""
    doc = _doc(src)
    if doc is None:
        return None
    sites = [
        s
        for s in doc.sites()
        if isinstance(s.node, ScalarNode) and s.node.tag == _STR and s.parent is not None
    ]
    site = _pick(rng, sites)
    if site is None:
        return None
    escape = rng.choice(["\\ud800", "\\udfff", "\\ud83d\\ude00"])
    original = str(site.node.value).replace("\\", "\\\\").replace('"', '\\"')
    fragment = '"' + original[:40] + escape + '"'
    doc.replace_raw(site, fragment)
    return _made(doc, f"{site.where()} → a double-quoted string with {escape}", REFUSE)


# Issue 28, findings 1 and 6 (writers): strings that cannot be encoded. A YAML double-quoted
# escape ``\ud800`` makes a lone surrogate, which no writer can encode as UTF-8 (the
# historian died of one). ``check`` may refuse the value or take it (a writer then stores it
# escaped: supervisor/core/encoding.py); never a traceback.

_SURROGATE_ESCAPES = ("\\ud800", "\\udfff", "\\udc80", "\\udbff")
_PLAIN_VALUE = re.compile(r"^(\s*(?:- )?[A-Za-z_][\w.]*): +([^\s#\"'\[\]{}&*|>!%@`][^#]*?)\s*$")


@_mutator("text.surrogate_escape", "check", weight=2, refuses=False)
def _text_surrogate_escape(rng: random.Random, src: Source, small: bool) -> Made | None:
    lines = _lines(src.text)
    found = [(i, m) for i, ln in enumerate(lines) if (m := _PLAIN_VALUE.match(ln.rstrip("\n")))]
    if not found:
        return None
    i, m = rng.choice(found)
    key, value = m.group(1), m.group(2)
    escape = rng.choice(_SURROGATE_ESCAPES)
    at = rng.randrange(len(value) + 1)
    quoted = (value[:at] + "\0" + value[at:]).replace("\\", "\\\\").replace('"', '\\"')
    end = "\n" if lines[i].endswith("\n") else ""
    lines[i] = f'{key}: "{quoted.replace(chr(0), escape)}"{end}'
    return Made(
        "".join(lines).encode("utf-8"),
        f"line {i + 1}: the escape {escape} (a lone surrogate) in {key.strip()}'s value",
        EITHER,
    )


# --------------------------------------------------------------------------------------------
# Reserved names (issue 28, finding 4): a recipe parameter renamed to a name an expression
# already reads — a measurement, a counter, a function — and every use of it renamed too, so
# that the recipe reads as its author meant it and only the shadowing is wrong. Refused at
# the parameter's key (supervisor/chains/compiler.py RESERVED_NAMES).
#
# The names are the issue's and the README's, written here, not read from the code under
# test: a name dropped from the compiler's table makes these variants accepted, and fail.

_SHADOWED = ("voltage", "current", "temperature", "cycle", "abs", "max", "min")
_WORD = r"(?<![A-Za-z0-9_.]){}(?![A-Za-z0-9_])"


@_mutator("names.reserved", "check", weight=3)
def _names_reserved(rng: random.Random, src: Source, small: bool) -> Made | None:
    doc = _doc(src)
    if doc is None:
        return None
    keys = [
        s
        for s in doc.sites()
        if s.is_key and s.path[:1] == ("parameters",) and len(s.path) == 2
        if isinstance(s.node, ScalarNode)
    ]
    site = _pick(rng, keys)
    if site is None or not isinstance(site.node, ScalarNode):
        return None
    old = str(site.node.value)
    new = rng.choice(_SHADOWED)
    word = re.compile(_WORD.format(re.escape(old)))
    for s in doc.values():  # every expression that reads the parameter reads the new name
        node = s.node
        if isinstance(node, ScalarNode) and node.tag == _STR and word.search(str(node.value)):
            node.value = word.sub(new, str(node.value))
    for s in doc.sites():  # an until's condition is a mapping key
        node = s.node
        if s.is_key and isinstance(node, ScalarNode) and word.search(str(node.value)):
            node.value = word.sub(new, str(node.value))
    doc.replace(site, _scalar(new))
    return _made(doc, f"{site.where()}: parameter {old!r} renamed {new!r}, uses too", REFUSE)
