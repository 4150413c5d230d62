"""The recipe endpoints of the HTTP API, for the Recipes screen (issue 12).

- ``GET /api/recipes``: the recipes of the recipes folder (``<name>.yaml``), with a title.
- ``GET /api/recipes/{name}``: one recipe's text.
- ``POST /api/recipes/validate {"text", "name"?}``: read and compiled as
  ``supervisor check`` does, with the same messages at the same line and column (the text
  is named ``<recipes dir>/<name>.yaml``, the file it would be saved as: a relative profile
  CSV is found where it would be). 200 ``{"ok": true, ...}``, 422 ``{"ok": false, "errors":
  [{"line", "column", "message", "file", "text"}]}`` (``text``: the line ``supervisor
  check`` prints).
- ``POST /api/recipes/dryrun {"text", "name"?, "parameters"?, "channel"?, "max_hours"?}``:
  the dry run (``supervisor dry-run``'s, injected as :class:`DryRunner`: this layer does not
  import the application's) with its timeline, capacity per cycle and a V/I trace of at
  most ``MAX_TRACE_POINTS`` points. ``channel``: the recipe is also checked against that
  channel's limits and runs on that channel's own plant (its supply, battery and sensors,
  simulated from the I/O map). One at a time (409 else).
- ``PUT /api/recipes/{name} {"text", "overwrite"?}``: engineers only; validated first, then
  written atomically (a temporary file in the same folder, then a rename: a reader sees the
  old recipe or the new one, never half of one). 422 with the errors and nothing written;
  409 when the recipe exists and ``"overwrite": true`` was not given.

Names match :data:`NAME_PATTERN` (no folder, no ``..``): anything else is refused before a
path is made of it. A text over ``MAX_YAML_BYTES`` is answered 413 with the message
``supervisor check`` gives for such a file; so is a request body too large to hold one.
Validation runs in a child process (``commands/childjob.py``) with a deadline and a memory
limit, killed when abandoned, never on the scan's event loop nor in a thread of its
process (issue 28: an abandoned thread ran on, holding the scan's CPU, memory and
lock); the disk is read and written in threads. A dry run runs flat out for seconds:
``supervisor run`` computes it in a child process (``app/preview.py`` says why: in a
thread it cost the scan deadlines), stopped at ``DRY_RUN_PREVIEW_TIMEOUT_S``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import re
import tempfile
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Final, Protocol

from aiohttp import web

from supervisor.audit import AuditLog, text_change
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.program import Program
from supervisor.commands.childjob import (
    ChildJobError,
    ChildJobs,
    ChildJobsBusy,
    ChildOutOfMemory,
)
from supervisor.commands.recipes import RecipeFolders, read_recipe_text
from supervisor.config.limits import (
    DRY_RUN_PREVIEW_TIMEOUT_S,
    MAX_YAML_BYTES,
    RECIPE_CHECK_MEMORY_BYTES,
    RECIPE_CHECK_WORKERS,
    RECIPE_COMPILE_TIMEOUT_S,
    size_text,
    too_large_message,
)
from supervisor.config.recipe import load_recipe_text
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.core.records import Record
from supervisor.hmi import body as body_reader

log = logging.getLogger(__name__)

__all__ = [
    "MAX_TRACE_POINTS",
    "NAME_PATTERN",
    "Checked",
    "DryRunner",
    "RecipesApi",
    "RecipesConfig",
    "Trace",
    "add_recipe_routes",
    "check_recipe_text",
    "cycle_json",
    "error_json",
    "timeline_json",
    "valid_name",
]

NAME_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,79}$")
"""A recipe's name (its file is ``<name>.yaml`` in the recipes folder): no folder, no
leading dot (hidden and temporary files), and no ``..`` anywhere."""
SUFFIX: Final = ".yaml"
MAX_TRACE_POINTS: Final = 2000
"""Points of a dry run's trace (a plot is about a thousand pixels wide)."""
MAX_BODY_BYTES: Final = 6 * MAX_YAML_BYTES + 64 * 1024
"""A request body: a recipe at its limit as a JSON string (``\\u00e8`` is six bytes for
the two of ``è``) and the other members. Read by this module, not by aiohttp, whose own
limit (1 MiB) is below a recipe at its limit once escaped."""
TITLE_SCAN_BYTES: Final = 64 * 1024
"""How much of a recipe the listing reads for its title (``description:`` or ``recipe:``
at the top level): a listing does not parse every recipe in full."""
MAX_PREVIEW_HOURS: Final = 1000.0
"""The virtual time a preview runs at most by default (``supervisor dry-run``'s default)."""

RoleOf = Callable[[web.Request], "str | None"]
"""The role of the request's user (viewer, operator, engineer), None without a session."""
ActorOf = Callable[[web.Request], str]


def _everyone_engineer(request: web.Request) -> str | None:
    # Without login (``hmi.login`` false) everyone on the loopback API may edit recipes,
    # as everyone may operate (docs: the HMI contract, Access).
    return "engineer"


def _hmi_actor(request: web.Request) -> str:
    return "hmi"


class DryRunner(Protocol):
    """``supervisor.app.preview.preview_in_child`` (the composition root hands it over):
    the dry run's answer as a mapping (``recipe``, ``end_reason``, ``finished``,
    ``simulated_s``, ``timed_out``, ``summary`` as summary.json, ``trace`` as
    :meth:`Trace.as_json`), or ``{"errors": [{"message", "file", "line", "col"}]}``; raises
    when no answer came (the reason is its message). ``channel``: run on that channel's own
    plant (its supply, battery and sensors, from the bench's I/O map)."""

    async def __call__(
        self,
        file: str,
        text: str,
        params: Mapping[str, str],
        capacity_ah: float | None,
        max_hours: float,
        timeout_s: float,
        channel: str | None = None,
    ) -> Mapping[str, Any]: ...


@dataclass
class RecipesConfig:
    """What the recipe endpoints need (``supervisor run`` builds it)."""

    recipes_dir: Path
    """Where the editor lists and saves recipes (the first recipe folder)."""
    dry_run: DryRunner | None = None
    """None: ``POST /api/recipes/dryrun`` answers 503."""
    target_of: Callable[[str], Target] | None = None
    """A channel's target (``Bench.target``) for a dry run or validation on a channel."""
    channels: Collection[str] = ()
    role_of: RoleOf = _everyone_engineer
    actor_of: ActorOf = _hmi_actor
    validate_timeout_s: float = RECIPE_COMPILE_TIMEOUT_S
    dry_run_timeout_s: float = DRY_RUN_PREVIEW_TIMEOUT_S
    folders: RecipeFolders | None = None
    """The command path's path policy (ADR 0026): a recipe is read only when its real path
    is inside one of them (a symbolic link in the folder to a file elsewhere is not
    served). None: ``recipes_dir`` alone."""
    checks: ChildJobs | None = None
    """Where texts are parsed and compiled: child processes with a deadline and a memory
    limit, killed when abandoned (``commands/childjob.py``). None: the API makes its own
    and kills them when the application stops."""
    audit: AuditLog | None = None
    """Where a save is recorded (``recipe.save``: the text's SHA-256, a diff against the
    version it replaced); None: not recorded."""


# --- validation (pure: safe in a child process) -------------------------------------------
@dataclass(frozen=True)
class Checked:
    """A recipe text that compiled, and its parameters as written (``"1.0 V"``)."""

    program: Program
    parameters: dict[str, str]

    def as_json(self) -> dict[str, Any]:
        p = self.program
        return {
            "ok": True,
            "recipe": p.name,
            "description": p.description,
            "steps": len(p.steps),
            "cycles": p.cycles,
            "parameters": [
                {"name": k, "value": v, "si": p.parameters.get(k)}
                for k, v in self.parameters.items()
            ],
        }


def check_recipe_text(
    text: str,
    file: str,
    target: Target | None = None,
    overrides: Mapping[str, str] | None = None,
    folders: RecipeFolders | None = None,
) -> Checked:
    """Parse and compile ``text`` as ``supervisor check`` does the file ``file``
    (``ConfigErrors`` with the same messages); ``target``: also against a channel;
    ``overrides``: parameter values given for a run; ``folders``: a file the recipe reads
    (a load profile) only from them (ADR 0026)."""
    recipe, pos = load_recipe_text(text, file)
    files = folders.refuse_file if folders is not None else None
    try:
        program = compile_recipe(recipe, pos, file, target, overrides, files)
        return Checked(program, {k: str(v) for k, v in recipe.parameters.items()})
    finally:
        del recipe
        pos.release_gradually()


def check_recipe_job(
    text: str,
    file: str,
    target: Target | None,
    overrides: Mapping[str, str] | None,
    folders: RecipeFolders | None,
) -> dict[str, Any]:
    """:func:`check_recipe_text` as plain data, for a child process (``ChildJobs``): the
    answer of ``Checked.as_json`` with ``"steps"``, or ``{"errors": [{"message", "file",
    "line", "col"}]}``."""
    try:
        return check_recipe_text(text, file, target, overrides, folders).as_json()
    except ConfigErrors as exc:
        errors = exc.errors
    except ConfigError as exc:
        errors = [exc]
    return {
        "errors": [
            {"message": e.message, "file": e.file, "line": e.line, "col": e.col} for e in errors
        ]
    }


PRELOAD: Final = ("supervisor.hmi.recipes_api",)
"""What a check's child process needs imported (once, in the fork server)."""


def recipe_checks(
    workers: int = RECIPE_CHECK_WORKERS, memory_limit_bytes: int = RECIPE_CHECK_MEMORY_BYTES
) -> ChildJobs:
    """The child processes recipe texts are checked in (``supervisor run`` makes them)."""
    return ChildJobs(workers, workers, memory_limit_bytes, PRELOAD)


def error_json(e: ConfigError) -> dict[str, Any]:
    return {
        "line": e.line,
        "column": e.col,
        "message": e.message,
        "file": e.file,
        "text": e.location_message(),
    }


def _config_error(e: Mapping[str, Any]) -> ConfigError:
    return ConfigError(str(e["message"]), e.get("file"), e.get("line"), e.get("col"))


class Trace:
    """At most ``limit`` records' time, voltage, current and temperature, spread over the
    whole run without knowing its length: every ``stride``-th record is kept, and when the
    buffer is full every other kept point is dropped and the stride doubles. The last
    record is always the last point."""

    def __init__(self, limit: int = MAX_TRACE_POINTS) -> None:
        if limit < 2:
            raise ValueError("a trace keeps at least two points")
        self.limit = limit
        self.stride = 1
        self.seen = 0
        self.points: list[tuple[float, float | None, float | None, float | None]] = []
        self.last: tuple[float, float | None, float | None, float | None] | None = None

    def __call__(self, rec: Record) -> None:
        point = (rec.test_time_s, rec.voltage_v, rec.current_a, rec.temperature_c)
        if self.seen % self.stride == 0:
            self.points.append(point)
            self.last = None
            if len(self.points) >= self.limit:  # room for the last record
                newest = self.points[-1]
                self.points = self.points[::2]
                self.stride *= 2
                if self.points[-1] is not newest:
                    self.last = newest
        else:
            self.last = point
        self.seen += 1

    def as_json(self) -> dict[str, Any]:
        points = self.points + ([self.last] if self.last is not None else [])
        return {
            "t_s": [round(p[0], 3) for p in points],
            "voltage_v": [p[1] for p in points],
            "current_a": [p[2] for p in points],
            "temperature_c": [p[3] for p in points],
            "records": self.seen,
        }


def cycle_json(c: Mapping[str, Any]) -> dict[str, Any]:
    """A summary.json cycle (publish/results.py) as the screens plot it."""
    return {
        "cycle": c["cycle"],
        "charge_ah": c.get("charge_capacity_ah"),
        "discharge_ah": c.get("discharge_capacity_ah"),
        "efficiency": c.get("coulombic_efficiency"),
        "energy_efficiency": c.get("energy_efficiency"),
        "charge_wh": c.get("charge_energy_wh"),
        "discharge_wh": c.get("discharge_energy_wh"),
        "complete": c.get("complete"),
        "note": c.get("efficiency_note"),
    }


def timeline_json(e: Mapping[str, Any]) -> dict[str, Any]:
    """A summary.json timeline event as the screens draw it."""
    return {
        "t_s": e.get("test_time_s"),
        "kind": e.get("kind"),
        "step": e.get("step"),
        "cycle": e.get("cycle"),
        "text": e.get("text"),
    }


def _hms(s: float) -> str:
    s = round(s)
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


# --- JSON in and out ----------------------------------------------------------------------
def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def _dumps(obj: Any) -> str:
    """JSON any parser reads (RFC 8259 has no NaN nor Infinity; see hmi/server.py)."""
    try:
        return json.dumps(obj, allow_nan=False)
    except ValueError:
        return json.dumps(_finite(obj), allow_nan=False)


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, dumps=_dumps)


def _error(status: int, reason: str, **more: Any) -> web.Response:
    body = {"ok": False, "error": _STATUS_WORD.get(status, "error"), "reason": reason}
    return _json({**body, **more}, status)


_STATUS_WORD: Final = {
    400: "bad request",
    401: "not logged in",
    403: "forbidden",
    404: "not found",
    409: "conflict",
    413: "too large",
    422: "recipe refused",
    500: "internal error",
    503: "unavailable",
}


def _refused(errors: list[ConfigError], status: int = 422) -> web.Response:
    first = errors[0].location_message() if errors else ""
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return _error(status, f"{first}{more}", errors=[error_json(e) for e in errors])


class BadBody(Exception):
    def __init__(
        self,
        status: int,
        reason: str,
        errors: list[ConfigError] | None = None,
        retry_after_s: int | None = None,
        close: bool = False,
    ):
        super().__init__(reason)
        self.close = close  # the body could not be read (an encoding not taken)
        self.status = status
        self.reason = reason
        self.errors = errors or []
        self.retry_after_s = retry_after_s

    def response(self) -> web.Response:
        resp = (
            _refused(self.errors, self.status) if self.errors else _error(self.status, self.reason)
        )
        if self.status == 413 or self.close:
            # The rest of the body is not read: the connection is closed after the answer
            # instead of reading on to the next request.
            resp.force_close()
        if self.retry_after_s is not None:
            resp.headers["Retry-After"] = str(self.retry_after_s)
        return resp


async def read_json_object(
    request: web.Request, limit_bytes: int = MAX_BODY_BYTES
) -> dict[str, Any]:
    """The request's JSON object, read here up to ``limit_bytes`` (413 above)."""
    too_large = (
        f"request body is too large: more than {size_text(limit_bytes)}; a recipe may have"
        f" at most {size_text(MAX_YAML_BYTES)} (README: Input limits)"
    )
    length = request.content_length
    if length is not None and length > limit_bytes:
        raise BadBody(413, too_large)
    # The API's one body reader (``supervisor.hmi.body``): encodings, charsets, depth and
    # lone surrogates refused like on every other route.
    try:
        return await body_reader.read_json_object(
            request, limit_bytes=limit_bytes, too_large=too_large
        )
    except body_reader.BodyError as exc:
        raise BadBody(exc.status, exc.reason, close=exc.close) from None


def _only(body: Mapping[str, Any], *allowed: str) -> None:
    unknown = sorted(set(body) - set(allowed))
    if unknown:
        raise BadBody(400, f"unknown member {', '.join(unknown)} (expected: {', '.join(allowed)})")


def recipe_text(body: Mapping[str, Any], file: str) -> str:
    """``body["text"]``, refused 413 over ``MAX_YAML_BYTES`` with the message
    ``supervisor check`` gives for such a file."""
    text = body.get("text")
    if not isinstance(text, str):
        raise BadBody(400, 'the body must have "text": the recipe\'s YAML as a string')
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_YAML_BYTES:
        message = too_large_message("a recipe or an I/O map", f"{size:,} bytes", MAX_YAML_BYTES)
        raise BadBody(413, message, [ConfigError(message, file)])
    return text


def _parameters(body: Mapping[str, Any]) -> dict[str, str]:
    p = body.get("parameters") or {}
    if not isinstance(p, dict):
        raise BadBody(400, "parameters must be an object {name: value}")
    out: dict[str, str] = {}
    for k, v in p.items():
        number = isinstance(v, int | float) and not isinstance(v, bool)
        if not (isinstance(v, str) or number) or (number and not math.isfinite(v)):
            raise BadBody(400, f"parameter {k}: {v!r} is not a value (a quantity such as '1.8 V')")
        out[str(k)] = str(v)
    return out


# --- the recipes folder ---------------------------------------------------------------------
def valid_name(name: str) -> bool:
    return bool(NAME_PATTERN.match(name)) and ".." not in name


def _title(path: Path) -> str:
    """``description:`` (else ``recipe:``) of the recipe's top level, from its start."""
    try:
        with path.open("rb") as f:
            head = f.read(TITLE_SCAN_BYTES).decode("utf-8", "replace")
    except OSError:
        return ""
    found: dict[str, str] = {}
    for line in head.splitlines():
        m = re.match(r"^(recipe|description):\s*(.*?)\s*$", line)
        if m and m.group(1) not in found:
            value = m.group(2)
            if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
                value = value[1:-1]
            found[m.group(1)] = value
    return found.get("description") or found.get("recipe") or ""


def _read(path: Path) -> tuple[str, float]:
    return read_recipe_text(path), path.stat().st_mtime


class RecipesApi:
    """The handlers (``add_recipe_routes`` registers them)."""

    def __init__(self, config: RecipesConfig) -> None:
        self.config = config
        self.dir = config.recipes_dir
        self.folders = config.folders or RecipeFolders.of([config.recipes_dir])
        self._save_lock = asyncio.Lock()
        self._dry_running = False
        self.own_checks = config.checks is None
        self.checks = config.checks if config.checks is not None else recipe_checks()

    def file_of(self, name: str) -> str:
        """The file a recipe ``name`` is (as ``supervisor check`` would be given it)."""
        return str(self.dir / f"{name}{SUFFIX}")

    def _name(self, request: web.Request) -> str:
        name = request.match_info["name"]
        if not valid_name(name):
            raise BadBody(
                400,
                f"recipe name {name[:80]!r} refused: letters, digits, '_', '-' and '.', not"
                " starting with '.' and without '..' (no folder)",
            )
        return name

    def _body_name(self, body: Mapping[str, Any]) -> str:
        name = body.get("name", "recipe")
        if not isinstance(name, str) or not valid_name(name):
            raise BadBody(400, f"name {str(name)[:80]!r} refused (letters, digits, '_', '-', '.')")
        return name

    def _target(self, body: Mapping[str, Any]) -> Target | None:
        channel = body.get("channel")
        if channel is None:
            return self._bench_target()
        if not isinstance(channel, str) or self.config.target_of is None:
            raise BadBody(400, "channel must be a channel's name")
        if channel not in self.config.channels:
            known = ", ".join(sorted(self.config.channels))
            raise BadBody(404, f"unknown channel {channel!r} ({known})")
        return self.config.target_of(channel)

    def _bench_target(self) -> Target | None:
        """No channel named: the bench's tags alone, which a recipe's conditions may name
        (``bms.cell_max``, as ``supervisor check MAP RECIPE`` checks it); no channel's
        limits. None without a bench."""
        if self.config.target_of is None or not self.config.channels:
            return None
        return Target(tags=self.config.target_of(next(iter(self.config.channels))).tags)

    # --- reading ------------------------------------------------------------------------
    def _listing(self) -> list[dict[str, Any]]:
        out = []
        try:
            entries = sorted(self.dir.iterdir())
        except OSError as exc:
            log.warning("recipes: cannot list %s: %s", self.dir, exc)
            return []
        for path in entries:
            name = path.name.removesuffix(SUFFIX)
            if not path.name.endswith(SUFFIX) or not valid_name(name) or not path.is_file():
                continue
            if not self.folders.inside(path):  # a link to elsewhere: not a recipe here
                continue
            try:
                modified = path.stat().st_mtime
            except OSError:
                continue
            out.append(
                {"name": name, "file": str(path), "title": _title(path), "modified": modified}
            )
        return out

    async def list(self, request: web.Request) -> web.Response:
        return _json({"recipes": await asyncio.to_thread(self._listing)})

    async def get(self, request: web.Request) -> web.Response:
        try:
            name = self._name(request)
        except BadBody as exc:
            return exc.response()
        path = Path(self.file_of(name))
        if not await asyncio.to_thread(path.is_file):
            return _error(404, f"no recipe {name!r} in {self.dir}")
        if not await asyncio.to_thread(self.folders.inside, path):
            return _error(
                403,
                f"recipe {name!r} is a link to a file outside the recipe folders: recipes are"
                f" read only from {self.folders.describe()}",
            )
        try:
            text, modified = await asyncio.to_thread(_read, path)
        except ConfigErrors as exc:
            return _refused(exc.errors)
        except OSError as exc:
            return _error(404, f"recipe {name!r}: {exc.strerror or exc}")
        return _json({"name": name, "file": str(path), "text": text, "modified": modified})

    # --- validating ---------------------------------------------------------------------
    async def _check(
        self,
        text: str,
        file: str,
        target: Target | None,
        overrides: Mapping[str, str] | None = None,
    ) -> dict[str, Any]:
        """``check_recipe_text`` in a child process (``Checked.as_json``); ``ConfigErrors``
        when refused; ``BadBody`` 503 past the time limit or when too many run, 413 past
        the memory limit. The child is killed if the request goes away meanwhile."""
        timeout_s = self.config.validate_timeout_s
        what = f"validating {file}"
        try:
            answer: dict[str, Any] = await self.checks.run(
                check_recipe_job, (text, file, target, overrides, self.folders), timeout_s, what
            )
        except ChildJobsBusy as exc:
            raise BadBody(503, str(exc), retry_after_s=exc.retry_after_s) from None
        except ChildOutOfMemory as exc:
            raise BadBody(413, f"{exc} (README: Input limits)") from None
        except ChildJobError as exc:  # its deadline, or it crashed
            raise BadBody(503, f"{exc} (README: Input limits)") from None
        if "errors" in answer:
            raise ConfigErrors([_config_error(e) for e in answer["errors"]])
        return answer

    async def close(self) -> None:
        """Kill the checks under way and wait for their end (the application stops)."""
        await self.checks.close()

    async def validate(self, request: web.Request) -> web.Response:
        try:
            body = await read_json_object(request)
            _only(body, "text", "name", "channel")
            file = self.file_of(self._body_name(body))
            text = recipe_text(body, file)
            checked = await self._check(text, file, self._target(body))
        except BadBody as exc:
            return exc.response()
        except ConfigErrors as exc:
            return _refused(exc.errors)
        answer = {**checked, "file": file}
        return _json(answer)

    # --- dry run ------------------------------------------------------------------------
    async def dryrun(self, request: web.Request) -> web.Response:
        runner = self.config.dry_run
        if runner is None:
            return _error(503, "no dry run on this server")
        try:
            body = await read_json_object(request)
            _only(body, "text", "name", "parameters", "channel", "max_hours")
            file = self.file_of(self._body_name(body))
            text = recipe_text(body, file)
            params = _parameters(body)
            target = self._target(body)
            max_hours = body.get("max_hours", MAX_PREVIEW_HOURS)
            if (
                isinstance(max_hours, bool)
                or not isinstance(max_hours, int | float)
                or not 0 < max_hours <= MAX_PREVIEW_HOURS
            ):
                raise BadBody(400, f"max_hours must be a number in (0, {MAX_PREVIEW_HOURS:g}]")
            if self._dry_running:
                raise BadBody(409, "a dry run is being computed: wait for its answer")
        except BadBody as exc:
            return exc.response()
        self._dry_running = True
        try:
            # Refused as `supervisor check` refuses it (and by the channel, if one is named)
            # before anything is simulated.
            await self._check(text, file, target, params)
            return await self._dry_run(runner, file, text, params, target, float(max_hours))
        except BadBody as exc:
            return exc.response()
        except ConfigErrors as exc:
            return _refused(exc.errors)
        finally:
            self._dry_running = False

    async def _dry_run(
        self,
        runner: DryRunner,
        file: str,
        text: str,
        params: dict[str, str],
        target: Target | None,
        max_hours: float,
    ) -> web.Response:
        timeout_s = self.config.dry_run_timeout_s
        capacity_ah = target.capacity_ah if target is not None else None
        channel = target.channel if target is not None else None
        try:
            res = await runner(file, text, params, capacity_ah, max_hours, timeout_s, channel)
        except Exception as exc:  # no answer (killed at its limit, crashed): say why
            log.error("recipes: dry run of %s: %s", file, exc)
            return _error(503, f"{exc} (README: Input limits)")
        if "errors" in res:
            return _refused([_config_error(e) for e in res["errors"]])
        end_reason = str(res["end_reason"])
        if res.get("timed_out"):
            end_reason = (
                f"the preview stopped after {timeout_s:g} s of computing, at test time"
                f" {_hms(float(res['simulated_s']))}; `supervisor dry-run {file}` runs it to"
                " its end"
            )
        summary: Mapping[str, Any] = res["summary"]
        return _json(
            {
                "ok": True,
                "recipe": res["recipe"],
                "file": file,
                "finished": res["finished"],
                "state": summary.get("state"),
                "duration_s": round(float(res["simulated_s"]), 3),
                "end_reason": end_reason,
                "cycles": [cycle_json(c) for c in summary.get("cycles", [])],
                "cycles_omitted": summary.get("cycles_omitted", 0),
                "timeline": [timeline_json(e) for e in summary.get("timeline", [])],
                "timeline_omitted": summary.get("timeline_omitted", 0),
                "trace": res["trace"],
            }
        )

    # --- saving -------------------------------------------------------------------------
    async def save(self, request: web.Request) -> web.Response:
        role = self.config.role_of(request)
        if role is None:
            return _error(401, "log in to save a recipe")
        if role != "engineer":
            return _error(403, f"{role} may not save recipes (engineers only)")
        try:
            name = self._name(request)
            body = await read_json_object(request)
            _only(body, "text", "overwrite")
            overwrite = body.get("overwrite", False)
            if not isinstance(overwrite, bool):
                raise BadBody(400, "overwrite must be true or false")
            file = self.file_of(name)
            text = recipe_text(body, file)
            checked = await self._check(text, file, self._bench_target())
        except BadBody as exc:
            return exc.response()
        except ConfigErrors as exc:
            return _refused(exc.errors)
        actor = self.config.actor_of(request)
        async with self._save_lock:
            try:
                previous = await asyncio.to_thread(_previous_text, Path(file), self.config.audit)
                created = await asyncio.to_thread(self._write, Path(file), text, overwrite)
            except FileExistsError:
                return _error(
                    409,
                    f'recipe {name!r} exists: send "overwrite": true to replace it',
                    exists=True,
                )
            except OSError as exc:
                log.error("recipes: %s cannot save %s: %s", actor, file, exc)
                return _error(500, f"cannot save {file}: {exc.strerror or exc}")
        log.info(
            "recipes: %s %s %s (%d steps)",
            actor,
            "created" if created else "replaced",
            file,
            checked["steps"],
        )
        audit = self.config.audit
        if audit is not None:
            change = await asyncio.to_thread(text_change, previous, text, name)
            audit.append(actor, "recipe.save", file, {**change, "created": created})
        answer = dict(checked)
        answer.update({"saved": True, "created": created, "name": name, "file": file})
        return _json(answer)

    def _write(self, path: Path, text: str, overwrite: bool) -> bool:
        """Write ``text`` as ``path`` atomically; True when it did not exist. Without
        ``overwrite`` an existing file is never replaced (``FileExistsError``), not even
        one that appears meanwhile: the new file is linked in, which fails if one exists."""
        self.dir.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=self.dir)
        tmp = Path(tmp_name)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(text.encode("utf-8"))
                f.flush()
                os.fsync(f.fileno())
            tmp.chmod(0o644)
            if overwrite:
                existed = path.exists()
                tmp.replace(path)
                return not existed
            os.link(tmp, path)  # atomic, and refuses to replace
            return True
        finally:
            tmp.unlink(missing_ok=True)


def _previous_text(path: Path, audit: AuditLog | None) -> str | None:
    """The text a save replaces, for the audit trail's diff (None: none, or not audited)."""
    if audit is None:
        return None
    try:
        return path.read_text("utf-8", "surrogateescape")
    except OSError:  # absent (a new recipe), or unreadable: the diff is against nothing
        return None


def add_recipe_routes(
    app: web.Application,
    config: RecipesConfig,
    role_of: RoleOf | None = None,
    actor_of: ActorOf | None = None,
) -> RecipesApi:
    """Register the recipe endpoints on ``app``. ``role_of`` and ``actor_of`` (the HTTP
    API's sessions: the user's role, None without a valid session; ``hmi:<user>``)
    replace the configuration's."""
    if role_of is not None:
        config = replace(config, role_of=role_of)
    if actor_of is not None:
        config = replace(config, actor_of=actor_of)
    api = RecipesApi(config)
    if api.own_checks:

        async def kill_checks(app: web.Application) -> None:
            await api.close()

        app.on_shutdown.append(kill_checks)
    app.add_routes(
        [
            web.get("/api/recipes", api.list),
            web.post("/api/recipes/validate", api.validate),
            web.post("/api/recipes/dryrun", api.dryrun),
            web.get("/api/recipes/{name}", api.get),
            web.put("/api/recipes/{name}", api.save),
        ]
    )
    return api
