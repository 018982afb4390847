// Shared by the console pages: JSON API calls (401 -> log-in page), formatting, the page header.
"use strict";

const $ = (id) => document.getElementById(id);
const session = { user: null };

/** A JSON API call: the parsed answer, or a thrown apiError. A 401 leaves for the log-in page,
 *  except with ``keepPage`` (the E-STOP: it must say it was not sent, not leave the page). */
async function api(method, path, body, isForm = false, { keepPage = false } = {}) {
  const opts = { method, headers: {} };
  if (body !== undefined) {
    if (isForm) opts.body = body;
    else { opts.headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(body); }
  }
  const res = await fetch(path, opts);
  if (res.status === 401 && !keepPage && !path.startsWith("/api/auth/login")) {
    // The page is leaving for the log-in page: the call never settles, so no caller shows a stale
    // error and no unhandled rejection is reported while the page unloads.
    toLogIn();
    return new Promise(() => {});
  }
  const data = await res.json().catch(() => null);
  if (!res.ok) throw responseError(res, data);
  return data;
}

const leavingForLogIn = [];

/** ``fn()`` runs just before this page leaves for the log-in page (to keep what the operator typed
 *  in sessionStorage for the page's return); a hook that throws does not stop the others. */
function onLeaveForLogIn(fn) { leavingForLogIn.push(fn); }

/** Leave for the log-in page, which comes back to this page (path and query) afterwards. */
function toLogIn() {
  for (const fn of leavingForLogIn) { try { fn(); } catch (e) { /* keep leaving */ } }
  location.href = `/console/login.html?next=${encodeURIComponent(location.pathname + location.search)}`;
}

/** The error of a refused response ``res`` with its parsed JSON body ``data`` (or null): the
 *  server's detail as a sentence (a validation list joined), its status and gate condition. */
function responseError(res, data) {
  let detail = data && data.detail;
  if (Array.isArray(detail)) detail = detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
  return apiError(res.status, detail || res.statusText, res.headers.get("X-Refused-Condition"));
}

/** The server's reason as a sentence an operator reads (never "409: ..."): capital first letter,
 *  a full stop; the HTTP status and the gate condition (server.throws.gate) stay on the error as
 *  ``status`` and ``condition`` for the code. */
function sentence(text) {
  const t = String(text || "").trim();
  if (!t) return "";
  const s = t[0].toUpperCase() + t.slice(1);
  return /[.!?…]$/.test(s) ? s : `${s}.`;
}

function apiError(status, detail, condition = null) {
  const reason = status === 503 && !detail ? "the server cannot reach the machine or its workers right now" : detail;
  const err = new Error(sentence(reason || `the server answered ${status}`));
  err.status = status;
  err.condition = condition;
  return err;
}

/** The host name the 3D view is served under for a console page at ``host``: the other name of
 *  the loopback interface (localhost <-> 127.0.0.1), so the browser gives the view its own
 *  renderer process (another site) and its WebGL drawing never holds up this page's E-STOP;
 *  any other host name serves it as is (a site gives its view its own name with
 *  SLINGER_VISER_PUBLIC_HOST, which the console's answer carries: embedViser; docs/deployment.md). */
function viewHost(host) {
  return { localhost: "127.0.0.1", "127.0.0.1": "localhost" }[host] || host;
}

/** Show the 3D view (viser) of console ``c`` (POST /api/consoles' answer) in ``iframe``, under
 *  the site's view host name (``c.viser_host``: Settings.viser_public_host) or else viewHost's: its
 *  websocket path (with the console's view token) binds the view to the console (server.console.scene);
 *  the status strip hears Esc from the frame's origin. */
function embedViser(iframe, c) {
  const host = c.viser_host || viewHost(location.hostname);
  const ws = `${location.protocol === "https:" ? "wss" : "ws"}://${host}:${c.viser_port}${c.viser_path}`;
  const origin = `${location.protocol}//${host}:${c.viser_port}`;
  if (typeof Strip !== "undefined") Strip.setViserOrigin(origin); // Esc inside the 3D view arrives from there
  iframe.src = `${origin}/?websocket=${encodeURIComponent(ws)}`;
}

/** Answers that may overtake each other (several GETs of one list on their way, each sent on a
 *  live event): ``const newest = latestOnly();`` once, then in the loader ``const mine = newest();``
 *  before the request and ``if (!mine()) return;`` after it: the answer to a request sent before
 *  the newest one is dropped, so an older answer landing late never draws over a newer one. */
function latestOnly() {
  let sent = 0;
  return () => { const mine = ++sent; return () => mine === sent; };
}

/** Milliseconds until the first shelving among ``alarms`` ends (server.console.alarms.alarm_dict:
 *  ``shelved``, ``shelved_until`` ISO 8601 UTC), at least ``minMs`` (a browser clock ahead of the
 *  server's asks again at most that often); null when none is shelved. The server publishes no
 *  event when a shelving runs out: a page showing alarms asks for them again then. */
function msToShelfEnd(alarms, minMs = 5000) {
  const ends = alarms.filter((a) => a.active && a.shelved && a.shelved_until).map((a) => Date.parse(a.shelved_until));
  return ends.length ? Math.max(minMs, Math.min(...ends) - Date.now() + 500) : null;
}

const fmt = (v, n = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(n));
const fmtVec = (v) => (v ? v.map((x) => fmt(x)).join(", ") : "–");
const ROLE_RANK = { viewer: 0, operator: 1, admin: 2 };
const can = (role) => session.user && ROLE_RANK[session.user.role] >= ROLE_RANK[role];

// The pages of the console, in the order of the navigation bar; [href, label, role needed].
const SITE_PAGES = [
  ["index.html", "Console"], ["history.html", "History"], ["accuracy.html", "Accuracy"],
  ["policies.html", "Policies"], ["fleet.html", "Fleet"], ["diagnosis.html", "Diagnosis"], ["alarms.html", "Alarms"],
  ["admin.html", "Users", "admin"], ["account.html", "My account"], ["/docs", "API"],
];

function renderNav() {
  for (const nav of document.querySelectorAll("nav[data-site-nav]")) {
    const here = location.pathname.split("/").pop() || "index.html";
    nav.innerHTML = SITE_PAGES.map(([href, label, role]) =>
      `<a href="${href}"${role ? ` data-role="${role}"` : ""}${href.startsWith("/") ? ' target="_blank"' : ""}` +
      `${href === here ? ' aria-current="page"' : ""}>${label}</a>`).join(" ");
  }
}
renderNav(); // common.js is loaded at the end of <body>: the header is already there

async function whoAmI() {
  session.user = await api("GET", "/api/auth/me");
  const who = $("who");
  if (who) who.textContent = `${session.user.username} (${session.user.role})`;
  for (const el of document.querySelectorAll("[data-role]")) el.hidden = !can(el.dataset.role);
  if (typeof Strip !== "undefined") Strip.watchLogIn(session.user.session_expires_at); // pages with the status strip
  return session.user;
}

/** Ask before a consequential action (reset E-STOP, promote, rollback, delete, 3D throw): a
 *  dialog that resolves true only on its OK button. Cancel has the focus (Enter or Space on it
 *  cancels): a dangerous act is never one key press away. :func:`cancelConfirm` closes it as
 *  cancelled (the page's state it asked about changed). */
function confirmAction(title, text, okLabel = "Confirm") {
  let dlg = $("confirm-dialog");
  if (!dlg) {
    dlg = document.createElement("dialog");
    dlg.id = "confirm-dialog";
    dlg.setAttribute("aria-labelledby", "confirm-title");
    dlg.innerHTML = '<form method="dialog"><h2 id="confirm-title"></h2><p id="confirm-text"></p><div class="actions">' +
      '<button id="confirm-cancel" value="cancel" type="submit">Cancel</button> <button id="confirm-ok" value="ok" type="submit" class="primary"></button></div></form>';
    document.body.appendChild(dlg);
  }
  $("confirm-title").textContent = title;
  $("confirm-text").textContent = text;
  $("confirm-ok").textContent = okLabel;
  dlg.returnValue = "cancel";
  // not showModal(): a modal dialog sits in the browser's top layer, above any z-index, and makes
  // the rest of the page inert: the E-STOP would be dimmed and dead under its backdrop. A plain
  // dialog with our own backdrop (.dialog-backdrop) keeps the E-STOP above both, live.
  let backdrop = $("dialog-backdrop");
  if (!backdrop) {
    backdrop = document.createElement("div");
    backdrop.id = "dialog-backdrop";
    backdrop.className = "dialog-backdrop";
    document.body.appendChild(backdrop);
  }
  const before = document.activeElement;
  return new Promise((resolve) => {
    dlg.addEventListener("close", () => {
      backdrop.hidden = true;
      if (before && before.focus) before.focus();
      resolve(dlg.returnValue === "ok");
    }, { once: true });
    backdrop.hidden = false;
    dlg.show();
    $("confirm-cancel").focus();
  });
}

/** Close the open confirm dialog (if any) as cancelled: its promise resolves false. */
function cancelConfirm() {
  const dlg = $("confirm-dialog");
  if (dlg && dlg.open) dlg.close("cancel");
}

async function logout() {
  await fetch("/api/auth/logout", { method: "POST" });
  location.href = "/console/login.html";
}

document.addEventListener("DOMContentLoaded", () => {
  const btn = $("logout");
  if (btn) btn.addEventListener("click", logout);
});
