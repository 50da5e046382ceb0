// A study's participants, to pay from (operators): who joined, what they did, their code and
// whether it is earned (GET /api/invites/<id>/participants), the same as a CSV file, and many
// codes checked at once for this study (POST /api/invites/verify-codes with its invite_id).

import { SignedOut, download, get, post, start } from "./api.js";
import { el, notify } from "./dom.js";

const $ = (id) => document.getElementById(id);
const invite = document.body.dataset.invite;
const WHY = { target: "reached the target", runs_over: "run over", paused: "paused by checks",
  nothing_left: "nothing left to label", entry_failed: "failed the entry test" };

function minutes(seconds) {
  return seconds < 90 ? `${Math.round(seconds)} s` : `${Math.round(seconds / 60)} min`;
}

function row(p) {
  const answers = `${p.decisive + p.equal} decisive · ${p.cant_tell} can't tell · ${p.skips} skips`
    + (p.flags ? ` (${p.flags} flagged)` : "") + (p.practice ? ` · ${p.practice} practice` : "");
  const gold = p.gold_answers ? `${p.gold_correct}/${p.gold_answers}` : "–";
  const state = (p.active ? "" : "deactivated · ") + (p.why === "entry_failed"
    ? `let go: failed the entry test (${p.entry_correct} right): not to be paid`
    : (p.complete ? `complete: ${WHY[p.why] ?? p.why}` : p.paused ? "paused" : "labelling")
      + (p.entry_test === "passed" ? " · passed the entry test" : ""));
  return el("tr", { "data-valid": p.code_valid },
    el("th", { scope: "row" }, p.participant ?? p.labeller),
    el("td", {}, new Date(p.joined_at).toLocaleString()),
    el("td", { class: "num" }, minutes(p.time_on_task_s)),
    el("td", { class: "num" }, answers),
    el("td", { class: "num" }, gold),
    el("td", {}, state),
    el("td", {}, el("code", {}, p.completion_code), " ",
      el("span", { class: p.code_valid ? "badge ok" : "badge" },
        p.code_valid ? "earned" : p.complete || !p.active ? "not to be paid" : "not yet")));
}

async function load() {
  const people = await get(`/api/invites/${invite}/participants`);
  const earned = people.filter((p) => p.code_valid).length;
  $("summary").textContent = `${people.length} joined · ${earned} earned their code`;
  $("participants-body").replaceChildren(...(people.length ? people.map(row)
    : [el("tr", {}, el("td", { colspan: 7, class: "muted" }, "Nobody has joined yet."))]));
}

async function checkCodes(event) {
  event.preventDefault();
  const codes = $("codes").value.split(/\n/).map((c) => c.trim()).filter(Boolean);
  const checked = await post("/api/invites/verify-codes", { codes, invite_id: Number(invite) });
  $("codes-result").replaceChildren(...checked.map((c) => el("li", { "data-valid": c.valid },
    el("code", {}, c.code), " — ",
    c.valid ? `pay ${c.participant ?? `labeller ${c.labeller_id}`} (${WHY[c.why] ?? c.why})`
      : c.repeat ? `${c.participant ?? `labeller ${c.labeller_id}`}: given above, pay once`
        : c.why === "unknown" ? "nobody's code"
          : c.why === "other_study"
            ? `another study's code (invite ${c.invite_id}): not to be paid for this one`
            : c.why === "not_complete" ? `${c.participant ?? "?"}: not complete yet`
              : `${c.participant ?? "?"}: ${WHY[c.why] ?? c.why}, not to be paid`)));
}

function guard(task) {
  return (...args) => task(...args).catch((error) => {
    if (!(error instanceof SignedOut)) notify(error.message, "error");
  });
}

start(() => {
  $("csv").addEventListener("click", guard(() => download(
    `/api/invites/${invite}/participants?format=csv`, `invite-${invite}-participants.csv`)));
  $("codes-form").addEventListener("submit", guard(checkCodes));
  guard(load)();
});
