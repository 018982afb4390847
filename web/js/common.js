// Shared by the console pages: JSON API calls (401 -> log-in page), formatting, the page header.
"use strict";

const $ = (id) => document.getElementById(id);
const session = { user: null };

async function api(method, path, body, isForm = false) {
  const opts = { method, headers: {} };
  if (body !== undefined) {
    if (isForm) opts.body = body;
    else { opts.headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(body); }
  }
  const res = await fetch(path, opts);
  if (res.status === 401 && !path.startsWith("/api/auth/login")) {
    location.href = `/console/login.html?next=${encodeURIComponent(location.pathname + location.search)}`;
    throw new Error("401: log in first");
  }
  const data = await res.json().catch(() => null);
  if (!res.ok) {
    let detail = data && data.detail;
    if (Array.isArray(detail)) detail = detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
    throw new Error(`${res.status}: ${detail || res.statusText}`);
  }
  return data;
}

const fmt = (v, n = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(n));
const fmtVec = (v) => (v ? v.map((x) => fmt(x)).join(", ") : "–");
const ROLE_RANK = { viewer: 0, operator: 1, admin: 2 };
const can = (role) => session.user && ROLE_RANK[session.user.role] >= ROLE_RANK[role];

// The pages of the console, in the order of the navigation bar; [href, label, role needed].
const SITE_PAGES = [
  ["index.html", "Console"], ["history.html", "History"], ["accuracy.html", "Accuracy"],
  ["policies.html", "Policies"], ["fleet.html", "Fleet"], ["diagnosis.html", "Diagnosis"],
  ["admin.html", "Users", "admin"], ["/docs", "API"],
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
  return session.user;
}

/** Ask before a consequential action (promote, rollback, 3D throw): a modal dialog; resolves true on OK. */
function confirmAction(title, text, okLabel = "Confirm") {
  let dlg = $("confirm-dialog");
  if (!dlg) {
    dlg = document.createElement("dialog");
    dlg.id = "confirm-dialog";
    dlg.setAttribute("aria-labelledby", "confirm-title");
    dlg.innerHTML = '<form method="dialog"><h2 id="confirm-title"></h2><p id="confirm-text"></p><div class="actions">' +
      '<button value="cancel" type="submit">Cancel</button> <button id="confirm-ok" value="ok" type="submit" class="primary"></button></div></form>';
    document.body.appendChild(dlg);
  }
  $("confirm-title").textContent = title;
  $("confirm-text").textContent = text;
  $("confirm-ok").textContent = okLabel;
  dlg.returnValue = "cancel";
  return new Promise((resolve) => {
    dlg.addEventListener("close", () => resolve(dlg.returnValue === "ok"), { once: true });
    dlg.showModal();
  });
}

async function logout() {
  await fetch("/api/auth/logout", { method: "POST" });
  location.href = "/console/login.html";
}

document.addEventListener("DOMContentLoaded", () => {
  const btn = $("logout");
  if (btn) btn.addEventListener("click", logout);
});
