"""Who may use the console: operators (they command the vehicle) and viewers (they watch).

* :class:`OperatorsFile`: names, roles and salted scrypt hashes of passwords (or of long random
  tokens made for the operator), in a JSON file (``coex operators add|remove|list``). Secrets
  are never stored, only their hashes. A new password must pass :func:`password_problem`.
* :class:`Access`: sign-ins, sessions and limits for one console server. It follows the
  operators file while it runs: the file is looked at (``stat``) at most every
  ``check_seconds`` and re-read when it changed, and every session is checked against it on
  every request and by every open event stream. Removing a person ends their sessions, a new
  password ends the sessions made with the old one, an operator made a viewer is a viewer at
  once (a viewer made an operator signs in again). Failed sign-ins are counted *before* the
  password is checked (parallel guesses see each other) and slow down the next try of that
  name from that address, of that address for any name, and of that name from anywhere
  (backoff, never a hard lock): a browser that signed in as the name before (its signed device
  cookie) or holds a live session of it is never made to wait by anyone else's failures, only by
  its own. Commands are limited per operator, whatever the number of their sessions (a refused
  command does not count). The web server (:mod:`.server`) asks it
  about every request; every refusal is logged with who and why.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coex import ConfigError

from .admission import Said

__all__ = ["Access", "Operator", "OperatorsFile", "Session", "SignInRefused", "SignInTry", "ROLES",
           "password_problem", "secret_file_problem"]

log = logging.getLogger("coex.console.access")

ROLES = ("operator", "viewer")
FILE_VERSION = 1
#: scrypt parameters (RFC 7914): about 16 MB and tens of milliseconds per check
SCRYPT = {"n": 2**14, "r": 8, "p": 1}
MAX_NAME = 64
MAX_SECRET = 1024
#: the shortest password accepted (OWASP ASVS 2.1.1)
MIN_SECRET = 12
#: passwords refused whatever their length (lower case, compared ignoring case and spaces)
COMMON = frozenset({
    "password", "passwordpassword", "password1234", "password12345", "password123456",
    "123456789012", "1234567890123", "12345678901234", "qwertyuiopas", "qwertyuiop123",
    "iloveyou1234", "letmeinletmein", "administrator", "adminadminadmin", "welcome12345",
    "changemechangeme", "changeme1234", "operator1234", "coexcoexcoex", "coexoperator",
})


#: a browser that signed in as a name is known for this many days (its device cookie)
DEVICE_DAYS = 90.0


def secret_file_problem(path: str | Path, what: str = "file") -> str | None:
    """Why ``path`` may not hold a secret (None: it may): other users (its group, everyone) can
    read or write it. The operators file, the TLS key: ``chmod 600`` them."""
    if os.name != "posix":
        return None
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None  # a missing file is said elsewhere
    if mode & 0o077:
        who = "everyone" if mode & 0o007 else "its group"
        return (f"the {what} {path} can be read or changed by {who} (mode {mode & 0o777:04o}): "
                f"make it private with chmod 600 {path}")
    return None


def password_problem(name: str, secret: str) -> str | None:
    """Why ``secret`` is not a good enough password for ``name`` (None: it is). At least
    :data:`MIN_SECRET` characters that are not only spaces, five different characters, not a
    common password and not the name itself; no rules about kinds of characters (ASVS 2.1)."""
    if len(secret) > MAX_SECRET:
        return f"a password has at most {MAX_SECRET} characters"
    if len(secret.strip()) < MIN_SECRET:
        return f"a password has at least {MIN_SECRET} characters besides leading and trailing spaces"
    if len(set(secret)) < 5:
        return "a password needs at least five different characters"
    plain = "".join(secret.lower().split())
    if plain in COMMON or plain == "".join(str(name).lower().split()):
        return "this password is too common (or is the name): choose another"
    return None


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
    "created"}]}``, written atomically with mode 0600. :meth:`reload` reads it again when it
    changed on disk."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.operators: dict[str, Operator] = {}
        self._seen: tuple[int, int, int] | None = None
        if self.path.exists():
            self._seen = self._signature()
            self.operators = self._read()

    def _signature(self) -> tuple[int, int, int] | None:
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def _read(self) -> dict[str, Operator]:
        out: dict[str, Operator] = {}
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
                out[op.name] = op
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ConfigError(f"cannot read operators file {self.path}: {exc}") from exc
        return out

    def reload(self) -> bool:
        """Read the file again if it changed (another inode, time or size); True if it did. A
        file that cannot be read (or is gone) lets nobody in until it is fixed (logged). A file
        other users may read is still followed (the operator keeps her console) and logged as an
        error until it is made private again."""
        sig = self._signature()
        if sig == self._seen:
            return False
        self._seen = sig
        try:
            if sig is None:
                raise ConfigError(f"the operators file {self.path} is gone")
            self.operators = self._read()
            log.info("operators file %s re-read: %d people", self.path, len(self.operators))
            problem = secret_file_problem(self.path, "operators file")
            if problem:
                log.error("%s (still used meanwhile)", problem)
        except ConfigError as exc:
            log.error("%s: nobody can use the console until it is fixed", exc)
            self.operators = {}
        return True

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
        returned (shown once: only its hash is kept). A password must pass
        :func:`password_problem` (:class:`ConfigError` with the reason)."""
        name = _check_name(name)
        if role not in ROLES:
            raise ConfigError(f"role {role!r}: one of {', '.join(ROLES)}")
        made = None
        if secret is None:
            secret = made = secrets.token_urlsafe(24)
        problem = password_problem(name, secret)
        if problem is not None:
            raise ConfigError(problem)
        salt = secrets.token_bytes(16)
        self.operators[name] = Operator(name, role, salt.hex(), _hash(secret, salt), time.time())
        return made

    def set_role(self, name: str, role: str) -> None:
        """Give ``name`` another role, keeping their password (a running console downgrades an
        operator made a viewer at once; a viewer made an operator signs in again)."""
        name = _check_name(name)
        if role not in ROLES:
            raise ConfigError(f"role {role!r}: one of {', '.join(ROLES)}")
        op = self.operators.get(name)
        if op is None:
            raise ConfigError(f"no operator {name!r} in {self.path}")
        self.operators[name] = Operator(op.name, role, op.salt, op.hash, op.created)

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
    #: the operator's password hash when they signed in: a new password ends the session
    fingerprint: str = ""
    #: when the session was last used (a request, or its page's open event stream)
    seen: float = 0.0

    @property
    def may_command(self) -> bool:
        return self.role == "operator"


class SignInRefused(Exception):
    """A sign-in that did not make a session: ``status`` 401 (wrong name or password) or 429
    (too many failures: ``wait`` seconds)."""

    def __init__(self, status: int, reason: str, wait: float = 0.0) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason
        self.wait = wait


@dataclass
class SignInTry:
    """One sign-in between :meth:`Access.begin` and :meth:`Access.finish`: the failure counters
    it already counts in, and its class in the queue of password checks (0: from a browser
    known for the name, 1: from an address without failures, 2: the rest)."""

    name: str
    client: str
    keys: list[str]
    known: bool
    klass: int
    at: float


class Access:
    """Sign-ins, sessions and limits for one console server (thread-safe).

    ``session_hours`` the longest a session lasts; ``idle_minutes`` a session not used for that
    long ends (an open page's event stream is use); ``max_failures`` failed sign-ins of one name
    from one address (or from one known browser) before each next try waits ``backoff``
    seconds, doubling up to ``max_backoff``; ``address_failures`` the same for one address
    whatever the names; ``account_failures`` for one name from anywhere (browsers that signed
    in as the name before are not held by it); failures older than ``window`` seconds are
    forgotten; ``commands_per_minute`` per operator; ``check_seconds`` how often the operators
    file is looked at; ``sign_ins`` password checks at once (scrypt takes 16 MB each)."""

    def __init__(self, operators: OperatorsFile, *, session_hours: float = 12.0,
                 idle_minutes: float = 30.0, max_failures: int = 5, address_failures: int = 20,
                 account_failures: int = 20, backoff: float = 2.0, max_backoff: float = 300.0,
                 window: float = 900.0, commands_per_minute: int = 30, check_seconds: float = 0.2,
                 sign_ins: int = 2, clock: Callable[[], float] = time.monotonic) -> None:
        if not operators.operators:
            raise ConfigError(f"the operators file {operators.path} names nobody "
                              "(add one: coex operators add NAME --role operator)")
        self.operators = operators
        self.session_seconds = float(session_hours) * 3600.0
        self.idle_seconds = float(idle_minutes) * 60.0
        self.max_failures = int(max_failures)
        self.address_failures = int(address_failures)
        self.account_failures = int(account_failures)
        self.backoff = float(backoff)
        self.max_backoff = float(max_backoff)
        self.window = float(window)
        self.commands_per_minute = int(commands_per_minute)
        self.check_seconds = float(check_seconds)
        self.sign_ins = max(1, int(sign_ins))
        self.clock = clock
        self._sessions: dict[str, Session] = {}
        self._failures: dict[str, deque[float]] = {}
        self._commands: dict[str, deque[float]] = {}
        self._lock = threading.Lock()
        self._checked = -float("inf")
        #: password checks at once (scrypt takes 16 MB each)
        self._checking = threading.BoundedSemaphore(self.sign_ins)
        #: failed and refused sign-ins are logged with the name and the address, a flood of
        #: them from one address in one line every ten seconds
        self.say = Said(logger=log)

    # ------------------------------------------------------------------ the operators file
    def refresh(self, force: bool = False) -> None:
        """Look at the operators file (at most every ``check_seconds``) and re-read it if it
        changed; sessions are checked against it as they are used."""
        now = time.monotonic()
        with self._lock:
            if not force and now - self._checked < self.check_seconds:
                return
            self._checked = now
            self.operators.reload()

    def shown(self, name: str) -> str:
        """``name`` as a log may show it: an operator's name, else not at all (a password typed
        into the name field must never reach a log)."""
        return repr(name) if name in self.operators.operators else "a name that is nobody's"

    # ------------------------------------------------------------------ known browsers
    def _device_mac(self, op: Operator, issued: int) -> str:
        # keyed by the operator's password hash (secret, in the 0600 file; a new password
        # forgets every browser), so the cookie survives a restart of the console
        key = hashlib.sha256(b"coex-device\0" + bytes.fromhex(op.hash)).digest()
        return hmac.new(key, f"{op.name}\0{issued}".encode(), hashlib.sha256).hexdigest()[:32]

    def device_cookie(self, s: Session) -> str | None:
        """The value of the cookie that makes this browser known for ``s``'s name (set at a
        successful sign-in; :data:`DEVICE_DAYS` days)."""
        op = self.operators.operators.get(s.name)
        if op is None:
            return None
        issued = int(time.time())
        return f"{issued}.{self._device_mac(op, issued)}.{op.name}"

    def device(self, cookie: str | None) -> Operator | None:
        """The operator whose browser ``cookie`` says this is (None: no valid device cookie)."""
        if not cookie:
            return None
        parts = str(cookie).split(".", 2)
        if len(parts) != 3 or not parts[0].isdigit() or len(parts[0]) > 12:
            return None
        issued, mac, name = int(parts[0]), parts[1], parts[2]
        op = self.operators.operators.get(name)
        if op is None or not 0 <= time.time() - issued <= DEVICE_DAYS * 86400.0:
            return None
        return op if hmac.compare_digest(mac, self._device_mac(op, issued)) else None

    # ------------------------------------------------------------------ sign-in
    def _wait(self, key: str, now: float, free: int) -> float:
        fails = self._failures.get(key)
        if not fails:
            return 0.0
        while fails and now - fails[0] > self.window:
            fails.popleft()
        if not fails:
            del self._failures[key]
            return 0.0
        if len(fails) < free:
            return 0.0
        delay = min(self.max_backoff, self.backoff * 2.0 ** (len(fails) - free))
        return max(0.0, fails[-1] + delay - now)

    def _keys(self, name: str, client: str, known: str | None) -> list[tuple[str, int]]:
        if known is not None:  # a known browser answers for its own failures only
            return [(f"{name}\0known\0{known}", self.max_failures)]
        return [(f"{name}\0{client}", self.max_failures), (f"\0{client}", self.address_failures),
                (f"{name}\0*", self.account_failures)]

    def _known(self, name: str, device: str | None, sid: str | None) -> str | None:
        op = self.device(device)
        if op is not None and op.name == name:
            return "device " + str(device).split(".", 2)[1][:12]
        s = self._sessions.get(sid or "")
        if s is not None and s.name == name:
            return "session " + s.sid[:12]
        return None

    def wait(self, name: str, client: str, device: str | None = None) -> float:
        """Seconds before ``name`` may try to sign in from ``client`` (0: now)."""
        now = self.clock()
        with self._lock:
            known = self._known(name[:MAX_NAME], device, None)
            return max(self._wait(k, now, free) for k, free in self._keys(name[:MAX_NAME], client, known))

    def begin(self, name: str, client: str, device: str | None = None, sid: str | None = None) -> SignInTry:
        """The first step of a sign-in (no password yet): :class:`SignInRefused` (429) while
        the try must wait, else a :class:`SignInTry` already counted as a failure of the name
        from ``client`` (of the known browser, with a valid ``device`` cookie or a live session
        ``sid`` of the name), so that parallel tries cannot pass the limit together;
        :meth:`finish` takes it back when the password was right."""
        self.refresh()
        name = str(name)[:MAX_NAME]
        now = self.clock()
        with self._lock:
            known = self._known(name, device, sid)
            keys = self._keys(name, client, known)
            wait = max(self._wait(k, now, free) for k, free in keys)
            if wait > 0:
                self.say(client, f"console sign-in refused for {self.shown(name)} from {client}"
                                 f"{f' ({known})' if known else ''}: too many failures, {wait:.0f} s to wait",
                         kind=f"refused {self.shown(name)} {known}")
                raise SignInRefused(429, f"too many failed sign-ins: try again in {wait:.0f} s", wait)
            # class 1: neither this address nor this name failed lately (a guesser's tries of a
            # name under attack, or from an address that failed, wait behind)
            clean = not self._failures.get(f"\0{client}") and not self._failures.get(f"{name}\0*")
            for k, _ in keys:
                self._failures.setdefault(k, deque()).append(now)
        return SignInTry(name, client, [k for k, _ in keys], known is not None,
                         0 if known is not None else 1 if clean else 2, now)

    def check(self, t: SignInTry, secret: str) -> Operator | None:
        """The password check of a try (scrypt: call it in a worker thread, a few at a time)."""
        return self.operators.verify(t.name, secret)

    def finish(self, t: SignInTry, op: Operator | None) -> Session:
        """The end of a sign-in: a new session, or :class:`SignInRefused` (401)."""
        if op is None:
            done = self.clock()
            with self._lock:  # the backoff runs from when the failure was known
                for key in t.keys:
                    fails = self._failures.get(key)
                    if fails is not None and t.at in fails:
                        fails.remove(t.at)
                        fails.append(done)
            self.say(t.client, f"console sign-in failed for {self.shown(t.name)} from {t.client}: wrong name or "
                               "password", kind=f"failed {self.shown(t.name)}")
            raise SignInRefused(401, "wrong name or password")
        now2 = self.clock()
        s = Session(secrets.token_urlsafe(32), op.name, op.role, secrets.token_urlsafe(24),
                    now2 + self.session_seconds, op.hash, now2)
        with self._lock:
            self._sessions[s.sid] = s
            for key in t.keys:
                fails = self._failures.get(key)
                if fails is None:
                    continue
                if key == t.keys[0]:
                    del self._failures[key]  # this name from here (this browser) starts afresh
                elif t.at in fails:
                    fails.remove(t.at)
        log.info("console sign-in: %s (%s) from %s", op.name, op.role, t.client)
        return s

    def cancel(self, t: SignInTry) -> None:
        """A try that was not checked after all (the console was too busy, the browser left):
        it counts as no failure."""
        with self._lock:
            for key in t.keys:
                fails = self._failures.get(key)
                if fails is not None and t.at in fails:
                    fails.remove(t.at)

    def login(self, name: str, secret: str, client: str, device: str | None = None,
              sid: str | None = None) -> Session:
        """A new session, or :class:`SignInRefused` (:meth:`begin`, the password check,
        :meth:`finish`). The try counts as a failure before the password is checked and is
        taken back when it was right."""
        t = self.begin(name, client, device, sid)
        with self._checking:
            op = self.check(t, secret)
        return self.finish(t, op)

    # ------------------------------------------------------------------ sessions
    def session(self, sid: str | None, touch: bool = True) -> Session | None:
        """The live session of ``sid`` (None: none, or it ended: expired, idle, its person
        removed from the operators file or given a new password or made an operator). A person
        made a viewer keeps the session as a viewer. ``touch``: this counts as use."""
        if not sid:
            return None
        self.refresh()
        now = self.clock()
        with self._lock:
            s = self._sessions.get(sid)
            if s is None:
                return None
            op = self.operators.operators.get(s.name)
            why = None
            if now >= s.expires:
                why = "expired"
            elif now - s.seen >= self.idle_seconds:
                why = f"idle for {self.idle_seconds / 60:.0f} min"
            elif op is None:
                why = "removed from the operators file"
            elif not hmac.compare_digest(op.hash, s.fingerprint):
                why = "their password changed"
            elif op.role != s.role:
                if op.role == "viewer":
                    log.warning("console: %s is a viewer now: their session is downgraded", s.name)
                    s.role = op.role
                else:
                    why = f"their role changed to {op.role} (sign in again)"
            if why is not None:
                del self._sessions[sid]
                log.warning("console session of %s ended: %s", s.name, why)
                return None
            if touch:
                s.seen = now
            return s

    def logout(self, sid: str | None) -> None:
        with self._lock:
            s = self._sessions.pop(sid or "", None)
        if s is not None:
            log.info("console sign-out: %s", s.name)

    # ------------------------------------------------------------------ commands
    def command_allowed(self, s: Session) -> float:
        """0 when the session's operator may send one more command now, else seconds to wait
        (at most ``commands_per_minute`` in any minute, counted per operator over all their
        sessions)."""
        now = self.clock()
        with self._lock:
            sent = self._commands.setdefault(s.name, deque())
            while sent and now - sent[0] >= 60.0:
                sent.popleft()
            if len(sent) >= self.commands_per_minute:
                return 60.0 - (now - sent[0])
            sent.append(now)
            return 0.0

    def command_refused(self, s: Session) -> None:
        """A command :meth:`command_allowed` counted was refused (a bad argument, nothing sent):
        it does not use up the operator's budget."""
        with self._lock:
            sent = self._commands.get(s.name)
            if sent:
                sent.pop()


def describe(s: Any) -> dict[str, Any]:
    return {"name": s.name, "role": s.role, "csrf": s.csrf, "may_command": s.may_command}
