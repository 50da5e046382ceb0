// The invite links panel on the runs page (refreshed every 30 s): make a link (for one run or
// all), copy it, revoke it, open its participants page (/invites/<id>/participants: who to pay),
// and check a participant's completion code (POST /api/invites/verify).

import { SignedOut, get, post } from "./api.js";
import { ago, el, listErrors, notify, poller } from "./dom.js";

const REFRESH_MS = 30_000; // uses, and links closing as their runs end or they expire

export function startInvites() {
  document.getElementById("new-invite").addEventListener("submit", createInvite);
  document.querySelector("#new-invite [name=run_id]").addEventListener("change", showRunQuality);
  document.getElementById("verify-code").addEventListener("submit", verifyCode);
  loadInvites();
}

const WHY = {
  target: "reached the target",
  runs_over: "the run ended before the target",
  paused: "paused by check pairs",
  nothing_left: "nothing left to label",
  entry_failed: "failed the entry test: not to be paid",
};

async function verifyCode(event) {
  event.preventDefault();
  const shown = document.getElementById("verify-result");
  const code = event.target.elements.code.value.trim();
  try {
    const who = await post("/api/invites/verify", { code });
    const target = who.target_answers == null ? "" : ` of ${who.target_answers}`;
    // Earned as the participants list's code_valid: not for one deactivated, let go by the
    // entry test, or paused where the link's pause message replaced the code.
    shown.textContent = `${who.earned ? "Valid" : "Not earned"}: `
      + `${who.participant || who.labeller} (labeller ${who.labeller_id}, `
      + `link ${who.invite_id}): ${who.counted}${target} decisive answers; `
      + (who.why === "entry_failed" ? `let go: ${WHY[who.why]}.`
        : who.complete ? `complete, ${WHY[who.why]}.` : "not complete yet.");
    shown.className = "small";
  } catch (error) {
    if (error instanceof SignedOut) return;
    shown.textContent = error.status === 404 ? `Not valid: ${error.message}.` : error.message;
    shown.className = "error small";
  }
}

/** The links (and the runs they may be for) now, and every REFRESH_MS from then on while the
 * tab is visible. */
export const loadInvites = poller(async () => {
  try {
    const [invites, runs] = await Promise.all([get("/api/invites"), get("/api/runs")]);
    fillRuns(runs);
    render(invites, new Map(runs.map((run) => [run.id, run])));
  } catch (error) {
    if (error instanceof SignedOut) return false;
    notify(`Could not load the invite links: ${error.message}`, "error");
  }
  return true;
}, REFRESH_MS);

/** The runs a link may be for: those taught by people that have not ended. */
function fillRuns(runs) {
  const select = document.querySelector("#new-invite [name=run_id]");
  if (select === document.activeElement) return; // being chosen from: left alone until next time
  const chosen = select.value;
  const open = runs.filter((run) => run.teacher === "human"
    && !["stopped", "finished", "failed"].includes(run.status));
  select.replaceChildren(el("option", { value: "" }, "all runs taught by people"),
    ...open.map((run) => el("option", { value: run.id }, `${run.id} · ${run.name}`)));
  select.value = open.some((run) => String(run.id) === chosen) ? chosen : "";
  showRunQuality();
}

/** The chosen run's own quality controls, set when it was made (its configuration). */
async function showRunQuality() {
  const shown = document.getElementById("invite-run-quality");
  const runId = document.querySelector("#new-invite [name=run_id]").value;
  const entry = document.querySelector("#new-invite [name=entry_pass]");
  entry.removeAttribute("max");
  entry.disabled = false;
  if (!runId) {
    shown.textContent = "Practice pairs, check pairs and answers per pair are each run's own "
      + "(the new-run form); choose a run to see them.";
    return;
  }
  try {
    const { values } = await get(`/api/runs/${runId}/config`);
    const practice = values["feedback.practice_pairs"];
    const entry = document.querySelector("#new-invite [name=entry_pass]");
    entry.max = String(practice);
    entry.disabled = practice < 1; // an entry test needs practice pairs
    shown.textContent = `Run ${runId}: ${practice} practice pair${practice === 1 ? "" : "s"}, `
      + `check pairs ${values["feedback.gold_rate"]} of each round (accuracy to go on `
      + `${values["feedback.gold_min_accuracy"]}), ${values["feedback.labels_per_query"]} `
      + "answer(s) per pair."
      + (practice < 1 ? " No practice pairs: no entry test."
        : ` An entry test passes 1 to ${practice} of them.`);
    shown.dataset.practice = String(practice);
  } catch (error) {
    if (!(error instanceof SignedOut)) shown.textContent = error.message;
  }
}

function render(invites, runs) {
  const body = document.getElementById("invites-body");
  if (invites.length === 0) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: 8, class: "muted" },
      "No invite links yet.")));
    return;
  }
  body.replaceChildren(...invites.slice().reverse().map((invite) => el("tr",
    { "data-invite": invite.id },
    el("td", {}, String(invite.id)),
    el("td", { class: "name" },
      el("code", { class: "invite-url" }, invite.url),
      invite.note ? el("div", { class: "muted small" }, invite.note) : null),
    el("td", {}, invite.run_id == null ? "all"
      : `${invite.run_id}${runs.has(invite.run_id) ? ` · ${runs.get(invite.run_id).task}` : ""}`),
    el("td", { class: "num" }, `${invite.uses}${invite.max_uses == null ? "" : ` / ${invite.max_uses}`}`),
    el("td", {}, `${invite.target_answers ?? "–"} · ${invite.completion_code ?? "–"}`,
      invite.redirect_url ? el("div", { class: "muted small" }, "redirects when done") : null,
      invite.consent_text ? el("div", { class: "muted small" }, "asks consent") : null,
      invite.entry_pass != null ? el("div", { class: "muted small entry-test" },
        `entry test: pass ${invite.entry_pass} practice`) : null,
      invite.entry_test_missing ? el("div", { class: "small error entry-test-missing" },
        `No entry test to take: ${invite.entry_test_missing}.`) : null),
    el("td", {}, until(invite.expires_at)),
    el("td", {}, el("span", { class: `badge ${invite.state === "open" ? "running" : "stopped"}`,
      title: invite.state === "closed" ? "its run is over: nobody can join" : null },
    invite.state.replace("_", " "))),
    el("td", { class: "actions" },
      el("a", { href: `/invites/${invite.id}/participants`, class: "small participants-link" },
        "Participants"), " ",
      el("button", { type: "button", class: "small", onclick: () => copy(invite) }, "Copy link"),
      invite.state === "revoked" ? null
        : el("button", { type: "button", class: "small", onclick: () => revoke(invite) }, "Revoke")),
  )));
}

function until(iso) {
  const seconds = (Date.parse(iso) - Date.now()) / 1000;
  if (seconds <= 0) return `expired ${ago(iso)}`;
  if (seconds < 5400) return `in ${Math.round(seconds / 60)} min`;
  if (seconds < 2 * 86400) return `in ${Math.round(seconds / 3600)} h`;
  return `in ${Math.round(seconds / 86400)} days`;
}

async function copy(invite) {
  try {
    await navigator.clipboard.writeText(invite.url);
    notify(`Link ${invite.id} copied.`);
  } catch {
    notify(`Copy it by hand: ${invite.url}`);
  }
}

async function revoke(invite) {
  if (!confirm(`Revoke link ${invite.id}? Nobody can join by it any more; those who did keep their access.`)) return;
  try {
    await post(`/api/invites/${invite.id}/revoke`);
    notify(`Link ${invite.id} revoked.`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`Link ${invite.id}: ${error.message}`, "error");
  }
  loadInvites();
}

function inviteBody(form) {
  const data = new FormData(form);
  const text = (name) => String(data.get(name) || "").trim();
  const body = {};
  for (const name of ["run_id", "expires_in_days", "max_uses", "target_answers", "wait_limit_s",
    "entry_pass"]) {
    if (text(name)) body[name] = Number(text(name));
  }
  for (const name of ["completion_code", "note", "redirect_url", "consent_text", "pause_message"]) {
    if (text(name)) body[name] = text(name);
  }
  return body;
}

async function createInvite(event) {
  event.preventDefault();
  const errors = document.getElementById("new-invite-errors");
  const result = document.getElementById("new-invite-result");
  errors.hidden = true;
  result.textContent = "";
  try {
    const invite = await post("/api/invites", inviteBody(event.target));
    result.replaceChildren("Created: ", el("code", {}, invite.url));
    loadInvites();
  } catch (error) {
    if (error instanceof SignedOut) return;
    listErrors(errors, error);
  }
}
