"""Accounts: argon2id password hashes, expiring session tokens, roles and the audit log.

A log-in creates a random token (``secrets.token_urlsafe``); the client holds it as the
``slinger_session`` cookie (the console) or sends ``Authorization: Bearer <token>`` (scripts).
The database stores only the token's SHA-256 and its expiry, so a leaked database does not leak
sessions. Roles are ordered (server.db.models.ROLES): viewer < operator < admin; a route that
needs a role accepts any higher one.

Two parts keep the E-STOP and the machine list independent of storage (docs/safety.md):
:class:`SessionMirror` is an in-memory copy of the valid sessions, loaded at start, refreshed
after every commit that changes users or sessions and every ``refresh_s`` (changes made by other
processes, e.g. ``slinger user``), and kept as it was while storage fails (and on disk:
server.accounts.session_file, read at start when storage fails then); :class:`AuditBacklog`
queues audit entries that cannot be written and writes them, with their original time, once
storage is back.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import threading
from collections import deque
from dataclasses import dataclass
from datetime import datetime, timedelta

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError
from sqlalchemy import Delete, Update, delete, event, func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from server.accounts.session_file import SessionFile
from server.db.models import ROLES, AuditEntry, AuthSession, User
from server.db.types import utcnow
from server.db.upsert import insert_if_absent
from server.errors import Conflict, Refused, Unauthenticated
from server.site.storage import StorageFault

log = logging.getLogger(__name__)

COOKIE_NAME = "slinger_session"
STOP_GRACE_S = 24 * 3600.0
"""How long after its log-in expired a session still authorises the E-STOP, and nothing else
(CHOSEN: a console left open past the end of its log-in must not lose its stop; docs/safety.md,
row S13). A log-out, a disabled or a deleted account end it at once. The session cookie lives this
much longer than the session, and expired sessions are purged only after it."""
MIN_PASSWORD_LENGTH = 12  # NIST SP 800-63B asks for >= 8, >= 15 when it is the only factor
MAX_PASSWORD_LENGTH = 256
_hasher = PasswordHasher()  # argon2id with the library's recommended parameters


class AuthError(Refused, ValueError):
    """An invalid account change (a weak password, an unknown role, a malformed user name); the
    message is safe to show. Subclasses: :class:`UserExists`, :class:`BadCredentials`."""


class UserExists(Conflict, AuthError):
    """A user of that name exists already."""


class BadCredentials(Unauthenticated, AuthError):
    """Unknown user, wrong password or inactive account. The message is the same for every cause
    (safe to show, on purpose); ``reason`` names the cause for the audit log only:
    ``"unknown user"``, ``"wrong password"`` or ``"account disabled"``."""

    def __init__(self, reason: str):
        super().__init__("invalid user name or password")
        self.reason = reason


def hash_password(password: str) -> str:
    """argon2id hash of ``password``."""
    return _hasher.hash(password)


def verify_password(password_hash: str, password: str) -> bool:
    """True if ``password`` matches ``password_hash`` (False for a malformed hash)."""
    try:
        return _hasher.verify(password_hash, password)
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def check_password(password: str) -> str:
    """``password`` if it is acceptable for an account.

    Raises:
        AuthError: shorter than MIN_PASSWORD_LENGTH or longer than MAX_PASSWORD_LENGTH characters.
    """
    if len(password) < MIN_PASSWORD_LENGTH:
        raise AuthError(f"password must have at least {MIN_PASSWORD_LENGTH} characters")
    if len(password) > MAX_PASSWORD_LENGTH:
        raise AuthError(f"password must have at most {MAX_PASSWORD_LENGTH} characters")
    return password


def role_at_least(role: str, needed: str) -> bool:
    """True if ``role`` has the rights of ``needed`` (viewer < operator < admin)."""
    return role in ROLES and ROLES.index(role) >= ROLES.index(needed)


def generate_password() -> str:
    """A random password for a generated account (16 URL-safe characters)."""
    return secrets.token_urlsafe(12)


def create_user(db: Session, username: str, password: str, role: str) -> User:
    """Add a user inside ``db``'s transaction.

    Raises:
        AuthError: unknown role, password too short or long (:func:`check_password`), malformed
            user name; :class:`UserExists` (an AuthError): the name is taken.
    """
    if role not in ROLES:
        raise AuthError(f"unknown role {role!r}; use one of {', '.join(ROLES)}")
    if not username or len(username) > 64 or not all(c.isalnum() or c in "._-@" for c in username):
        raise AuthError("user name must be 1-64 letters, digits or . _ - @")
    check_password(password)
    taken = UserExists(f"user {username!r} exists")
    if db.scalar(select(User).where(User.username == username)) is not None:
        raise taken  # before the (deliberately slow) password hash
    # a concurrent add of the same name: this insert waits for it and adds nothing
    if not insert_if_absent(db, User, ["username"], username=username, password_hash=hash_password(password),
                            role=role, active=True):
        raise taken
    return db.scalars(select(User).where(User.username == username)).one()


def user_count(db: Session) -> int:
    return int(db.scalar(select(func.count()).select_from(User)) or 0)


def authenticate(db: Session, username: str, password: str) -> User:
    """The active user with these credentials.

    Raises:
        BadCredentials: "invalid user name or password" (the same text for every cause, on
            purpose; its ``reason`` names the cause for the audit log).
    """
    user = db.scalar(select(User).where(User.username == username))
    if user is None:
        hash_password(password)  # spend the same time as a real check
        raise BadCredentials("unknown user")
    if not verify_password(user.password_hash, password):
        raise BadCredentials("wrong password")
    if not user.active:
        raise BadCredentials("account disabled")
    if _hasher.check_needs_rehash(user.password_hash):
        user.password_hash = hash_password(password)
    return user


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def create_session(db: Session, user: User, ttl_s: float) -> tuple[str, AuthSession]:
    """A new session token for ``user`` valid ``ttl_s`` seconds; sessions expired more than
    :data:`STOP_GRACE_S` ago are purged."""
    now = utcnow()
    db.execute(delete(AuthSession).where(AuthSession.expires_at < now - timedelta(seconds=STOP_GRACE_S)))
    token = secrets.token_urlsafe(32)
    row = AuthSession(token_sha256=_digest(token), user_id=user.id, user_key=user.session_key, created_at=now,
                      expires_at=now + timedelta(seconds=ttl_s))
    db.add(row)
    return token, row


def session_for_token(db: Session, token: str | None, grace_s: float = 0.0) -> tuple[User, datetime] | None:
    """(the active user, the session's expiry, UTC) of a session token that has not expired, or
    expired less than ``grace_s`` seconds ago (:data:`STOP_GRACE_S` for the E-STOP), else None.

    The session must carry the account's current ``session_key`` (server.db.models.User): a
    session whose account was deleted, even by a tool that bypasses foreign keys, never
    authenticates a later account that got the same ``id``.
    """
    if not token:
        return None
    row = db.get(AuthSession, _digest(token))
    if row is None or row.expires_at <= utcnow() - timedelta(seconds=grace_s):
        return None
    user = db.get(User, row.user_id)
    if user is None or not secrets.compare_digest(user.session_key, row.user_key):
        log.warning("session of user id %s refused: its account was deleted or replaced", row.user_id)
        return None
    return (user, row.expires_at) if user.active else None


def user_for_token(db: Session, token: str | None) -> User | None:
    """The active user of an unexpired session token, else None (:func:`session_for_token`)."""
    found = session_for_token(db, token)
    return found[0] if found is not None else None


def end_session(db: Session, token: str | None) -> None:
    """Log out: delete the session of ``token`` (no error if there is none)."""
    if token:
        db.execute(delete(AuthSession).where(AuthSession.token_sha256 == _digest(token)))


def clean_text(value: str, limit: int | None = None) -> str:
    """``value`` with control and other non-printable characters escaped (``\\x1b``,
    ``\\u2028``), cut to ``limit`` characters: safe for a log line, a terminal and a table cell."""
    out = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in str(value))
    return out if limit is None or len(out) <= limit else out[: limit - 1] + "…"


def _clean_detail(value, depth: int = 0):
    if isinstance(value, str):
        return clean_text(value, 1000)
    if isinstance(value, dict) and depth < 4:
        return {clean_text(str(k), 64): _clean_detail(v, depth + 1) for k, v in list(value.items())[:50]}
    if isinstance(value, (list, tuple)) and depth < 4:
        return [_clean_detail(v, depth + 1) for v in list(value)[:50]]
    if value is None or isinstance(value, (bool, int, float)):
        return value
    return clean_text(repr(value), 1000)


def audit(db: Session, username: str, action: str, subject: str | None = None, **detail) -> None:
    """Write one audit-log entry inside ``db``'s transaction (and log it). Every text is
    cleaned (:func:`clean_text`: control characters escaped, cut to the column's length), so
    that a hostile machine id or reason cannot forge log lines or break the audit table."""
    username, action = clean_text(username, 64), clean_text(action, 32)
    subject = clean_text(subject, 128) if subject is not None else None
    detail = _clean_detail(detail)
    db.add(AuditEntry(username=username, action=action, subject=subject, detail=detail))
    log.info("audit: %s %s %s %s", username, action, subject or "", detail or "")


def record_audit(sessions: sessionmaker[Session], username: str, action: str, subject: str | None = None,
                 **detail) -> None:
    """:func:`audit` in its own transaction."""
    with sessions.begin() as db:
        audit(db, username, action, subject, **detail)


def ensure_admin(sessions: sessionmaker[Session], username: str = "admin") -> str | None:
    """Create an admin with a random password if there is no user at all.

    Returns:
        The generated password (to show ONCE), or None when users already exist.
    """
    with sessions.begin() as db:
        if user_count(db) > 0:
            return None
        password = generate_password()
        create_user(db, username, password, "admin")
        audit(db, "system", "user_add", username, role="admin", reason="first local admin")
    return password


AUDIT_BACKLOG_MAX = 10_000
"""At most this many unwritten audit entries are kept in memory (the oldest are dropped, counted)."""
MIRROR_REFRESH_S = 2.0
"""The session mirror re-reads the sessions this often (changes made by other processes), s."""


@dataclass(frozen=True)
class SessionUser:
    """The account behind a session as the :class:`SessionMirror` holds it (the attributes of
    :class:`server.db.models.User` that authorisation and the routes read)."""

    id: int
    username: str
    role: str
    active: bool
    created_at: datetime


class AuditBacklog:
    """Audit entries that could not be written (storage fault), kept in memory in order and
    written with their original time by :meth:`flush` once storage is back.

    Args:
        sessions: the session factory.
        max_entries: at most this many are kept; older ones are dropped and counted in ``dropped``.
    """

    def __init__(self, sessions: sessionmaker[Session], max_entries: int = AUDIT_BACKLOG_MAX):
        self.sessions = sessions
        self._queue: deque[tuple[datetime, str, str, str | None, dict]] = deque(maxlen=max_entries)
        self._lock = threading.Lock()
        self.dropped = 0
        """Entries dropped because the backlog was full."""

    def record(self, username: str, action: str, subject: str | None = None, **detail) -> bool:
        """Write one audit entry now (after any queued ones); queue it if storage fails.

        Returns:
            True if it is written, False if it waits in the backlog.
        """
        at = utcnow()
        if self.flush():
            try:
                with self.sessions.begin() as db:
                    _add_audit(db, at, username, action, subject, detail)
                return True
            except (SQLAlchemyError, OSError, StorageFault) as e:
                log.error("audit entry %s %s queued in memory: %s", action, subject or "", _first_line(e))
        self._push(at, username, action, subject, detail)
        return False

    def _push(self, at, username, action, subject, detail) -> None:
        with self._lock:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append((at, username, action, subject, detail))

    def pending(self) -> int:
        """Entries waiting to be written."""
        with self._lock:
            return len(self._queue)

    def flush(self) -> bool:
        """Write every queued entry (one transaction). Returns True if none is left; on a storage
        error they stay queued (False)."""
        with self._lock:
            if not self._queue:
                return True
            batch = list(self._queue)
        try:
            with self.sessions.begin() as db:
                for at, username, action, subject, detail in batch:
                    _add_audit(db, at, username, action, subject, detail)
        except (SQLAlchemyError, OSError, StorageFault) as e:
            log.debug("audit backlog of %d not written yet: %s", len(batch), _first_line(e))
            return False
        with self._lock:
            for _ in batch:
                self._queue.popleft()
        log.warning("wrote %d audit entries queued while storage was failing", len(batch))
        return True


def _add_audit(db: Session, at: datetime, username: str, action: str, subject: str | None, detail: dict) -> None:
    audit(db, username, action, subject, **detail)
    for obj in db.new:
        if isinstance(obj, AuditEntry) and obj.at is None:
            obj.at = at


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


class SessionMirror:
    """The valid sessions in memory: token SHA-256 -> (:class:`SessionUser`, expiry), so that a
    stop can be authorised without storage.

    It holds exactly what :func:`session_for_token` accepts with the E-STOP's grace (a session not
    expired more than :data:`STOP_GRACE_S` ago, an existing active account with the session's
    ``session_key``), read in one query; :meth:`user` takes only the unexpired ones. :meth:`watch` makes every
    commit of the server's sessions that adds, changes or deletes users or sessions re-read it
    before the commit's caller goes on (a log-out, a deleted or disabled account, a new role take
    effect at once); a thread re-reads it every ``refresh_s`` for changes made by other processes.
    A failed read (storage fault) keeps what it held; expiry is judged in memory.

    With ``file`` (server.accounts.session_file) every read that changed what the mirror holds is
    written there, and :meth:`start` reads the file when the database cannot be read: sessions
    issued before a restart then still authorise an E-STOP (or a reset) while storage fails, as
    they would have without the restart. The file holds what the last successful read held: an
    account disabled while this server was down stays valid from the file until the database
    answers (as a change made during a storage fault waits for the next successful read).

    Args:
        sessions: the session factory.
        refresh_s: see MIRROR_REFRESH_S.
        on_tick: called after each periodic refresh (e.g. :meth:`AuditBacklog.flush`).
        file: where the sessions are kept across restarts (None: memory only).
    """

    def __init__(self, sessions: sessionmaker[Session], refresh_s: float = MIRROR_REFRESH_S, on_tick=None,
                 file: SessionFile | None = None):
        self.sessions = sessions
        self.refresh_s = refresh_s
        self.on_tick = on_tick
        self.file = file
        self._map: dict[str, tuple[SessionUser, datetime]] = {}
        self._lock = threading.Lock()
        self._file_lock = threading.Lock()
        self._saved: dict[str, tuple[SessionUser, datetime]] | None = None
        self._generation = 0
        self.loaded = False
        """True once a read succeeded (before that, a miss means "unknown", not "invalid")."""
        self.from_file = False
        """True while the mirror holds the file's sessions (storage failed at start; no read yet)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def user(self, token: str | None) -> SessionUser | None:
        """The active user of an unexpired session ``token`` as last read, else None. No I/O."""
        found = self.session(token)
        return found[0] if found is not None else None

    def session(self, token: str | None, grace_s: float = 0.0) -> tuple[SessionUser, datetime] | None:
        """(the active user, the session's expiry) of ``token`` as last read if the session has not
        expired, or expired less than ``grace_s`` seconds ago (at most :data:`STOP_GRACE_S`: the
        mirror holds no older one), else None. No I/O."""
        if not token:
            return None
        with self._lock:
            entry = self._map.get(_digest(token))
        if entry is None or entry[1] <= utcnow() - timedelta(seconds=grace_s) or not entry[0].active:
            return None
        return entry

    def refresh(self) -> bool:
        """Read the valid sessions now. Returns False (the mirror unchanged) on a storage error."""
        with self._lock:
            self._generation += 1
            generation = self._generation
        try:
            with self.sessions() as db:
                rows = db.execute(select(AuthSession.token_sha256, AuthSession.expires_at, User).join(
                    User, User.id == AuthSession.user_id).where(
                    AuthSession.expires_at > utcnow() - timedelta(seconds=STOP_GRACE_S), AuthSession.user_key == User.session_key, User.active.is_(True)
                )).all()
        except (SQLAlchemyError, OSError, StorageFault) as e:
            log.debug("session mirror not refreshed: %s", _first_line(e))
            return False
        fresh = {digest: (SessionUser(u.id, u.username, u.role, u.active, u.created_at), expires)
                 for digest, expires, u in rows}
        with self._lock:
            if generation == self._generation:  # a later refresh (after a newer commit) wins
                self._map = fresh
                self.loaded = True
                self.from_file = False
        self._save()
        return True

    def _save(self) -> None:
        """Write the mirror to its file if what it holds changed since the last write (logged on
        failure; the next change or :meth:`stop` tries again)."""
        if self.file is None:
            return
        with self._file_lock:
            with self._lock:
                current = dict(self._map)  # a copy: drop() changes the map in place
            if current == self._saved:
                return
            try:
                self.file.save({digest: (u.id, u.username, u.role, u.active, u.created_at, expires)
                                for digest, (u, expires) in current.items()})
                self._saved = current
            except OSError as e:
                log.error("session mirror file %s not written (%s): sessions from now on need storage after a "
                          "restart", self.file.path, e.strerror or e)

    def _load_file(self) -> None:
        """Hold the file's sessions not expired more than :data:`STOP_GRACE_S` ago (start, when the
        database cannot be read)."""
        if self.file is None:
            return
        oldest = utcnow() - timedelta(seconds=STOP_GRACE_S)
        kept = {digest: (SessionUser(uid, name, role, active, created), expires)
                for digest, (uid, name, role, active, created, expires) in self.file.load().items() if expires > oldest}
        with self._lock:
            if self.loaded:  # a read succeeded meanwhile
                return
            self._map, self.from_file = kept, True
            self._saved = dict(kept)
        log.warning("storage not readable at start: %d session(s) authorised from %s until it answers", len(kept),
                    self.file.path)

    def drop(self, token: str | None) -> None:
        """Forget ``token`` at once (the database said it is not valid)."""
        if token:
            with self._lock:
                self._map.pop(_digest(token), None)

    def watch(self, sessions: sessionmaker[Session]) -> None:
        """Refresh after every commit of ``sessions`` that touched users or sessions (ORM
        objects flushed, or bulk UPDATE/DELETE statements on their tables)."""

        @event.listens_for(sessions, "after_flush")
        def _flushed(db, _ctx) -> None:
            if any(isinstance(o, (User, AuthSession)) for o in (*db.new, *db.dirty, *db.deleted)):
                db.info["auth_changed"] = True

        @event.listens_for(sessions, "do_orm_execute")
        def _executed(state) -> None:
            stmt = state.statement
            if isinstance(stmt, (Update, Delete)) and \
                    getattr(stmt.table, "name", None) in (User.__tablename__, AuthSession.__tablename__):
                state.session.info["auth_changed"] = True

        @event.listens_for(sessions, "after_commit")
        def _committed(db) -> None:
            if db.info.pop("auth_changed", False):
                self.refresh()

        @event.listens_for(sessions, "after_rollback")
        def _rolled_back(db) -> None:
            db.info.pop("auth_changed", None)

    def start(self) -> None:
        """Read once (the file's sessions if that fails), then start the refresh thread."""
        if not self.refresh():
            self._load_file()
        self._thread = threading.Thread(target=self._loop, name="session-mirror", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the refresh thread; the file is written if a change is not on it yet."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._save()

    def _loop(self) -> None:
        while not self._stop.wait(self.refresh_s):
            self.refresh()
            if self.on_tick is not None:
                try:
                    self.on_tick()
                except Exception:
                    log.exception("session mirror tick failed")
