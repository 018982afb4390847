// My account: change my own password (POST /api/account/password; every session ends after it).
"use strict";

async function changePassword(e) {
  e.preventDefault();
  const msg = $("password-msg");
  if ($("new-password").value !== $("new-password-2").value) {
    msg.textContent = "The two new passwords differ: type the same one twice.";
    msg.className = "error";
    return;
  }
  try {
    await api("POST", "/api/account/password", { current_password: $("current-password").value, new_password: $("new-password").value });
    msg.textContent = "Password changed. Log in again with the new one…";
    msg.className = "ok";
    setTimeout(() => { location.href = "/console/login.html"; }, 1500);
  } catch (err) {
    msg.textContent = `Not changed: ${err.message}`;
    msg.className = "error";
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  $("password-form").addEventListener("submit", changePassword);
});
