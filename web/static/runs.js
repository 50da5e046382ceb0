// The runs table (the newest runs, older ones on demand) and the workers panel (those heard from
// lately), refreshed every few seconds; the runs' controls; and the new-run form, which shows
// the preset's budget and clip length and when the first pairs come (GET /api/runs/defaults).

import { SignedOut, get, post, start } from "./api.js";
import { ago, el, lastReturn, listErrors, notify, num, poller, runActions } from "./dom.js";
import { loadInvites, startInvites } from "./invites.js";
import { loadLabellers } from "./labellers.js";

const PAGE = 100; // the newest runs the table shows; "Show older runs" adds as many again
let shown = PAGE;

const refresh = poller(async () => {
  try {
    // One more than shown: whether there are older ones. The workers: those heard from in the
    // last day (GET /api/workers?all=true lists every one that ever reported).
    const [page, workers] = await Promise.all([get(`/api/runs?limit=${shown + 1}`),
      get("/api/workers")]);
    const older = page.length > shown;
    render(older ? page.slice(1) : page, workers);
    document.getElementById("runs-more").hidden = !older;
    renderWorkers(workers);
    document.getElementById("updated").textContent =
      `updated ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    if (error instanceof SignedOut) return false;
    notify(`Could not load the runs: ${error.message}`, "error");
  }
  return true;
}, 5000);

/** Why a queued run waits, from the workers as last seen. */
function queuedWhy(workers) {
  const alive = workers.filter((w) => w.state === "training" || w.state === "idle");
  if (alive.length === 0) return "no worker is running: start one (sepoa worker)";
  if (alive.some((w) => w.state === "idle")) return "a free worker will claim it";
  return `waiting for a free worker (${alive.length} busy)`;
}

function renderWorkers(workers) {
  const body = document.getElementById("workers-body");
  if (workers.length === 0) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: 5, class: "muted" },
      "No worker has reported yet: start one with `sepoa worker` (sepoa up starts one).")));
    return;
  }
  body.replaceChildren(...workers.map((w) => el("tr", { "data-worker": w.id },
    el("td", { class: "name" }, w.id),
    el("td", {}, w.host || "–"),
    el("td", {}, w.run_id == null ? "–" : el("a", { href: `/runs/${w.run_id}` }, String(w.run_id))),
    el("td", {}, ago(w.last_seen_at)),
    el("td", {}, el("span", { class: `badge ${w.state}` }, w.state)),
  )));
}

function render(runs, workers) {
  const body = document.getElementById("runs-body");
  if (runs.length === 0) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: 10, class: "muted" },
      "No runs yet: create one below.")));
    return;
  }
  body.replaceChildren(...runs.slice().reverse().map((run) => el("tr", {},
    el("td", {}, el("a", { href: `/runs/${run.id}` }, String(run.id))),
    el("td", { class: "name" }, el("a", { href: `/runs/${run.id}` }, run.name)),
    el("td", {}, run.task),
    el("td", {}, run.algo),
    el("td", {}, teacherText(run)),
    el("td", {}, el("span", { class: `badge ${run.status}` }, run.status),
      run.status === "queued" ? el("span", { class: "why" }, queuedWhy(workers)) : null),
    el("td", { class: "num" }, num(run.step)),
    el("td", { class: "num" }, `${num(run.labels_used)} / ${num(run.budget)}`),
    el("td", { class: "num" }, num(lastReturn(run.progress), 4)),
    el("td", { class: "actions" }, runActions(run.status).map(([label, action, ask]) =>
      el("button", {
        type: "button",
        class: "small",
        onclick: () => control(run, label, action, ask),
      }, label))),
  )));
}

function teacherText(run) {
  // ε is set by the teacher parameters or by a config override; the API refuses both at once.
  const eps = run.teacher_params?.eps ?? run.config?.["teacher.eps"];
  if (run.teacher === "human") return "people";
  return eps != null ? `scripted ε=${eps}` : "scripted";
}

async function control(run, label, action, ask) {
  if (ask && !confirm(`${label} run ${run.id} (${run.name})?`)) return;
  try {
    await post(`/api/runs/${run.id}/${action}`);
    notify(`Run ${run.id}: ${label.toLowerCase()} done.`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`Run ${run.id}: ${error.message}`, "error");
  }
  refresh();
}

const QUALITY_FIELDS = ["practice_pairs", "gold_rate", "gold_min_accuracy", "labels_per_query"];

/** The form as the API's RunCreate body; throws a readable Error for bad JSON. */
function runBody(form) {
  const data = new FormData(form);
  const text = (name) => String(data.get(name) || "").trim();
  const number = (name) => (text(name) === "" ? null : Number(text(name)));
  let config = {};
  if (text("config")) {
    try {
      config = JSON.parse(text("config"));
    } catch (error) {
      throw new Error(`config: not valid JSON (${error.message})`);
    }
  }
  if (text("segment_length")) config["feedback.segment_length"] = number("segment_length");
  // The quality controls are config fields: the server checks them as any config value.
  for (const name of QUALITY_FIELDS) {
    if (text(name)) config[`feedback.${name}`] = number(name);
  }
  const body = {
    task: text("task"),
    algo: text("algo"),
    preset: text("preset"),
    seed: number("seed") ?? 0,
    teacher: text("teacher"),
    teacher_params: number("eps") == null ? {} : { eps: number("eps") },
    config,
  };
  if (text("budget")) body.budget = number("budget");
  if (text("name")) body.name = text("name");
  if (text("clip_size")) body.clip_size = text("clip_size");
  if (text("instruction")) body.instruction = text("instruction");
  return body;
}

async function createRun(event) {
  event.preventDefault();
  const form = event.target;
  const errors = document.getElementById("new-run-errors");
  const result = document.getElementById("new-run-result");
  errors.hidden = true;
  result.textContent = "";
  try {
    const run = await post("/api/runs", runBody(form));
    result.textContent = `Created run ${run.id} (${run.name}).`;
    form.elements.name.value = "";
    refresh();
    loadInvites();
  } catch (error) {
    if (error instanceof SignedOut) return;
    listErrors(errors, error);
  }
}

// ---- the form's defaults and estimates ------------------------------------------------------

let defaultsAsked = 0;

/** "45 s", "12 min", "1.5 h". */
function duration(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

/** The preset's budget and clip length as placeholders, and when the first pairs come. */
async function showDefaults() {
  const form = document.getElementById("new-run");
  const task = form.elements.task.value.trim();
  const timing = document.getElementById("timing-note");
  if (!task) {
    timing.textContent = "";
    return;
  }
  const asked = ++defaultsAsked;
  const params = new URLSearchParams({
    task, algo: form.elements.algo.value, preset: form.elements.preset.value,
  });
  let data;
  try {
    data = await get(`/api/runs/defaults?${params}`);
  } catch (error) {
    if (error instanceof SignedOut) return;
    if (asked === defaultsAsked) timing.textContent = ""; // an unknown task: the form says why
    return;
  }
  if (asked !== defaultsAsked) return; // a later choice answered first
  form.elements.budget.placeholder = `${data.budget} (the preset's)`;
  document.getElementById("budget-note").textContent =
    `${data.per_round} pairs a round; ${data.budget} answers in all unless you say otherwise`;
  form.elements.segment_length.placeholder = `${data.segment_length} (the preset's)`;
  showClipNote(data);
  const notes = [];
  if (data.pretrain_steps) {
    notes.push(`S-EPOA first pretrains skills for this task: ${num(data.pretrain_steps)} steps, `
      + `about ${duration(data.pretrain_seconds)} at ${num(data.pretrain_steps_per_s)} steps/s `
      + (data.pretrain_pace_measured ? "(this server's workers' last pace)"
        : "(the small preset's pace on 2 CPU cores)")
      + ", unless a snapshot of them exists already. Labellers wait meanwhile.");
  }
  if (data.first_round_steps) {
    notes.push(`The first pairs come after ${num(data.first_round_steps)} environment steps.`);
  }
  timing.textContent = notes.join(" ");
  timing.dataset.pretrain = data.pretrain_steps ? "yes" : "no";
  form.dataset.defaults = JSON.stringify(data);
}

/** The clip length in steps, as the label page plays it (1×) and in the task's own time. */
function showClipNote(data = JSON.parse(document.getElementById("new-run").dataset.defaults
  || "null")) {
  if (!data) return;
  const form = document.getElementById("new-run");
  const steps = Number(form.elements.segment_length.value) || data.segment_length;
  const perStep = data.clip_seconds / data.segment_length;
  const taskPerStep = data.task_seconds == null ? null : data.task_seconds / data.segment_length;
  document.getElementById("clip-note").textContent =
    `${steps} steps play in ${(steps * perStep).toFixed(1)} s on the label page at 1×`
    + (taskPerStep == null ? "" : ` (${(steps * taskPerStep).toFixed(2)} s of the task's time)`);
}

start(() => {
  document.getElementById("runs-more").addEventListener("click", () => {
    shown += PAGE;
    refresh();
  });
  const form = document.getElementById("new-run");
  for (const name of ["task", "algo", "preset"]) {
    form.elements[name].addEventListener("change", showDefaults);
  }
  form.elements.segment_length.addEventListener("input", () => showClipNote());
  form.addEventListener("submit", createRun);
  refresh();
  loadLabellers();
  startInvites();
});
