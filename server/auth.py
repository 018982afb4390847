"""Accounts: argon2id password hashes, expiring session tokens, roles and the audit log.

A log-in creates a random token (``secrets.token_urlsafe``); the client holds it as the
``slinger_session`` cookie (the console) or sends ``Authorization: Bearer <token>`` (scripts).
The database stores only the token's SHA-256 and its expiry, so a leaked database does not leak
sessions. Roles are ordered (server.db.models.ROLES): viewer < operator < admin; a route that
needs a role accepts any higher one.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
from datetime import timedelta

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError
from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import ROLES, AuditEntry, AuthSession, User
from server.db.types import utcnow
from server.db.upsert import insert_if_absent
from server.errors import Conflict, Refused, Unauthenticated

log = logging.getLogger(__name__)

COOKIE_NAME = "slinger_session"
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
    """A new session token for ``user`` valid ``ttl_s`` seconds; expired sessions are purged."""
    now = utcnow()
    db.execute(delete(AuthSession).where(AuthSession.expires_at < now))
    token = secrets.token_urlsafe(32)
    row = AuthSession(token_sha256=_digest(token), user_id=user.id, user_key=user.session_key, created_at=now,
                      expires_at=now + timedelta(seconds=ttl_s))
    db.add(row)
    return token, row


def user_for_token(db: Session, token: str | None) -> User | None:
    """The active user of an unexpired session token, else None.

    The session must carry the account's current ``session_key`` (server.db.models.User): a
    session whose account was deleted, even by a tool that bypasses foreign keys, never
    authenticates a later account that got the same ``id``.
    """
    if not token:
        return None
    row = db.get(AuthSession, _digest(token))
    if row is None or row.expires_at <= utcnow():
        return None
    user = db.get(User, row.user_id)
    if user is None or not secrets.compare_digest(user.session_key, row.user_key):
        log.warning("session of user id %s refused: its account was deleted or replaced", row.user_id)
        return None
    return user if user.active else None


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
