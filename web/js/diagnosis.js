// Diagnosis page: start a run on a machine's stored throws, list runs, show a report:
// the where, the verdict with its evidence (wins under resampling, at-bound flags, ambiguity)
// and how far each named effect shrinks the gap on held-out throws.
"use strict";

const pct = (x) => (x === null || x === undefined ? "–" : `${(100 * x).toFixed(0)}%`);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));
let adaptationId = null;
const runStatus = {};
// each job event asks again: only the newest answer draws (an older one landing late would show a finished run running)
const newestRuns = latestOnly(), newestRun = latestOnly(), newestAdaptation = latestOnly();

async function loadRuns() {
  const mine = newestRuns();
  const runs = await api("GET", "/api/diagnosis/runs");
  if (!mine()) return;
  const body = $("runs").querySelector("tbody");
  body.innerHTML = "";
  for (const r of runs) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td><a href="#${esc(r.id)}">${esc(r.id)}</a></td><td>${esc(r.machine_id)}</td><td>${r.throws}</td>` +
      `<td class="status-${r.status === "done" ? "landed" : esc(r.status)}">${esc(r.status)}</td><td>${esc(r.verdict ? r.verdict.text : (r.error || ""))}</td>`;
    body.appendChild(tr);
  }
  const want = location.hash.slice(1) || (runs.find((r) => r.status === "done") || {}).id;
  if (want) showRun(want);
}

function paramText(c) {
  return Object.entries(c.params).map(([k, v]) =>
    `${esc(k)} = ${Number(v).toPrecision(4)}${c.sigma[k] !== undefined ? " ± " + Number(c.sigma[k]).toPrecision(2) : " (not identifiable)"}` +
    (c.at_bound.includes(k) ? " <b class=\"flag\">at bound</b>" : "")).join(", ");
}

function showWhere(w) {
  const phases = Object.entries(w.phases || {}).map(([p, s]) => `${p} ${pct(s)}`).join(", ");
  $("where-summary").textContent = w.gap
    ? `The gap is in ${w.carriers.join(", ")}` + (phases ? ` (share of the excess per phase: ${phases}).` : ".")
    : "No channel exceeds its measured noise: no gap.";
  const chans = Object.entries(w.channels).sort((a, b) => (b[1].chi2 / b[1].dof) - (a[1].chi2 / a[1].dof));
  const sig = w.noise.sigma;
  $("where").querySelector("tbody").innerHTML = chans.map(([c, v]) =>
    `<tr class="${v.gap ? "gap" : ""}"><td>${esc(c)}</td><td>${v.gap ? "gap" : "–"}</td><td>${fmt(v.chi2 / v.dof, 2)}</td>` +
    ["swing", "release", "flight"].map((p) => { const b = v.by_phase[p]; return `<td>${b && b.dof ? fmt(b.chi2 / b.dof, 2) : "–"}</td>`; }).join("") +
    `<td>${sig[c] !== undefined ? Number(sig[c]).toPrecision(2) : (c.startsWith("impact") ? Number(w.noise.impact_sigma_m).toPrecision(2) + " m" : "–")}</td></tr>`).join("");
}

function showWhich(rounds) {
  const rows = [];
  const gated = [];
  rounds.forEach((r, i) => {
    rows.push(`<tr><td>${i + 1}</td><td><i>none (twin as is)</i></td><td>${pct(r.wins_none)}</td><td>–</td><td>–</td><td>${esc(r.decision)}</td></tr>`);
    for (const c of r.candidates) {
      rows.push(`<tr class="${c.effect === r.named ? "named" : ""}"><td>${i + 1}</td><td>${esc(c.effect)}</td><td>${pct(c.wins)}</td><td>${pct(c.beats_none)}</td>` +
        `<td>${c.admissible ? "yes" : "no: " + esc(c.reason)}</td><td>${paramText(c)}</td></tr>`);
    }
    for (const [e, why] of Object.entries(r.gated_out)) gated.push(`${e} (round ${i + 1}): ${why}`);
  });
  $("which").querySelector("tbody").innerHTML = rows.join("");
  $("gated").textContent = gated.length ? "Not fitted (they cannot act where the gap is): " + gated.join("; ") : "";
}

function showHowFar(h) {
  const shares = $("shares").querySelector("tbody");
  const acc = $("accuracy").querySelector("tbody");
  if (!h) {
    $("howfar").textContent = "No effect named: nothing to add to the twin.";
    shares.innerHTML = "";
    acc.innerHTML = "";
    return;
  }
  $("howfar").textContent = `On ${h.test_throws.length} held-out throws: χ² excess over noise ${fmt(h.chi2_excess_before, 1)} → ${fmt(h.chi2_excess_after, 1)} ` +
    `(gap shrink ${pct(h.gap_shrink)}); impact error RMS ${fmt(h.impact_rms_m.before, 3)} → ${fmt(h.impact_rms_m.after, 3)} m (shrink ${pct(h.impact_gap_shrink)}).`;
  shares.innerHTML = Object.entries(h.share_of_shrink).map(([e, s]) => `<tr><td>${esc(e)}</td><td>${pct(s)}</td></tr>`).join("");
  const a = h.accuracy;
  acc.innerHTML = Object.keys(a.observed).sort((x, y) => x - y).map((d) =>
    `<tr><td>${d}</td>` + ["observed", "replayed_nominal", "replayed_fitted"].map((k) => {
      const v = a[k][d];
      return `<td>${v ? `${fmt(v.mean_downrange_m)} ± ${fmt(v.sigma_downrange_m)}` : "–"}</td>`;
    }).join("") + "</tr>").join("");
}

/** The answer in plain words first: what is wrong, how sure, what to do. */
function plainSummary(run, rep) {
  const v = rep.verdict, w = rep.where || {};
  const m = run.machine_id || "the machine";
  const n = run.throws ? `${run.throws} throws` : "its throws";
  if (v.answer === "drifting") return `${m}'s gap is not the same early and late in the log: ${v.text} ` +
    "What to do: find what changed on the machine around then (wear, oil temperature, a repair, a new payload); " +
    "do not adapt the policy to this log; diagnose again on throws made after the change.";
  if (!w.gap) return `The twin matches ${m} within its measurement noise on ${n}. Nothing to do.`;
  const named = (rep.rounds || []).filter((r) => r.decision === "named");
  const sure = named.length ? Math.min(...named.map((r) => (r.candidates.find((c) => c.effect === r.named) || {}).wins || 0)) : null;
  const h = rep.how_far;
  const shrink = h && h.impact_rms_m ? ` With it, the twin's impact error on throws it never saw drops from ${fmt(h.impact_rms_m.before, 2)} m to ${fmt(h.impact_rms_m.after, 2)} m.` : "";
  if (v.answer === "named" || (v.effects && v.effects.length && v.answer !== "unexplained")) {
    const effects = (v.effects || named.map((r) => r.named)).map((e) => e.replace(/_/g, " ")).join(" and ");
    let text = `${m} behaves differently from the twin: ${effects}` + (sure !== null ? ` (it explains the gap in ${pct(sure)} of resamples).` : ".") + shrink;
    if (v.answer === "ambiguous") text += ` A further difference could be ${v.between.map((e) => e.replace(/_/g, " ")).join(" or ")}: to tell them apart, ${v.measurement}.`;
    return `${text} What to do: adapt the policy to this machine (section 4 below), evaluate and promote it under Policies.`;
  }
  if (v.answer === "ambiguous") return `${m} differs from the twin, but the throws cannot tell whether it is ${v.between.map((e) => e.replace(/_/g, " ")).join(" or ")}. ` +
    `What to do: ${v.measurement}, then run the diagnosis again.`;
  const partly = (v.partly_consistent || []).map((p) => `${p.effect.replace(/_/g, " ")} (${[].concat(p.why).join("; ")})`);
  if (partly.length) return `${m} differs from the twin (in ${(w.carriers || []).join(", ")}). It is partly consistent with ${partly.join(" and ")}, ` +
    "which is not confirmed: do not replace parts on this evidence. What to do: check the machine (hydraulics, sensors, payload) " +
    "and the twin's model with an engineer; throws still work but may miss more.";
  return `${m} differs from the twin (in ${(w.carriers || []).join(", ")}) and no known effect explains it. What to do: ` +
    "check the machine (hydraulics, sensors, payload) and the twin's model with an engineer; throws still work but may miss more.";
}

async function showRun(id) {
  const mine = newestRun();
  const run = await api("GET", `/api/diagnosis/runs/${id}`);
  if (!mine() || !run.report) return;
  const rep = run.report;
  $("report").hidden = false;
  $("r-id").textContent = id;
  const v = rep.verdict;
  $("r-summary").textContent = plainSummary(run, rep);
  $("r-verdict").textContent = `${v.answer.replace("_", " ")}: ${v.text}`;
  $("r-verdict").dataset.answer = v.answer;
  $("r-ambiguity").hidden = v.answer !== "ambiguous";
  if (v.answer === "ambiguous") $("r-ambiguity").textContent = `Ambiguous between ${v.between.join(" and ")}. To separate them: ${v.measurement}.`;
  const file = (n) => `/api/diagnosis/runs/${id}/files/${n}`;
  for (const n of ["where", "which", "how_far"]) {
    const img = $(`img-${n}`);
    img.hidden = !(rep.plots && rep.plots[n]);
    if (!img.hidden) img.src = file(`${n}.png`);
  }
  $("r-json").href = file("report.json");
  $("r-profile").href = file("profile_fitted.json");
  showWhere(rep.where);
  showWhich(rep.rounds);
  showHowFar(rep.how_far);
}

async function showAdaptation(id) {
  const mine = newestAdaptation();
  const st = await api("GET", `/api/adaptations/${id}`);
  if (!mine()) return;
  const last = st.progress.length ? st.progress[st.progress.length - 1] : "";
  $("adapt-msg").textContent = st.status === "done" ? `version ${st.policy_version} made: evaluate and promote it under Policies`
    : st.status === "failed" ? `failed: ${st.error}` : `adapting ${st.base_version}… ${last}`;
}

// Runs and adaptations are jobs: their progress and completion arrive as "job" events on
// /api/live (no polling). A diagnosis event refreshes the run list (and the shown report when
// it finished); an adaptation event refreshes the adaptation line.
function onJob(job) {
  if (job.kind === "diagnosis") {
    if (runStatus[job.id] !== job.status) { runStatus[job.id] = job.status; loadRuns(); }
  } else if (job.kind === "adaptation" && job.id === adaptationId) {
    showAdaptation(job.id);
  }
}

async function fillMachines() {
  let ids = [];
  try { ids = (await api("GET", "/api/machines")).map((m) => m.id); } catch (e) { /* none listed */ }
  listMachines(ids);
  if (Strip.machineId && ids.includes(Strip.machineId)) $("machine_id").value = Strip.machineId;
}

/** The machine choices: those listed so far and ``ids`` (a machine that came online after the
 *  page's GET /api/machines joins by its live state), sorted; the choice made stays. */
function listMachines(ids) {
  const sel = $("machine_id"), was = sel.value;
  const all = [...new Set([...[...sel.options].map((o) => o.value), ...ids])].sort();
  if (all.length === sel.options.length) return;
  sel.innerHTML = "";
  for (const id of all) sel.add(new Option(id, id));
  if (was) sel.value = was;
}

document.addEventListener("DOMContentLoaded", async () => {
  await whoAmI();
  Live.on("machine", (m) => listMachines([m.machine_id])); // before the GET: a machine heard meanwhile is kept
  await fillMachines();
  Strip.onSelect((id) => { if ([...$("machine_id").options].some((o) => o.value === id)) $("machine_id").value = id; });
  Live.on("job", onJob); // the strip starts the live stream on this page
  Live.on("connected", loadRuns);
  $("start").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    $("start-msg").textContent = "exporting throws…";
    try {
      const st = await api("POST", "/api/diagnosis/runs", { machine_id: $("machine_id").value, limit: Number($("limit").value) });
      $("start-msg").textContent = `run ${st.id} started on ${st.throws} throws`;
      loadRuns();
    } catch (e) {
      $("start-msg").textContent = e.message;
    }
  });
  $("upload").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const form = new FormData();
    for (const f of $("up-bags").files) form.append("bags", f, f.name);
    form.append("mapping", $("up-mapping").files[0]);
    form.append("impacts", $("up-impacts").files[0]);
    form.append("machine_id", $("up-machine").value || "external");
    $("upload-msg").textContent = `uploading ${$("up-bags").files.length} bags…`;
    try {
      const st = await api("POST", "/api/diagnosis/uploads", form, true);
      $("upload-msg").textContent = `Run ${st.id} started on the uploaded bags; it appears in the list below.`;
      loadRuns();
    } catch (e) {
      $("upload-msg").textContent = e.message;
    }
  });
  $("adapt").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const id = $("r-id").textContent;
    $("adapt-msg").textContent = "starting…";
    try {
      const st = await api("POST", `/api/diagnosis/runs/${id}/adapt`, { mode: $("adapt-mode").value });
      adaptationId = st.id;
      showAdaptation(st.id);
    } catch (e) {
      $("adapt-msg").textContent = e.message;
    }
  });
  window.addEventListener("hashchange", () => showRun(location.hash.slice(1)));
  loadRuns();
});
