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

from collections.abc import Mapping
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

__all__ = ["PreparedRecipe", "RecipeLoader", "compile_recipe_file", "read_recipe_text"]


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
    channel: str, file: str | Path, target: Target, parameters: Mapping[str, str] | None = None
) -> PreparedRecipe:
    """Read, parse and compile ``file`` for ``channel`` (``ConfigErrors`` with
    file:line:col when refused). Touches nothing but the file: safe in a worker thread."""
    overrides = dict(parameters or {})
    text = read_recipe_text(file)
    recipe, pos = load_recipe_text(text, str(file))
    try:
        program = compile_recipe(recipe, pos, str(file), target, overrides)
    finally:
        del recipe
        pos.release_gradually()
    return PreparedRecipe(channel, str(file), text, program, overrides)
