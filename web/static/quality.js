// Label quality (docs/QUALITY.md): each labeller's reliability on the runs page, for all runs or
// one (`?quality_run=<id>` chooses it), with the gold-threshold pauses an operator can lift; and
// the run page's "Agreement" card (pairwise agreement, Fleiss' κ, per round).
//
// The runs page starts the table through labellers.js; on the run page this module starts its
// card itself, after run.js has read the token (module scripts run in document order).

import { SignedOut, get, request } from "./api.js";
import { el, notify, poller } from "./dom.js";

const REFRESH_MS = 30_000; // quality is worked out from every label row: not every 5 s
const BIAS_P = 0.01; // a left share this unlikely under 0.5 is flagged as position bias
const DASH = "—";

/** 0.923 → "0.92"; null → "—". */
export function fixed(value, digits = 2) {
  return value == null || Number.isNaN(value) ? DASH : Number(value).toFixed(digits);
}

/** A share {k, n, rate, low, high} as "0.92 [0.81, 0.97]" (the interval kept on one line, so
 * that a narrow column breaks before it); "—" with no n. */
function shareText(share) {
  if (!share || share.rate == null) return DASH;
  if (share.low == null) return fixed(share.rate);
  return [`${fixed(share.rate)} `,
    el("span", { class: "interval" }, `[${fixed(share.low)}, ${fixed(share.high)}]`)];
}

function pValue(p) {
  if (p == null) return DASH;
  return p < 0.001 ? "p < 0.001" : `p = ${fixed(p, 3)}`;
}

function seconds(s) {
  return s == null ? DASH : s < 100 ? `${fixed(s, 1)} s` : `${Math.round(s)} s`;
}

function shareCell(share) {
  return el("td", { class: "num", title: share && share.n ? `${share.k} of ${share.n}` : null },
    shareText(share),
    share && share.n ? el("span", { class: "muted small of" }, ` ${share.k}/${share.n}`) : null);
}

/** The practice round's answers: "2/3 right", "–" for none. */
function practiceCell(share) {
  return el("td", { class: "num practice" }, share && share.n ? `${share.k}/${share.n} right` : "–");
}

// ---- the labellers' quality table (runs page) -----------------------------------------------

let chosenRun = null; // null: all runs
let refreshQuality = null;

/** Starts the quality table of the runs page (once); later calls refresh it. */
export function startQuality() {
  if (refreshQuality) {
    refreshQuality();
    return;
  }
  const select = document.getElementById("quality-run");
  const wanted = new URLSearchParams(location.search).get("quality_run");
  chosenRun = wanted && /^\d+$/.test(wanted) ? Number(wanted) : null;
  select.addEventListener("change", () => {
    chosenRun = select.value ? Number(select.value) : null;
    const url = new URL(location.href);
    if (chosenRun == null) url.searchParams.delete("quality_run");
    else url.searchParams.set("quality_run", chosenRun);
    history.replaceState(null, "", url);
    refreshQuality();
  });
  refreshQuality = poller(loadQuality, REFRESH_MS);
  refreshQuality();
}

async function loadQuality() {
  try {
    const query = chosenRun == null ? "" : `?run_id=${chosenRun}`;
    const [runs, rows] = await Promise.all([get("/api/runs"), get(`/api/quality/labellers${query}`)]);
    fillRuns(runs);
    renderQuality(rows);
  } catch (error) {
    if (error instanceof SignedOut) return false;
    const body = document.getElementById("quality-body");
    body.replaceChildren(el("tr", {}, el("td", { colspan: 13, class: "error" },
      `Could not load the labellers' quality: ${error.message}`)));
  }
  return true;
}

function fillRuns(runs) {
  const select = document.getElementById("quality-run");
  const options = [el("option", { value: "" }, "all runs"),
    ...runs.slice().reverse().map((run) =>
      el("option", { value: String(run.id) }, `${run.id} · ${run.name}`))];
  if (chosenRun != null && !runs.some((run) => run.id === chosenRun)) {
    options.push(el("option", { value: String(chosenRun) }, `${chosenRun} (unknown)`));
  }
  select.replaceChildren(...options);
  select.value = chosenRun == null ? "" : String(chosenRun);
  document.getElementById("quality-caption").textContent = chosenRun == null
    ? "Each labeller's answers on all runs"
    : `Each labeller's answers on run ${chosenRun}`;
}

function renderQuality(rows) {
  const body = document.getElementById("quality-body");
  if (rows.length === 0) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: 13, class: "muted" },
      chosenRun == null ? "No answers yet." : `No answers on run ${chosenRun} yet.`)));
    return;
  }
  body.replaceChildren(...rows.map((who) => {
    const biased = who.left_p_value != null && who.left_p_value < BIAS_P;
    return el("tr", { "data-labeller": who.labeller_name },
      el("th", { scope: "row", class: "name" }, who.labeller_name),
      el("td", { class: "num answer-count" }, String(who.answers)),
      el("td", { class: "num" }, fixed(who.answers_per_hour, 1)),
      el("td", { class: "num" }, seconds(who.median_answer_s)),
      shareCell(who.accuracy),
      shareCell(who.shadow_agreement),
      shareCell(who.gold_accuracy),
      practiceCell(who.practice),
      shareCell(who.cant_tell),
      shareCell(who.skips),
      el("td", { class: "num left-share" }, shareText(who.left), " ",
        el("span", { class: "muted small" }, pValue(who.left_p_value)),
        biased ? el("span", { class: "badge bias", title: `left share differs from 0.5, p < ${BIAS_P}` },
          "position bias") : null),
      el("td", { class: "num agreement" }, fixed(who.agreement_with_others),
        who.shared_queries ? el("span", { class: "muted small of" },
          ` on ${who.shared_queries} shared`) : null),
      el("td", { class: "actions" }, who.paused ? [
        el("span", { class: "badge paused" }, "paused"), " ",
        el("button", { type: "button", class: "small", onclick: () => liftPause(who) }, "Let go on"),
      ] : null));
  }));
}

async function liftPause(who) {
  if (chosenRun == null) return;
  if (!confirm(`Let ${who.labeller_name} answer run ${chosenRun}'s pairs again?`)) return;
  try {
    await request("DELETE", `/api/quality/runs/${chosenRun}/pauses/${who.labeller_id}`);
    notify(`${who.labeller_name} may answer run ${chosenRun} again.`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`${who.labeller_name}: ${error.message}`, "error");
  }
  refreshQuality();
}

// ---- the run page's agreement card -----------------------------------------------------------

async function loadAgreement(runId) {
  try {
    showAgreement(await get(`/api/quality/agreement?run_id=${runId}`));
  } catch (error) {
    if (error instanceof SignedOut) return false;
    // No such run (404), or an id no run can have (422, /runs/-5): run.js says so; asking again
    // changes nothing.
    if (error.status === 404 || error.status === 422) return false;
    document.getElementById("agreement-facts").replaceChildren(
      el("dt", {}, "Error"), el("dd", { class: "error" }, error.message));
  }
  return true;
}

function showAgreement(report) {
  const all = report.everyone;
  const facts = [
    ["Pairwise agreement", fixed(all.pairwise_agreement)],
    ["Fleiss' κ", fixed(all.fleiss_kappa)],
    ["Queries with ≥ 2 answers", String(all.queries)],
    ["Their answers", String(all.answers)],
  ];
  document.getElementById("agreement-facts").replaceChildren(
    ...facts.flatMap(([name, value]) => [el("dt", {}, name), el("dd", {}, value)]));
  const body = document.getElementById("agreement-rounds");
  body.replaceChildren(...(report.rounds.length === 0
    ? [el("tr", {}, el("td", { colspan: 4, class: "muted" },
      "No query has two answers yet (feedback.labels_per_query above 1, or gold pairs)."))]
    : report.rounds.map((round) => el("tr", {},
      el("th", { scope: "row", class: "num" }, String(round.round)),
      el("td", { class: "num" }, String(round.queries)),
      el("td", { class: "num" }, fixed(round.pairwise_agreement)),
      el("td", { class: "num" }, fixed(round.fleiss_kappa))))));
}

const card = document.getElementById("agreement-card");
if (card) {
  const runId = Number(document.body.dataset.runId);
  poller(() => loadAgreement(runId), REFRESH_MS)();
}
