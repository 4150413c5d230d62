"""The one command path (docs/design.md "Safety"): operator commands checked (role, state,
interlocks), executed, recorded with their actor, and answered accepted or refused with
the reason. Every client — the HTTP API, the command line, OPC UA methods — uses it.

Layer: above chains, safety and channels (it drives them), below app (which builds it).
"""

from supervisor.commands.model import (
    HTTP_STATUS,
    Command,
    CommandEvent,
    Result,
    ResultKind,
    Target,
    TargetKind,
    Verb,
)
from supervisor.commands.path import CommandPath
from supervisor.commands.recipes import (
    PreparedRecipe,
    RecipeFolders,
    RecipeLoader,
    compile_recipe_file,
    read_recipe_text,
)
from supervisor.commands.roles import EveryoneOperates, Roles

__all__ = [
    "HTTP_STATUS",
    "Command",
    "CommandEvent",
    "CommandPath",
    "EveryoneOperates",
    "PreparedRecipe",
    "RecipeFolders",
    "RecipeLoader",
    "Result",
    "ResultKind",
    "Roles",
    "Target",
    "TargetKind",
    "Verb",
    "compile_recipe_file",
    "read_recipe_text",
]
