"""Domain errors: what went wrong, in the domain's words, without HTTP status codes.

Services raise these; the API maps each kind to one status in one exception handler
(server.api.errors), with the ``X-Refused-Condition`` header when ``condition`` is set:

=================  ====  ==========================================================
error              HTTP  meaning
=================  ====  ==========================================================
:class:`NotFound`  404   no such machine, policy version, preview, diagnosis run
:class:`Refused`   422   the request cannot be served as asked (a target out of
                         range, a missing confirmation, a preview that does not
                         match, a file that is not a valid policy)
:class:`Conflict`  409   the request is valid but the current state forbids it
                         (E-STOP latched, a stale preview, a busy run, a duplicate)
:class:`Limited`   429   the caller is over a limit; try again later
:class:`Unavailable` 503 a runtime, a worker or storage does not answer now
:class:`Failed`    500   the work itself failed (a preview job raised)
=================  ====  ==========================================================
"""

from __future__ import annotations


class DomainError(Exception):
    """Base of the domain errors.

    Args:
        detail: a sentence for the operator (shown as is).
        condition: a short machine-readable name of the failed condition (e.g. ``preview_stale``),
            or None.
    """

    def __init__(self, detail: str, condition: str | None = None):
        super().__init__(detail)
        self.detail, self.condition = detail, condition


class NotFound(DomainError):
    """The thing asked for does not exist."""


class Refused(DomainError):
    """The request cannot be served as asked (its ``condition`` names why, when there is one)."""


class Conflict(DomainError):
    """The request is valid, but the current state does not allow it."""


class Limited(DomainError):
    """The caller is over a limit (rate, count); try again later."""


class Unavailable(DomainError):
    """Something the request needs does not answer now (runtime, worker, storage)."""


class Failed(DomainError):
    """The requested work itself failed."""


KINDS: dict[str, type[DomainError]] = {cls.__name__.lower(): cls for cls in
                                       (NotFound, Refused, Conflict, Limited, Unavailable, Failed)}
"""Error classes by lower-case name: how an error crosses a process boundary (a job's result)."""
