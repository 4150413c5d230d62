"""A recipe load in two parts: what may take seconds, and what must be quick.

Reading, decoding, parsing and compiling a recipe (:func:`compile_recipe_file`) reads the
file and a snapshot of its channel (a ``Target``) and changes nothing: it runs in a worker
thread while the scan keeps its period (README "Input limits": a file within the limits
can still take seconds on a slow machine). Applying the compiled program to the channel
(``RecipeLoader.install_recipe``) is quick and runs on the event loop between two scans,
like every other command. The command line and tests without a running loop call both in
turn (``CommandPath.execute``); the HTTP API awaits the first in its thread
(``CommandPath.execute_async``). Both are the same command, with the same checks.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.engine import ChainRunner
from supervisor.chains.program import Program
from supervisor.config.limits import MAX_YAML_BYTES, read_limited
from supervisor.config.recipe import load_recipe_text
from supervisor.config.text import decode_yaml
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.publish.provenance import TestMetadata
from supervisor.tags.spec import clipped_repr

__all__ = [
    "PreparedRecipe",
    "RecipeFolders",
    "RecipeLoader",
    "RecipeNotFound",
    "RecipeOutside",
    "compile_recipe_file",
    "read_recipe_text",
]

RECIPE_SUFFIXES = (".yaml", ".yml")


class RecipeOutside(Exception):
    """A recipe asked for outside the recipe folders (the message names them, never the
    file's content: it is never opened)."""


class RecipeNotFound(Exception):
    """No such recipe in the recipe folders."""


@dataclass(frozen=True)
class RecipeFolders:
    """The path policy of recipes asked for over the network (HTTP, OPC UA, ``supervisor
    ctl``, the screens' recipe editor; docs/adr/0026-threat-model.md): a recipe loads only
    when its real path — every symbolic link followed — is inside the real path of one of
    ``folders``. Anything else is refused before it is opened, whether it exists or not,
    so that a refusal tells nothing of a file outside (neither its content nor that it is
    there). The one place this is decided: the command path asks it for every load, the
    recipe editor for every read."""

    folders: tuple[Path, ...]
    """As configured (relative to the working directory, like ``state_dir``)."""

    @classmethod
    def of(cls, folders: Sequence[str | Path]) -> RecipeFolders:
        if not folders:
            raise ValueError("recipe folders: at least one")
        return cls(tuple(Path(f) for f in folders))

    def describe(self) -> str:
        return ", ".join(f"{f}/" for f in self.folders)

    def _roots(self) -> list[Path]:
        # Resolved at each use: a folder made (or re-linked) after start-up counts as it is.
        roots = []
        for f in self.folders:
            try:
                roots.append(f.resolve())
            except (OSError, RuntimeError, ValueError):  # a link loop: no folder there
                continue
        return roots

    def inside(self, path: str | Path) -> bool:
        """Whether ``path``'s real location is inside one of the folders."""
        roots = self._roots()
        try:
            real = Path(path).resolve()
        except (OSError, RuntimeError, ValueError):  # a link loop, a NUL byte
            return False
        return any(real.is_relative_to(r) for r in roots)

    def refuse_file(self, path: Path) -> str | None:
        """Why a file a recipe reads (a load profile) may not be read — outside the
        folders — or None (``compile_recipe``'s ``files``)."""
        if self.inside(path):
            return None
        return (
            f"{clipped_repr(str(path))} is outside the recipe folders: a recipe reads files"
            f" only from {self.describe()}"
        )

    def locate(self, recipe: str) -> Path:
        """The file of ``recipe``: a name (``slow``: ``<folder>/slow.yaml`` in the first
        folder that has it), a path relative to the working directory or to a folder, or an
        absolute path. ``RecipeOutside`` when it is not inside a folder, ``RecipeNotFound``
        when it is but is not there. The path returned is as given (error messages name
        the file as the operator wrote it)."""
        given = Path(recipe)
        if "/" not in recipe and not recipe.endswith(RECIPE_SUFFIXES):
            candidates = [f / f"{recipe}.yaml" for f in self.folders]  # a name
        elif given.is_absolute():
            candidates = [given]
        else:
            candidates = [given, *(f / given for f in self.folders)]
        roots = self._roots()
        missing = False
        for c in candidates:
            try:
                real = c.resolve()
            except (OSError, RuntimeError, ValueError):  # a link loop, a NUL byte
                continue
            if not any(real.is_relative_to(r) for r in roots):
                continue
            # Not "is a file": a device (/dev/zero) or a pipe is read to its size limit,
            # and refused there with the limit named (README: Input limits).
            if real.exists():
                return c
            missing = True
        if missing:
            raise RecipeNotFound(f"{recipe}: no such recipe in {self.describe()}")
        raise RecipeOutside(
            f"{clipped_repr(recipe)} is outside the recipe folders: recipes load only from"
            f" {self.describe()} (the I/O map's recipes: folders)"
        )


@dataclass(frozen=True)
class PreparedRecipe:
    """A recipe read and compiled for one channel, not loaded yet."""

    channel: str
    file: str
    text: str
    """The text compiled, which the retained state keeps (ADR 0010): a restart recompiles
    the same recipe even if the file changed or moved since."""
    program: Program
    parameters: Mapping[str, str] = field(default_factory=dict)


class RecipeLoader(Protocol):
    """What the command path needs of a bench to load recipes (``app.Bench`` is one)."""

    def target(self, channel: str) -> Target:
        """What a recipe may ask of ``channel``: a snapshot, taken on the event loop."""
        ...

    def install_recipe(self, prepared: PreparedRecipe) -> ChainRunner:
        """Load ``prepared`` on its channel (quick; on the event loop). Raises
        ``OperatorError`` when the channel's state refuses it."""
        ...

    @property
    def test_metadata(self) -> dict[str, TestMetadata]:
        """Per channel, the metadata of its next test."""
        ...

    def set_test_metadata(self, channel: str, given: dict[str, Any], replace: bool) -> None:
        """``given`` (checked fields) over the next test's metadata (``replace``: instead)."""
        ...

    def cell_under_test(self, cell_id: str, channel: str) -> tuple[str, str] | None:
        """The other channel and its test under way with cell ``cell_id``, if any."""
        ...


def read_recipe_text(path: str | Path) -> str:
    """A recipe file's text; ``ConfigErrors`` naming the file when it cannot be read, is
    over ``MAX_YAML_BYTES`` (checked before it is read in full: ``/dev/zero`` is refused,
    not read until memory runs out) or is not UTF-8."""
    file = str(path)
    try:
        data = read_limited(path, MAX_YAML_BYTES, "a recipe")
    except FileNotFoundError:
        raise ConfigErrors([ConfigError("file not found", file)]) from None
    except IsADirectoryError:
        raise ConfigErrors([ConfigError("is a directory, not a file", file)]) from None
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    except OSError as exc:
        why = f"cannot read file: {exc.strerror or exc}"
        raise ConfigErrors([ConfigError(why, file)]) from None
    try:
        return decode_yaml(data, file).text
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None


def compile_recipe_file(
    channel: str,
    file: str | Path,
    target: Target,
    parameters: Mapping[str, str] | None = None,
    folders: RecipeFolders | None = None,
) -> PreparedRecipe:
    """Read, parse and compile ``file`` for ``channel`` (``ConfigErrors`` with
    file:line:col when refused). Touches nothing but the file: safe in a worker thread.
    ``folders``: the files the recipe reads (a load profile) must be inside them too."""
    overrides = dict(parameters or {})
    text = read_recipe_text(file)
    recipe, pos = load_recipe_text(text, str(file))
    files = folders.refuse_file if folders is not None else None
    try:
        program = compile_recipe(recipe, pos, str(file), target, overrides, files)
    finally:
        del recipe
        pos.release_gradually()
    return PreparedRecipe(channel, str(file), text, program, overrides)
