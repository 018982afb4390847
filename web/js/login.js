// Log-in page: POST /api/auth/login, then back to the page that sent us here (console pages only).
"use strict";

document.getElementById("login-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const body = { username: document.getElementById("username").value, password: document.getElementById("password").value };
  const res = await fetch("/api/auth/login", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  if (res.ok) {
    const next = new URLSearchParams(location.search).get("next");
    location.href = next && next.startsWith("/console/") ? next : "/console/";
  } else {
    const data = await res.json().catch(() => ({}));
    document.getElementById("login-error").textContent = typeof data.detail === "string" ? data.detail : "log-in failed";
  }
});
