"""The console's pages from one head and one top bar: server-side includes in web/*.html.

A page writes ``<!--#include virtual="_head.html" title="Slinger: fleet" -->`` where its
``<head>`` goes, ``<!--#include virtual="_top.html" -->`` for the top bar (site navigation, user,
log-out, the server-unreachable banner) and ``<!--#include virtual="_scripts.html" -->`` for the
scripts every page runs (common.js, live.js, strip.js: the status strip with its E-STOP). The
named file (``web/_*.html``, a partial) replaces the comment; each ``name="value"`` argument fills
``{{name}}`` in it, HTML-escaped. :class:`PageFiles` serves the console folder with its pages so
assembled (the other files as they are).
"""

from __future__ import annotations

import html
import re
from pathlib import Path

from starlette.responses import HTMLResponse, Response
from starlette.staticfiles import StaticFiles

INCLUDE = re.compile(r'<!--#include virtual="(?P<file>_[A-Za-z0-9_-]+\.html)"(?P<args>(?:\s+[a-z]+="[^"]*")*)\s*-->')
ARG = re.compile(r'([a-z]+)="([^"]*)"')
SLOT = re.compile(r"\{\{([a-z]+)\}\}")


def assemble(page: str, web_dir: Path) -> str:
    """``page`` (an HTML text) with every include replaced by its partial from ``web_dir``.

    Raises:
        ValueError: a partial that does not exist, or a ``{{slot}}`` that the include gives no value.
    """
    def one(m: re.Match) -> str:
        path = web_dir / m["file"]
        if not path.is_file():
            raise ValueError(f"include of a missing partial {m['file']}")
        args = dict(ARG.findall(m["args"] or ""))

        def slot(s: re.Match) -> str:
            if s[1] not in args:
                raise ValueError(f"{m['file']} needs {s[1]}=\"...\" in its include")
            return html.escape(html.unescape(args[s[1]]))

        return SLOT.sub(slot, path.read_text(encoding="utf-8")).rstrip("\n")

    return INCLUDE.sub(one, page)


class PageFiles(StaticFiles):
    """StaticFiles whose ``.html`` files are served assembled (:func:`assemble`); the partials
    themselves (``_*.html``) are not served."""

    def file_response(self, full_path, stat_result, scope, status_code: int = 200) -> Response:
        path = Path(full_path)
        if path.suffix == ".html":
            if path.name.startswith("_"):
                return HTMLResponse("Not Found", status_code=404)
            return HTMLResponse(assemble(path.read_text(encoding="utf-8"), path.parent), status_code=status_code)
        return super().file_response(full_path, stat_result, scope, status_code)
