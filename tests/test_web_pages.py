"""The console's pages share one head and one top bar (server.console.pages): no page carries a
copied <head>, every page is served assembled, the partials are not served, a bad include is an
error that names it; the 3D view may be framed under the other loopback name (web_guard CSP)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from server.api.web_guard import content_security_policy
from server.console.pages import assemble

WEB = Path(__file__).resolve().parent.parent / "web"
PAGES = sorted(p.name for p in WEB.glob("[a-z]*.html"))


def test_no_page_has_a_copied_head_or_top_bar():
    assert len(PAGES) >= 10
    for name in PAGES:
        text = (WEB / name).read_text()
        assert "<head>" not in text and "<meta" not in text, name
        assert '<!--#include virtual="_head.html"' in text, name
        if name != "login.html":
            assert "<header" not in text and '<!--#include virtual="_top.html" -->' in text, name
            assert '<!--#include virtual="_scripts.html" -->' in text and 'src="js/strip.js"' not in text, name


def test_every_page_is_served_assembled(client):
    for name in PAGES:
        r = client.get(f"/console/{name}")
        assert r.status_code == 200, (name, r.text)
        html = r.text
        assert "#include" not in html and html.count("<head>") == 1 and '<meta charset="utf-8">' in html, name
        title = re.search(r'include virtual="_head.html" title="([^"]*)"', (WEB / name).read_text())[1]
        assert f"<title>{title}</title>" in html, name
        if name != "login.html":
            assert 'id="logout"' in html and 'src="js/strip.js"' in html, name
        assert "content-security-policy" in r.headers, name


def test_partials_are_not_served_and_bad_includes_are_named(client, tmp_path):
    assert client.get("/console/_head.html").status_code == 404
    (tmp_path / "_p.html").write_text("<p>{{who}}</p>")
    assert assemble('<!--#include virtual="_p.html" who="a &amp; <b>" -->', tmp_path) == "<p>a &amp; &lt;b&gt;</p>"
    with pytest.raises(ValueError, match="_missing.html"):
        assemble('<!--#include virtual="_missing.html" -->', tmp_path)
    with pytest.raises(ValueError, match="who"):
        assemble('<!--#include virtual="_p.html" -->', tmp_path)


def test_the_3d_view_may_be_framed_under_the_other_loopback_name():
    assert "frame-src 'self' http://localhost:* http://127.0.0.1:*" in content_security_policy("http", "localhost", [])
    assert "frame-src 'self' http://127.0.0.1:* http://localhost:*" in content_security_policy("http", "127.0.0.1", [])
    assert "localhost" not in content_security_policy("https", "site.example", [])


def test_the_3d_view_may_be_framed_from_the_sites_view_host_name():
    """Settings.viser_public_host: the console page frames the view from that name (its own
    renderer process on a deployed site); a malformed name adds nothing."""
    csp = content_security_policy("https", "console.site.example", [], view_host="view.site.example")
    assert "frame-src 'self' https://console.site.example:* https://view.site.example:*;" in csp
    assert "frame-src 'self' https://console.site.example:*;" in content_security_policy(
        "https", "console.site.example", [], view_host="bad host;")


def test_the_consoles_final_throw_statuses_are_the_servers():
    """web/js/console.js keeps its own copy of the statuses that end a throw (it waits for one to
    show the result); it must name exactly server.db.models.FINAL_STATUSES."""
    from server.db.models import FINAL_STATUSES

    line = re.search(r"const FINAL_STATUSES = \[([^\]]*)\];", (WEB / "js" / "console.js").read_text())
    assert line, "console.js no longer declares FINAL_STATUSES: update this test"
    assert tuple(re.findall(r'"([a-z_]+)"', line.group(1))) == FINAL_STATUSES
