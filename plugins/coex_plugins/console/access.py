"""Who may use the console: operators (they command the vehicle) and viewers (they watch).

* :class:`OperatorsFile`: names, roles and salted scrypt hashes of passwords (or of long random
  tokens made for the operator), in a JSON file (``coex operators add|remove|list``). Secrets
  are never stored, only their hashes.
* :class:`Access`: logins (failed ones rate-limited and logged), sessions (random ids in an
  HttpOnly, SameSite=Strict cookie, with an expiry), a CSRF token per session, and a command
  rate limit per operator. The web server (:mod:`.server`) asks it about every request.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coex_core.errors import ConfigError

__all__ = ["Access", "Operator", "OperatorsFile", "Session", "ROLES"]

log = logging.getLogger("coex.console.access")

ROLES = ("operator", "viewer")
FILE_VERSION = 1
#: scrypt parameters (RFC 7914): about 16 MB and tens of milliseconds per check
SCRYPT = {"n": 2**14, "r": 8, "p": 1}
MAX_NAME = 64
MAX_SECRET = 1024


@dataclass(frozen=True)
class Operator:
    name: str
    role: str
    salt: str
    hash: str
    created: float = 0.0

    @property
    def commands(self) -> bool:
        return self.role == "operator"


def _hash(secret: str, salt: bytes) -> str:
    return hashlib.scrypt(secret.encode(), salt=salt, maxmem=64 * 2**20, dklen=32, **SCRYPT).hex()


def _check_name(name: str) -> str:
    name = str(name).strip()
    if not name or len(name) > MAX_NAME or not all(c.isalnum() or c in "._-@" for c in name):
        raise ConfigError(f"operator name {name!r}: 1..{MAX_NAME} letters, digits and . _ - @")
    return name


class OperatorsFile:
    """The operators file: ``{"version": 1, "operators": [{"name", "role", "salt", "hash",
    "created"}]}``, written atomically with mode 0600."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.operators: dict[str, Operator] = {}
        if self.path.exists():
            self._load()

    def _load(self) -> None:
        try:
            doc = json.loads(self.path.read_text())
            if doc.get("version") != FILE_VERSION:
                raise ConfigError(f"{self.path}: operators file version {doc.get('version')!r}, "
                                  f"expected {FILE_VERSION}")
            for row in doc["operators"]:
                op = Operator(_check_name(row["name"]), str(row["role"]), str(row["salt"]),
                              str(row["hash"]), float(row.get("created", 0.0)))
                if op.role not in ROLES:
                    raise ConfigError(f"{self.path}: operator {op.name!r} has role {op.role!r} "
                                      f"(one of {', '.join(ROLES)})")
                self.operators[op.name] = op
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"cannot read operators file {self.path}: {exc}") from exc

    def save(self) -> None:
        doc = {"version": FILE_VERSION,
               "operators": [vars(op) for op in sorted(self.operators.values(), key=lambda o: o.name)]}
        tmp = self.path.with_name(self.path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
        os.replace(tmp, self.path)

    def add(self, name: str, role: str, secret: str | None = None) -> str | None:
        """Add or replace ``name`` with ``role``; with no ``secret``, a random token is made and
        returned (shown once: only its hash is kept)."""
        name = _check_name(name)
        if role not in ROLES:
            raise ConfigError(f"role {role!r}: one of {', '.join(ROLES)}")
        made = None
        if secret is None:
            secret = made = secrets.token_urlsafe(24)
        if not 8 <= len(secret) <= MAX_SECRET:
            raise ConfigError(f"a password has 8..{MAX_SECRET} characters")
        salt = secrets.token_bytes(16)
        self.operators[name] = Operator(name, role, salt.hex(), _hash(secret, salt), time.time())
        return made

    def remove(self, name: str) -> None:
        if self.operators.pop(_check_name(name), None) is None:
            raise ConfigError(f"no operator {name!r} in {self.path}")

    def verify(self, name: str, secret: str) -> Operator | None:
        """The operator, if ``secret`` is theirs (a constant-time comparison; an unknown name
        costs the same as a known one)."""
        op = self.operators.get(str(name))
        if len(secret) > MAX_SECRET:
            return None
        salt = bytes.fromhex(op.salt) if op is not None else b"\0" * 16
        digest = _hash(secret, salt)
        if op is None:
            return None
        return op if hmac.compare_digest(digest, op.hash) else None


@dataclass
class Session:
    sid: str
    name: str
    role: str
    csrf: str
    expires: float
    commands: deque[float] = field(default_factory=deque)

    @property
    def may_command(self) -> bool:
        return self.role == "operator"


class Access:
    """Logins, sessions and limits for one console server (thread-safe)."""

    def __init__(self, operators: OperatorsFile, *, session_hours: float = 12.0,
                 max_failures: int = 5, lockout: float = 300.0, commands_per_minute: int = 30,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not operators.operators:
            raise ConfigError(f"the operators file {operators.path} names nobody "
                              "(add one: coex operators add NAME --role operator)")
        self.operators = operators
        self.session_seconds = float(session_hours) * 3600.0
        self.max_failures = int(max_failures)
        self.lockout = float(lockout)
        self.commands_per_minute = int(commands_per_minute)
        self.clock = clock
        self._sessions: dict[str, Session] = {}
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ logins
    def locked_out(self, who: str) -> float:
        """Seconds before ``who`` (a name, or a client address) may try again (0: now)."""
        now = self.clock()
        with self._lock:
            fails = self._failures.get(who)
            while fails and now - fails[0] > self.lockout:
                fails.popleft()
            if fails is not None and len(fails) >= self.max_failures:
                return max(0.0, self.lockout - (now - fails[0]))
        return 0.0

    def login(self, name: str, secret: str, client: str) -> Session | None:
        """A new session, or None (the failure is counted against the name and the client)."""
        if self.locked_out(name) or self.locked_out(client):
            return None
        op = self.operators.verify(name, secret)
        now = self.clock()
        if op is None:
            with self._lock:
                for who in (name, client):
                    self._failures.setdefault(who, deque()).append(now)
            log.warning("console login failed for %r from %s", name[:MAX_NAME], client)
            return None
        s = Session(secrets.token_urlsafe(32), op.name, op.role, secrets.token_urlsafe(24),
                    now + self.session_seconds)
        with self._lock:
            self._sessions[s.sid] = s
            self._failures.pop(name, None)
        log.info("console login: %s (%s) from %s", op.name, op.role, client)
        return s

    def session(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        now = self.clock()
        with self._lock:
            s = self._sessions.get(sid)
            if s is None:
                return None
            if now >= s.expires or s.name not in self.operators.operators:
                del self._sessions[sid]
                return None
            return s

    def logout(self, sid: str | None) -> None:
        with self._lock:
            self._sessions.pop(sid or "", None)

    # ------------------------------------------------------------------ commands
    def command_allowed(self, s: Session) -> float:
        """0 when the session's operator may send one more command now, else seconds to wait
        (at most ``commands_per_minute`` in any minute)."""
        now = self.clock()
        with self._lock:
            while s.commands and now - s.commands[0] >= 60.0:
                s.commands.popleft()
            if len(s.commands) >= self.commands_per_minute:
                return 60.0 - (now - s.commands[0])
            s.commands.append(now)
            return 0.0


def parse_cookies(header: str | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for part in (header or "").split(";"):
        k, sep, v = part.strip().partition("=")
        if sep:
            out[k.strip()] = v.strip()
    return out


def describe(s: Any) -> dict[str, Any]:
    return {"name": s.name, "role": s.role, "csrf": s.csrf, "may_command": s.may_command}
