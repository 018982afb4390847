// Users and audit log (admins): add users; the audit log with each entry's details as a readable list.
"use strict";

/** An audit entry's detail object as a definition list (nested values as compact JSON). */
function detailList(detail) {
  const dl = document.createElement("dl");
  dl.className = "kv";
  for (const [k, v] of Object.entries(detail || {})) {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = k.replace(/_/g, " ");
    dd.textContent = v === null ? "–" : Array.isArray(v) && v.every((x) => typeof x === "number") ? v.map((x) => fmt(x)).join(", ")
      : typeof v === "object" ? JSON.stringify(v) : String(v);
    dl.append(dt, dd);
  }
  return dl;
}

async function loadUsers() {
  const users = await api("GET", "/api/users");
  const body = $("users").querySelector("tbody"); body.innerHTML = "";
  for (const u of users) {
    const tr = body.insertRow();
    [u.username, u.role, u.active ? "yes" : "no", new Date(u.created_at).toLocaleString()].forEach((c) => { tr.insertCell().textContent = c; });
  }
  const log = await api("GET", "/api/audit?limit=100");
  const ab = $("audit").querySelector("tbody"); ab.innerHTML = "";
  $("audit-empty").hidden = log.length > 0;
  for (const a of log) {
    const tr = ab.insertRow();
    [new Date(a.at).toLocaleString(), a.username, a.action.replace(/_/g, " "), a.subject || ""].forEach((c) => { tr.insertCell().textContent = c; });
    tr.insertCell().appendChild(detailList(a.detail));
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  if (!can("admin")) { $("u-status").textContent = "Only admins see users and the audit log."; return; }
  $("add-user").addEventListener("submit", async (e) => {
    e.preventDefault();
    try {
      await api("POST", "/api/users", { username: $("n-username").value, password: $("n-password").value, role: $("n-role").value });
      $("u-status").textContent = `added ${$("n-username").value}`; loadUsers();
    } catch (err) { $("u-status").textContent = err.message; }
  });
  loadUsers();
});
