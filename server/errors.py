"""Domain errors: what went wrong, in the domain's words, without HTTP status codes.

Services raise these; the API maps each kind to one status in one exception handler
(server.api.errors), with the ``X-Refused-Condition`` header when ``condition`` is set:

=================  ====  ==========================================================
error              HTTP  meaning
=================  ====  ==========================================================
:class:`Unauthenticated` 401 no valid session (log in first), or bad credentials
:class:`Denied`    403   the user's role or ownership does not allow the request
:class:`NotFound`  404   no such machine, policy version, preview, diagnosis run
:class:`Refused`   422   the request cannot be served as asked (a target out of
                         range, a missing confirmation, a preview that does not
                         match, a file that is not a valid policy)
:class:`Conflict`  409   the request is valid but the current state forbids it
                         (E-STOP latched, a stale preview, a busy run, a duplicate)
:class:`TooLarge`  413   the request body is over its size limit
:class:`Limited`   429   the caller is over a limit; try again later
:class:`Unavailable` 503 a runtime, a worker or storage does not answer now
:class:`Failed`    500   the work itself failed (a preview job raised)
=================  ====  ==========================================================

The errors of a service subclass these (e.g. ``server.fleet.commands.RuntimeUnavailable`` is an
:class:`Unavailable`); where an error was a built-in exception before (``ValueError``,
``LookupError``, ``RuntimeError``), it keeps that base too, so existing ``except`` clauses hold.
"""

from __future__ import annotations

from typing import TypeVar

T = TypeVar("T")


class DomainError(Exception):
    """Base of the domain errors.

    Args:
        detail: a sentence for the operator (shown as is).
        condition: a short machine-readable name of the failed condition (e.g. ``preview_stale``),
            or None.
        retry_after_s: for :class:`Limited` and :class:`Unavailable`: in how many seconds to try
            again (s, whole; None: the API's default for the kind).
    """

    def __init__(self, detail: str, condition: str | None = None, retry_after_s: int | None = None):
        super().__init__(detail)
        self.detail, self.condition, self.retry_after_s = detail, condition, retry_after_s


class Unauthenticated(DomainError):
    """The caller is not logged in (no, expired or revoked session) or gave bad credentials."""


class Denied(DomainError):
    """The caller is known, but their role or ownership does not allow the request."""


class NotFound(DomainError):
    """The thing asked for does not exist."""


class Refused(DomainError):
    """The request cannot be served as asked (its ``condition`` names why, when there is one)."""


class Conflict(DomainError):
    """The request is valid, but the current state does not allow it."""


class TooLarge(DomainError):
    """The request (an upload) is larger than its limit; nothing of it is kept."""


class Limited(DomainError):
    """The caller is over a limit (rate, count); try again later."""


class Unavailable(DomainError):
    """Something the request needs does not answer now (runtime, worker, storage)."""


class Failed(DomainError):
    """The requested work itself failed."""


KINDS: dict[str, type[DomainError]] = {cls.__name__.lower(): cls for cls in
                                       (Unauthenticated, Denied, NotFound, Refused, Conflict, TooLarge, Limited,
                                        Unavailable, Failed)}
"""Error classes by lower-case name: how an error crosses a process boundary (a job's result)."""


def kind_of(error: DomainError) -> str:
    """The :data:`KINDS` name of ``error``'s nearest kind (``"failed"`` for a bare DomainError)."""
    for cls in type(error).__mro__:
        if cls in KINDS.values():
            return cls.__name__.lower()
    return "failed"


def found(value: T | None, detail: str) -> T:
    """``value`` if it is not None (a looked-up row, run or file).

    Raises:
        NotFound: ``value`` is None, with ``detail`` as its sentence.
    """
    if value is None:
        raise NotFound(detail)
    return value
