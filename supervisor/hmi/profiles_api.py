"""Load profiles from the screens (issue 32, finding 5): the Tk HMI's "Load Profile" (seed
002 §2.3, annex VI) as endpoints of the HTTP API, for the Recipes screen.

- ``GET /api/profiles``: the profile CSVs of the recipes folder (``*.csv``) and of its
  ``profiles/`` folder (where the screens' uploads are kept).
- ``POST /api/profiles/preview {"csv_base64" | "csv" | "file", "name"?, "channel"?}``: the
  CSV read as ``supervisor import profile`` reads it (columns by name, Unix timestamps
  made relative), answered with its first rows (``table``), a current trace of at most
  ``MAX_CHART_POINTS`` points (``chart``), the reader's notices and the recipe made of it
  (``recipe``, ``text``): the text the dry run (``POST /api/recipes/dryrun``) takes.
  ``csv_base64``: the file's bytes (its encoding is found as from a file: UTF-8 or
  CP1252); ``csv``: its text; ``file``: a CSV of the list above. ``name``: the uploaded
  file's name, which errors and the recipe name come from. ``channel``: also checked
  against that channel's limits. 422 ``{"errors": [{"file", "line", "column", "message",
  "text"}]}`` at the first error's line and column.
- ``POST /api/profiles/load {... as preview, "channel"}``: operators and engineers (the
  recipe load's role): the recipe is written into ``profiles/`` of the recipes folder
  (with the CSV beside it) and loaded on the channel through the command path — checked,
  recorded with its actor, answered as ``PUT /api/channels/{ch}/recipe`` is. The screen
  then starts it with the channel's start command.

The CSV is read and compiled in a child process with a deadline and a memory limit (the
recipe checks' ``ChildJobs``: a file of 100,000 rows costs seconds, never the scan's).
A profile whose recipe is over a recipe's size limit (about 30,000 rows inline) is
refused here with the way round: ``supervisor import profile`` names the CSV instead.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import logging
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from supervisor.audit import sha256_bytes, sha256_text
from supervisor.chains.compiler import Target
from supervisor.chains.profile_csv import parse_profile_csv
from supervisor.chains.profile_recipe import (
    check_points,
    compile_profile_recipe,
    profile_recipe_name,
    profile_recipe_text,
)
from supervisor.chains.program import ProfilePoint
from supervisor.commands import Command, CommandPath, Verb
from supervisor.commands import Target as CommandTarget
from supervisor.commands.childjob import ChildJobError, ChildJobsBusy, ChildOutOfMemory
from supervisor.config.limits import (
    MAX_PROFILE_CSV_BYTES,
    MAX_YAML_BYTES,
    read_limited,
    too_large_message,
)
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.hmi.recipes_api import (
    BadBody,
    RecipesApi,
    error_json,
    read_json_object,
    valid_name,
)

log = logging.getLogger(__name__)

__all__ = [
    "MAX_CHART_POINTS",
    "MAX_TABLE_ROWS",
    "PROFILES_DIR",
    "ProfilesApi",
    "add_profile_routes",
    "profile_job",
]

PROFILES_DIR: Final = "profiles"
"""Where, in the recipes folder, the screens keep the profiles they load."""
MAX_TABLE_ROWS: Final = 200
"""Rows of a preview's table (the chart shows the whole profile)."""
MAX_CHART_POINTS: Final = 2000
MAX_BODY_BYTES: Final = 2 * MAX_PROFILE_CSV_BYTES + 64 * 1024
"""A CSV at its limit as base64 (4/3) or as a JSON string of ASCII (``\\n`` is two
bytes), and the other members."""
_FIELDS: Final = ("v_min", "v_max", "i_min", "i_max", "t_min", "t_max")
_SOURCES: Final = ("csv_base64", "csv", "file")

ActorOf = Callable[[web.Request], str]


# --- the job (pure: run in a child process) -------------------------------------------------
def _row_json(p: ProfilePoint) -> dict[str, float | None]:
    row: dict[str, float | None] = {"t_s": p.t_s, "current_a": p.current_a}
    row.update({f: getattr(p, f) for f in _FIELDS})
    return row


def _chart(points: Sequence[ProfilePoint]) -> dict[str, list[float]]:
    """Every n-th point (and the last) up to ``MAX_CHART_POINTS``, as a step plot."""
    stride = max(1, -(-len(points) // (MAX_CHART_POINTS - 1)))
    kept = list(points[::stride])
    if kept[-1] is not points[-1]:
        kept.append(points[-1])
    return {"t_s": [p.t_s for p in kept], "current_a": [p.current_a for p in kept]}


def _errors(errors: Sequence[ConfigError]) -> dict[str, Any]:
    return {"errors": [error_json(e) for e in errors]}


def profile_job(raw: bytes, source: str, name: str, target: Target | None) -> dict[str, Any]:
    """The preview of a profile CSV's bytes (``source`` names it in errors; ``name``: its
    file name, the recipe's name comes from), or ``{"errors": [...]}``."""
    try:
        table = parse_profile_csv(raw, source)
        check_points(table.points, source)
        recipe = profile_recipe_name(Path(name).stem)
        text = profile_recipe_text(table, name, recipe)
        if len(text.encode("utf-8")) > MAX_YAML_BYTES:
            size = f"{len(table.points):,} rows"
            raise ConfigError(
                too_large_message("a profile loaded from the screens", size, MAX_YAML_BYTES)
                + "; `supervisor import profile` makes a recipe that names the CSV",
                source,
            )
        compile_profile_recipe(text, f"{PROFILES_DIR}/{recipe}.yaml", source, target)
    except ConfigErrors as exc:
        return _errors(exc.errors)
    except ConfigError as exc:
        return _errors([exc])
    points = table.points
    return {
        "ok": True,
        "file": source,
        "recipe": recipe,
        "rows": len(points),
        "duration_s": points[-1].t_s - points[0].t_s,
        "notices": list(table.notices),
        "unix_start_s": table.unix_start_s,
        "table": [_row_json(p) for p in points[:MAX_TABLE_ROWS]],
        "chart": _chart(points),
        "text": text,
    }


# --- the endpoints ----------------------------------------------------------------------------
def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status)


def _refused(errors: Sequence[Mapping[str, Any]]) -> web.Response:
    first = str(errors[0].get("text") or errors[0].get("message")) if errors else ""
    return _json({"ok": False, "error": "profile refused", "reason": first, "errors": errors}, 422)


def _upload_name(body: Mapping[str, Any]) -> str:
    name = body.get("name", "profile.csv")
    if not isinstance(name, str) or not name.strip():
        raise BadBody(400, "name must be the profile's file name")
    return Path(name.replace("\\", "/")).name[:120] or "profile.csv"


class ProfilesApi:
    """The handlers (``add_profile_routes`` registers them)."""

    def __init__(self, recipes: RecipesApi, commands: CommandPath, actor_of: ActorOf) -> None:
        self.recipes = recipes
        self.config = recipes.config
        self.commands = commands
        self.actor_of = actor_of
        self.dir = recipes.dir / PROFILES_DIR
        self._write_lock = asyncio.Lock()

    # --- the CSVs of the recipes folder ---------------------------------------------------
    def _listing(self) -> list[dict[str, Any]]:
        out = []
        for folder, prefix in ((self.recipes.dir, ""), (self.dir, f"{PROFILES_DIR}/")):
            try:
                entries = sorted(folder.glob("*.csv"))
            except OSError:
                continue
            for path in entries:
                if not valid_name(path.name) or not self.recipes.folders.inside(path):
                    continue
                try:
                    st = path.stat()
                except OSError:
                    continue
                out.append(
                    {"name": prefix + path.name, "size": st.st_size, "modified": st.st_mtime}
                )
        return out

    async def list(self, request: web.Request) -> web.Response:
        return _json({"profiles": await asyncio.to_thread(self._listing)})

    def _folder_file(self, name: str) -> Path:
        """A CSV of the listing by its name; ``BadBody`` for anything else."""
        folder, _, base = name.rpartition("/")
        if folder not in ("", PROFILES_DIR) or not valid_name(base) or not base.endswith(".csv"):
            raise BadBody(400, f"file {name[:80]!r}: a profile CSV of GET /api/profiles")
        path = (self.dir if folder else self.recipes.dir) / base
        if not self.recipes.folders.inside(path):
            raise BadBody(403, f"{name!r} is outside the recipe folders")
        return path

    async def _source(self, body: Mapping[str, Any]) -> tuple[bytes, str, str]:
        """The CSV's bytes, the name errors give it and its file name."""
        given = [k for k in _SOURCES if k in body]
        if len(given) != 1:
            raise BadBody(400, "give the profile as one of csv_base64, csv or file")
        value = body[given[0]]
        if not isinstance(value, str):
            raise BadBody(400, f"{given[0]} must be a string")
        if given[0] == "file":
            path = self._folder_file(value)
            try:
                raw = await asyncio.to_thread(
                    read_limited, path, MAX_PROFILE_CSV_BYTES, "a load profile"
                )
            except OSError as exc:
                raise BadBody(404, f"{value}: {exc.strerror or exc}") from None
            except ConfigError as exc:
                raise BadBody(413, exc.message, [exc]) from None
            return raw, str(path), path.name
        name = _upload_name(body)
        if given[0] == "csv":
            return value.encode("utf-8", "surrogatepass"), name, name
        try:
            return base64.b64decode(value, validate=True), name, name
        except (binascii.Error, ValueError):
            raise BadBody(400, "csv_base64 is not base64") from None

    def _target(self, body: Mapping[str, Any], needed: bool) -> tuple[str | None, Target | None]:
        channel = body.get("channel")
        if channel is None and not needed:
            return None, None
        if not isinstance(channel, str) or self.config.target_of is None:
            raise BadBody(400, "channel must be a channel's name")
        if channel not in self.config.channels:
            known = ", ".join(sorted(self.config.channels))
            raise BadBody(404, f"unknown channel {channel!r} ({known})")
        return channel, self.config.target_of(channel)

    async def _read(
        self, request: web.Request, channel_needed: bool
    ) -> tuple[dict[str, Any], bytes, str | None]:
        """``(answer, raw, channel)``: the job's answer for the request's profile."""
        body = await read_json_object(request, MAX_BODY_BYTES)
        unknown = sorted(set(body) - {*_SOURCES, "name", "channel"})
        if unknown:
            raise BadBody(400, f"unknown member {', '.join(unknown)}")
        raw, source, name = await self._source(body)
        if len(raw) > MAX_PROFILE_CSV_BYTES:
            message = too_large_message(
                "a load profile", f"{len(raw):,} bytes", MAX_PROFILE_CSV_BYTES
            )
            raise BadBody(413, message, [ConfigError(message, source)])
        channel, target = self._target(body, channel_needed)
        answer = await self._run(raw, source, name, target)
        return answer, raw, channel

    async def _run(
        self, raw: bytes, source: str, name: str, target: Target | None
    ) -> dict[str, Any]:
        what = f"reading the profile {source}"
        try:
            answer: dict[str, Any] = await self.recipes.checks.run(
                profile_job, (raw, source, name, target), self.config.validate_timeout_s, what
            )
        except ChildJobsBusy as exc:
            raise BadBody(503, str(exc), retry_after_s=exc.retry_after_s) from None
        except ChildOutOfMemory as exc:
            raise BadBody(413, f"{exc} (README: Input limits)") from None
        except ChildJobError as exc:
            raise BadBody(503, f"{exc} (README: Input limits)") from None
        return answer

    async def preview(self, request: web.Request) -> web.Response:
        try:
            answer, _, _ = await self._read(request, channel_needed=False)
        except BadBody as exc:
            return exc.response()
        if "errors" in answer:
            return _refused(answer["errors"])
        return _json(answer)

    # --- loading onto a channel -------------------------------------------------------------
    def _role_refusal(self, request: web.Request) -> web.Response | None:
        role = self.config.role_of(request)
        if role is None:
            return _json({"ok": False, "reason": "log in to load a profile"}, 401)
        if role not in ("operator", "engineer"):
            reason = f"{role} may not load a profile (operators and engineers)"
            return _json({"ok": False, "accepted": False, "reason": reason}, 403)
        return None

    async def load(self, request: web.Request) -> web.Response:
        refused = self._role_refusal(request)
        if refused is not None:
            return refused
        try:
            answer, raw, channel = await self._read(request, channel_needed=True)
        except BadBody as exc:
            return exc.response()
        if "errors" in answer:
            return _refused(answer["errors"])
        recipe = str(answer["recipe"])
        async with self._write_lock:
            try:
                await asyncio.to_thread(self._write, recipe, raw, str(answer["text"]))
            except OSError as exc:
                log.error("profiles: cannot write %s into %s: %s", recipe, self.dir, exc)
                return _json({"ok": False, "reason": f"cannot write the recipe: {exc}"}, 500)
        file = f"{PROFILES_DIR}/{recipe}.yaml"
        actor = self.actor_of(request)
        log.info("profiles: %s loads %s (%d rows) on %s", actor, file, answer["rows"], channel)
        if self.config.audit is not None:  # the recipe written (its load is a command)
            sums = {"sha256": sha256_text(str(answer["text"])), "csv_sha256": sha256_bytes(raw)}
            self.config.audit.append(actor, "recipe.save", file, {**sums, "from_profile": True})
        command = Command(CommandTarget.channel(str(channel)), Verb.LOAD, {"recipe": file}, actor)
        result = await self.commands.execute_async(command)
        body = result.as_json()
        body.update({"recipe": recipe, "file": file, "notices": answer["notices"]})
        return _json(body, result.http_status)

    def _write(self, recipe: str, raw: bytes, text: str) -> None:
        """The CSV as received and its recipe, each replaced atomically."""
        self.dir.mkdir(parents=True, exist_ok=True)
        for path, data in (
            (self.dir / f"{recipe}.csv", raw),
            (self.dir / f"{recipe}.yaml", text.encode()),
        ):
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=self.dir)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
                Path(tmp).chmod(0o644)
                Path(tmp).replace(path)
            finally:
                Path(tmp).unlink(missing_ok=True)


def add_profile_routes(
    app: web.Application, recipes: RecipesApi, commands: CommandPath, actor_of: ActorOf
) -> ProfilesApi:
    """Register the profile endpoints on ``app``, beside the recipe endpoints ``recipes``
    (their folder, checks and roles); ``actor_of``: who a load's command is from."""
    api = ProfilesApi(recipes, commands, actor_of)
    app.add_routes(
        [
            web.get("/api/profiles", api.list),
            web.post("/api/profiles/preview", api.preview),
            web.post("/api/profiles/load", api.load),
        ]
    )
    return api
