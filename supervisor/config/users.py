"""Bench users (OPC UA and the HMI): names, roles, password hashes (never a password).

``users.yaml`` (``<state_dir>/opcua/users.yaml`` unless the I/O map names another)::

    users:
      alice: {role: operator, password: "scrypt$16384$8$1$<salt>$<hash>"}

Roles (docs/design.md "Tags", access levels): a **viewer** (and an anonymous session) reads and
subscribes; an **operator** also calls the channel methods and writes operator tags; an
**engineer** also writes engineer tags (limits). Hashes are scrypt (RFC 7914, n=2^14, r=8,
p=1: about 50 ms and 16 MB per check, which is what makes a stolen file slow to attack);
``supervisor opcua add-user`` writes them. A password given in clear in the file is refused
with the line that holds it.

The file is read again when it changes, so a user added while the bench runs can log in
without a restart. A successful check is remembered as an HMAC under a key that lives only
in this process, so the next login of the same user costs microseconds, not 50 ms (20
clients connecting at once would otherwise queue a second of scrypt).

An unknown user name costs the same scrypt as a wrong password: it is checked against a
dummy hash made with the same parameters (issue 27: an unknown name answered in 2.7 ms, a
known one in 188 ms, which told a guesser which names exist).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import os
import re
import secrets
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

import yaml
from pydantic import Field, field_validator

from supervisor.config.models import Strict
from supervisor.config.yamlpos import load_yaml, validate
from supervisor.core.encoding import storable_text
from supervisor.core.errors import ConfigError
from supervisor.tags import Access

log = logging.getLogger(__name__)

Role = Literal["viewer", "operator", "engineer"]
ROLES: Final[tuple[Role, ...]] = ("viewer", "operator", "engineer")
ROLE_ACCESS: Final[dict[str, Access]] = {
    "viewer": Access.READ_ONLY,
    "operator": Access.OPERATOR,
    "engineer": Access.ENGINEER,
}
ANONYMOUS: Final = "anonymous"
"""The name of an anonymous session (a viewer); no user may be called so."""

SCRYPT_N: Final = 2**14
SCRYPT_R: Final = 8
SCRYPT_P: Final = 1
SALT_BYTES: Final = 16
HASH_BYTES: Final = 32
HASH_PATTERN: Final = (
    r"^scrypt\$[0-9]+\$[0-9]+\$[0-9]+\$[A-Za-z0-9+/]+={0,2}\$[A-Za-z0-9+/]+={0,2}$"
)
NAME_PATTERN: Final = r"^[A-Za-z0-9_.@-]{1,64}$"
MAX_SCRYPT_N: Final = 2**20
"""A hash asking for more work than this is refused (a file must not make a login take
minutes or gigabytes)."""


def hash_password(password: str, *, n: int = SCRYPT_N) -> str:
    """``scrypt$n$r$p$salt$hash`` (base64) of ``password`` with a fresh random salt."""
    salt = secrets.token_bytes(SALT_BYTES)
    digest = _scrypt(password, salt, n, SCRYPT_R, SCRYPT_P)
    b64 = base64.b64encode
    return f"scrypt${n}${SCRYPT_R}${SCRYPT_P}${b64(salt).decode()}${b64(digest).decode()}"


def check_password(password: str, stored: str) -> bool:
    """Does ``password`` match the ``stored`` hash (constant-time comparison)?"""
    try:
        kind, n, r, p, salt, digest = stored.split("$")
        if kind != "scrypt":
            return False
        expected = base64.b64decode(digest, validate=True)
        got = _scrypt(password, base64.b64decode(salt, validate=True), int(n), int(r), int(p))
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got, expected)


def _within_bounds(n: int, r: int, p: int) -> bool:
    return 2 <= n <= MAX_SCRYPT_N and not n & (n - 1) and 1 <= r <= 32 and 1 <= p <= 16


def _scrypt(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    if not _within_bounds(n, r, p):
        raise ValueError("scrypt parameters out of bounds")
    return hashlib.scrypt(
        password.encode("utf-8"), salt=salt, n=n, r=r, p=p, maxmem=256 * n * r, dklen=HASH_BYTES
    )


NOT_A_HASH: Final = (
    "must be a password hash written by `supervisor opcua add-user`, never the password itself"
)


class UserEntry(Strict):
    role: Role
    # Checked by ``read_users`` (a pydantic error would repeat the value: a password).
    password: str = Field(description="scrypt hash written by `supervisor opcua add-user`")


class UsersFile(Strict):
    users: dict[str, UserEntry] = Field(default_factory=dict)

    @field_validator("users")
    @classmethod
    def _names(cls, v: dict[str, UserEntry]) -> dict[str, UserEntry]:
        for name in v:
            problem = name_problem(name)
            if problem:
                raise ValueError(problem)
        return v


def name_problem(name: str) -> str:
    """Why ``name`` cannot be a user's name ("" when it can)."""
    if name == ANONYMOUS:
        return f"{ANONYMOUS!r} is the name of anonymous sessions"
    if not re.fullmatch(NAME_PATTERN, name):  # not "$": it matches before a final newline
        return f"user name {name!r}: letters, digits and _.@- only (1 to 64 characters)"
    return ""


@dataclass(frozen=True, slots=True)
class User:
    name: str
    role: Role

    @property
    def access(self) -> Access:
        return ROLE_ACCESS[self.role]


def read_users(path: Path) -> dict[str, UserEntry]:
    """The users of ``path`` (none when it does not exist); ConfigError naming file:line:col
    for a bad file."""
    if not path.exists():
        return {}
    data, positions = load_yaml(path)
    if data is None:
        return {}
    users = validate(UsersFile, data, positions, str(path)).users
    for name, entry in users.items():
        if not re.match(HASH_PATTERN, entry.password):
            at = positions.nearest(("users", name, "password"))
            raise ConfigError(f"users.{name}.password: {NOT_A_HASH}", path, at.line, at.col)
    return users


class UserStore:
    """The users of one file, checked at login (from the OPC UA server's thread)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._key = secrets.token_bytes(32)
        self._users: dict[str, UserEntry] = {}
        self._verified: dict[str, bytes] = {}
        self._stamp: tuple[int, int] | None = None
        self._dummy: str | None = None
        self.checks = 0
        """Password hashes computed so far (scrypt runs): an unknown user costs one too."""
        self.reload()

    def reload(self) -> None:
        """Read the file again (ConfigError for a bad file: the server refuses to start)."""
        self._users = read_users(self.path)
        self._verified.clear()
        self._stamp = self._file_stamp()

    def _file_stamp(self) -> tuple[int, int] | None:
        try:
            st = self.path.stat()
        except OSError:
            return None
        return (st.st_mtime_ns, st.st_size)

    def _refresh(self) -> None:
        if self._file_stamp() == self._stamp:
            return
        try:
            self.reload()
            log.info("OPC UA users reloaded from %s (%d users)", self.path, len(self._users))
        except ConfigError as exc:  # a bad edit: keep serving the users we had
            log.error("OPC UA users not reloaded: %s", exc.location_message())
            self._stamp = self._file_stamp()

    def role_of(self, name: str) -> Role | None:
        entry = self._users.get(name)
        return entry.role if entry is not None else None

    def authenticate(self, name: str, password: str) -> User | None:
        """The user when ``password`` is theirs, else None."""
        # A character UTF-8 cannot encode (a lone surrogate from a JSON escape) would raise
        # in the hash, a 500; escaped, it is just a wrong password (no stored hash is of
        # such a text: ``core/encoding.py``).
        password = storable_text(password)
        self._refresh()
        entry = self._users.get(name)
        if entry is None:
            # The same work as a wrong password of a known user: the answer's time must not
            # tell which names exist.
            self.checks += 1
            check_password(password, self._dummy_hash())
            return None
        tag = hmac.new(self._key, f"{entry.password}\0{password}".encode(), "sha256").digest()
        known = self._verified.get(name)
        if known is not None and hmac.compare_digest(known, tag):
            return User(name, entry.role)
        self.checks += 1
        if not check_password(password, entry.password):
            return None
        self._verified[name] = tag
        return User(name, entry.role)

    def _dummy_hash(self) -> str:
        """A hash of a random password with the parameters of the file's first hash (the
        default ones for an empty file), made once: what an unknown user is checked
        against."""
        n, r, p = _params_of(next(iter(self._users.values()), None))
        if self._dummy is None or self._dummy.split("$")[1:4] != [str(n), str(r), str(p)]:
            salt = secrets.token_bytes(SALT_BYTES)
            digest = _scrypt(secrets.token_urlsafe(16), salt, n, r, p)
            b64 = base64.b64encode
            self._dummy = f"scrypt${n}${r}${p}${b64(salt).decode()}${b64(digest).decode()}"
        return self._dummy

    def __len__(self) -> int:
        return len(self._users)


def _params_of(entry: UserEntry | None) -> tuple[int, int, int]:
    """scrypt's (n, r, p) of ``entry``'s hash, the defaults when none or out of bounds."""
    default = (SCRYPT_N, SCRYPT_R, SCRYPT_P)
    if entry is None:
        return default
    try:
        n, r, p = (int(x) for x in entry.password.split("$")[1:4])
    except ValueError:
        return default
    if not _within_bounds(n, r, p):
        return default
    return (n, r, p)


def add_user(path: Path, name: str, role: str, password: str) -> bool:
    """Add ``name`` (or replace their role and password) in the users file; returns True
    when the user is new. The file is written whole and renamed into place, readable by
    its owner only."""
    if role not in ROLES:
        raise ConfigError(f"role {role!r}: one of {', '.join(ROLES)}")
    problem = name_problem(name)
    if problem:
        raise ConfigError(problem)
    if not password:
        raise ConfigError("an empty password is not a password")
    users = read_users(path)
    new = name not in users
    users[name] = UserEntry.model_validate({"role": role, "password": hash_password(password)})
    _write(path, users)
    return new


def remove_user(path: Path, name: str) -> bool:
    users = read_users(path)
    if name not in users:
        return False
    del users[name]
    _write(path, users)
    return True


def _write(path: Path, users: dict[str, UserEntry]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    body = {"users": {n: {"role": u.role, "password": u.password} for n, u in users.items()}}
    text = (
        "# OPC UA users: written by `supervisor opcua add-user` (scrypt hashes, never"
        " passwords).\n" + yaml.safe_dump(body, sort_keys=True)
    )
    fd, tmp = tempfile.mkstemp(prefix=".users.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        Path(tmp).chmod(0o600)
        Path(tmp).replace(path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
