// Alarms page: the active alarms or the whole alarm history (GET /api/alarms), following live
// ``alarm`` events; operators acknowledge one or all, shelve for a chosen time and unshelve.
"use strict";

const STATE_WORDS = { unacked: "active, not acknowledged", acked: "active, acknowledged",
  rtn_unacked: "cleared, not acknowledged", normal: "cleared and acknowledged" };
const SHELVE_CHOICES = [15, 60, 240, 480];

const when = (t) => (t ? new Date(t).toLocaleString() : "–");

function say(text, isError = false) {
  $("alarms-status").textContent = text;
  $("alarms-status").className = isError ? "error" : "";
}

async function act(promise, done) {
  try { await promise; say(done); } catch (e) { say(e.message, true); }
  load();
}

function actions(a) {
  const span = document.createElement("span");
  if (!a.active) return span;
  if (a.state === "unacked" || a.state === "rtn_unacked") {
    const b = document.createElement("button");
    b.type = "button"; b.className = "alarm-ack"; b.textContent = "Acknowledge";
    b.addEventListener("click", () => act(api("POST", `/api/alarms/${a.id}/ack`), `Acknowledged: ${a.title}.`));
    span.append(b, " ");
  }
  if (a.shelved) {
    const b = document.createElement("button");
    b.type = "button"; b.className = "alarm-unshelve"; b.textContent = "Unshelve";
    b.addEventListener("click", () => act(api("DELETE", `/api/alarms/${a.id}/shelve`), `Unshelved: ${a.title}.`));
    span.append(b);
  } else {
    const sel = document.createElement("select");
    sel.setAttribute("aria-label", `shelve ${a.title} for`);
    for (const m of SHELVE_CHOICES) sel.add(new Option(m < 60 ? `${m} min` : `${m / 60} h`, String(m)));
    const b = document.createElement("button");
    b.type = "button"; b.className = "alarm-shelve"; b.textContent = "Shelve";
    b.addEventListener("click", () => act(api("POST", `/api/alarms/${a.id}/shelve`, { minutes: Number(sel.value) }),
      `Shelved for ${sel.selectedOptions[0].textContent}: ${a.title}.`));
    span.append(sel, " ", b);
  }
  return span;
}

const newestLoad = latestOnly(); // each alarm event asks again: only the newest answer draws
let shelfTimer = null;

async function load() {
  const all = $("alarm-scope").value === "all", mine = newestLoad();
  let rows;
  try { rows = await api("GET", all ? "/api/alarms?active=false&limit=500" : "/api/alarms"); } catch (e) { if (mine()) say(e.message, true); return; }
  if (!mine()) return;
  // a shelving that runs out is no event: ask again when the first one ends
  clearTimeout(shelfTimer);
  const wait = msToShelfEnd(rows);
  if (wait !== null) shelfTimer = setTimeout(load, wait);
  const body = $("alarm-table").querySelector("tbody");
  body.innerHTML = "";
  $("alarms-empty").hidden = rows.length > 0;
  for (const a of rows) {
    const tr = body.insertRow();
    tr.dataset.alarmId = a.id;
    tr.className = `alarm-row alarm-${a.priority}`;
    const cells = [when(a.raised_at), a.priority, a.machine_id || "–", `${a.title}. ${a.text} ${a.todo}`,
      STATE_WORDS[a.state] + (a.shelved ? " (shelved)" : ""),
      a.acked_at ? `${when(a.acked_at)} by ${a.acked_by}` : "–", when(a.cleared_at),
      a.shelved ? `${when(a.shelved_until)} (${a.shelved_by})` : "–"];
    for (const c of cells) tr.insertCell().textContent = c;
    const td = tr.insertCell();
    td.dataset.role = "operator"; td.hidden = !can("operator");
    td.append(actions(a));
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  $("alarm-scope").addEventListener("change", load);
  $("alarms-ack-all").addEventListener("click", () => act(api("POST", "/api/alarms/ack-all", {}), "Every alarm acknowledged."));
  Live.on("alarm", load);
  Live.on("connected", load);
  await load();
});
