"""HTTP hygiene middlewares (pure ASGI): request body size limit and security headers.

- :class:`BodySizeLimit`: 413 for a request body larger than the limit of its route: at once
  from ``Content-Length``, or as soon as a streamed (chunked) body grows past it. The default
  limit is small (JSON bodies); routes that take files get their own explicit, larger limit.
- :class:`SecurityHeaders`: ``Content-Security-Policy`` (own scripts plus the console pages'
  inline scripts by hash, no ``unsafe-inline`` for scripts; the viser 3D view may be framed from
  the same host on any port, and from the site's view host name (Settings.viser_public_host) or, without
  one, on a loopback name from the other loopback name; this site may not be framed by anyone: ``frame-ancestors 'none'``),
  ``X-Frame-Options: DENY``, ``X-Content-Type-Options: nosniff``, ``Referrer-Policy:
  same-origin``. /docs and /redoc (server.app: Swagger UI and ReDoc from the server itself) run inline code: they get
  the other headers but no CSP.
- :func:`contained_file`: a served file, its links resolved, only if it stays inside its folder.
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
from pathlib import Path

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

_INLINE_SCRIPT = re.compile(r"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.DOTALL | re.IGNORECASE)
_HOSTNAME = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]{1,253})$")
NO_CSP_PATHS = ("/docs", "/redoc")
LOOPBACK_NAMES = {"localhost": "127.0.0.1", "127.0.0.1": "localhost"}
"""The two names of the loopback interface: a console page opened under one frames its 3D view
under the other (another site, so Chromium draws the view in its own renderer process)."""


def inline_script_hashes(web_dir: Path) -> list[str]:
    """CSP sources (``'sha256-...'``) of every inline ``<script>`` in ``web_dir``'s HTML files."""
    out = set()
    for page in sorted(web_dir.glob("*.html")):
        for body in _INLINE_SCRIPT.findall(page.read_text(encoding="utf-8")):
            out.add("'sha256-" + base64.b64encode(hashlib.sha256(body.encode()).digest()).decode() + "'")
    return sorted(out)


def content_security_policy(scheme: str, hostname: str | None, script_hashes: list[str],
                            view_host: str | None = None) -> str:
    """The console's CSP for a request to ``scheme://hostname``; ``view_host``: the host name
    the 3D view is loaded from when the site names one (Settings.viser_public_host)."""
    frame = f" {scheme}://{hostname}:*" if hostname and _HOSTNAME.match(hostname) else ""
    if view_host and _HOSTNAME.match(view_host):
        frame += f" {scheme}://{view_host}:*"
    elif hostname in LOOPBACK_NAMES:  # the console serves its 3D view under the other name (web/js/common.js viewHost)
        frame += f" {scheme}://{LOOPBACK_NAMES[hostname]}:*"
    return "; ".join([
        "default-src 'self'", "script-src " + " ".join(["'self'", *script_hashes]),
        "style-src 'self' 'unsafe-inline'", "img-src 'self' data: blob:", "connect-src 'self'",
        f"frame-src 'self'{frame}", "frame-ancestors 'none'", "base-uri 'self'", "form-action 'self'",
        "object-src 'none'",
    ])


def _header(scope: Scope, name: bytes) -> str | None:
    for k, v in scope.get("headers", []):
        if k == name:
            return v.decode("latin-1")
    return None


def _hostname(host: str | None) -> str | None:
    """The host name of a ``Host`` header (``[::1]:8000`` -> ``[::1]``, ``a:80`` -> ``a``)."""
    if not host:
        return None
    if host.startswith("["):
        return host[: host.find("]") + 1] or None
    return host.split(":", 1)[0] or None


class SecurityHeaders:
    """Adds the security headers to every HTTP response (keeps any a route set itself)."""

    def __init__(self, app: ASGIApp, script_hashes: list[str], view_host: str | None = None):
        self.app, self.script_hashes, self.view_host = app, script_hashes, view_host

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        extra = [(b"x-frame-options", b"DENY"), (b"x-content-type-options", b"nosniff"),
                 (b"referrer-policy", b"same-origin")]
        if not scope["path"].startswith(NO_CSP_PATHS):
            csp = content_security_policy(scope.get("scheme", "http"), _hostname(_header(scope, b"host")),
                                          self.script_hashes, self.view_host)
            extra.append((b"content-security-policy", csp.encode()))

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                have = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = list(message.get("headers", [])) + [(k, v) for k, v in extra if k not in have]
            await send(message)

        await self.app(scope, receive, send_with_headers)


class BodySizeLimit:
    """413 for request bodies above the limit.

    Args:
        max_bytes: default limit for every route.
        overrides: ``{(method, path): max_bytes}`` for routes that take larger bodies (uploads).
    """

    def __init__(self, app: ASGIApp, max_bytes: int, overrides: dict[tuple[str, str], int] | None = None):
        self.app, self.max_bytes, self.overrides = app, max_bytes, dict(overrides or {})

    def limit_for(self, method: str, path: str) -> int:
        return self.overrides.get((method, path.rstrip("/") or "/"), self.max_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit = self.limit_for(scope["method"], scope["path"])
        declared = _header(scope, b"content-length")
        if declared is not None and (not declared.strip().isdigit() or int(declared) > limit):
            return await _too_large(send, limit)
        seen = 0

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:  # answered by the app's HTTPException handling: an HTTPException, not a
                    # server.errors.TooLarge, as FastAPI turns any other error raised while it reads a body into 400
                    raise HTTPException(413, _too_large_text(limit))
            return message

        await self.app(scope, limited_receive, send)


def _too_large_text(limit: int) -> str:
    return f"request body larger than {limit} bytes"


async def _too_large(send: Send, limit: int) -> None:
    body = json.dumps({"detail": _too_large_text(limit)}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def contained_file(folder: Path, path: Path | None) -> Path | None:
    """``path`` with every symbolic link resolved, if that is a regular file inside ``folder``
    (itself resolved); None otherwise. Serve the returned path, so that a link placed in a served
    folder (a diagnosis report, the telemetry folder) never hands out a file from elsewhere."""
    if path is None:
        return None
    try:
        real, root = Path(path).resolve(strict=True), Path(folder).resolve(strict=True)
    except (OSError, RuntimeError):  # missing, or a link loop
        return None
    return real if real.is_relative_to(root) and real.is_file() else None
