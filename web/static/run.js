// One run: status and controls, teacher switch, label export, the configuration it trains
// with, learning curves and label throughput; all of it but the configuration (read at the
// start and after a teacher switch) refreshed every 5 s while the tab is visible.

import { SignedOut, download, get, getBlob, post, request, start } from "./api.js";
import { drawChart } from "./chart.js";
import { ago, el, notify, num, poller, runActions } from "./dom.js";
import { showInstruction, startInstructionForm } from "./instruction_form.js";

const runId = Number(document.body.dataset.runId);
// Throughput buckets: the smallest of these that cuts the run's lifetime into at most 120 bars.
const BUCKETS_S = [60, 300, 900, 3600, 3 * 3600, 6 * 3600, 86_400];
const MIN_SPAN_MS = 30 * 60_000; // the throughput chart shows at least the last half hour

const refresh = poller(async () => {
  try {
    const run = await get(`/api/runs/${runId}`);
    const bucket = bucketFor(run);
    const [activity, [episodes, evals, rounds], throughput, flags] = await Promise.all([
      get(`/api/runs/${runId}/activity`),
      readMetrics(run),
      get(`/api/runs/${runId}/throughput?bucket_s=${bucket}`),
      get(`/api/runs/${runId}/flags`),
    ]);
    document.getElementById("loading").hidden = true;
    document.getElementById("run-body").hidden = false; // before drawing: charts fit its width
    showRun(run);
    showActivity(activity); // with the facts it explains, in one paint
    drawCurves(run, episodes, evals, rounds);
    drawThroughput(throughput, run);
    showFlags(flags);
    await drawPeers(run, evals);
    await drawCalibration(run);
    document.getElementById("updated").textContent =
      `updated ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    if (error instanceof SignedOut) return false;
    if (error.status === 404 || error.status === 422) {
      document.getElementById("loading").hidden = true;
      notify(`${error.message}.`, "error", 3600);
      return false; // no such run (or an id no run can have: /runs/-5): nothing to refresh
    }
    notify(`Could not refresh: ${error.message}`, "error");
  }
  return true;
}, 5000);

// The run's three curves, kept here by step and asked for only past what the page has
// (`after_step`): a run of many episodes would send them all every 5 s otherwise. A resumed run
// rewrites the steps after its checkpoint, which may be steps the page has: so the page asks
// from the step the run had reached at its last refresh when that is lower (it is, after a
// resume), and a step sent again replaces the one kept.
const STREAMS = ["episodes", "eval", "rounds"];
const curves = Object.fromEntries(STREAMS.map((stream) => [stream, new Map()]));
const lastStep = Object.fromEntries(STREAMS.map((stream) => [stream, -1]));
let stepBefore = null; // the run's step as the previous refresh read it

async function readMetrics(run) {
  const fresh = await Promise.all(STREAMS.map((stream) => {
    const after = Math.min(lastStep[stream], stepBefore ?? Infinity);
    const since = after >= 0 ? `&after_step=${after}` : "";
    return get(`/api/runs/${runId}/metrics?stream=${stream}${since}`);
  }));
  stepBefore = Math.max(0, run.step - 1); // a row of that very step may come after this read
  return STREAMS.map((stream, i) => {
    const kept = curves[stream];
    for (const row of fresh[i]) {
      kept.set(row.step, row);
      lastStep[stream] = Math.max(lastStep[stream], row.step);
    }
    return [...kept.values()].sort((a, b) => a.step - b.step);
  });
}

// The report's figure (the run beside its peers), drawn by the server; redrawn only when this
// run has a new evaluation, as drawing it costs the server a fraction of a second.
let peersDrawnFor = null;
async function drawPeers(run, evals) {
  const metric = run.task.startsWith("metaworld:") ? "success_rate" : "return";
  const key = `${evals.length}:${metric}`;
  if (key === peersDrawnFor) return;
  const blob = await getBlob(`/api/runs/${runId}/curves.png?metric=${metric}`);
  const img = document.getElementById("peers-img");
  const old = img.src;
  img.src = URL.createObjectURL(blob);
  if (old.startsWith("blob:")) URL.revokeObjectURL(old);
  img.hidden = false;
  peersDrawnFor = key;
}

// The teacher-calibration figure (docs/QUALITY.md), drawn by the server; asked again only when
// the run has new answers.
let calibrationDrawnFor = null;
async function drawCalibration(run) {
  if (run.labels_used === calibrationDrawnFor) return;
  const blob = await getBlob(`/api/quality/calibration.png?run_id=${runId}`);
  const img = document.getElementById("calibration-img");
  const old = img.src;
  img.src = URL.createObjectURL(blob);
  if (old.startsWith("blob:")) URL.revokeObjectURL(old);
  img.hidden = false;
  calibrationDrawnFor = run.labels_used;
}

/** People teach a run with a scripted shadow teacher beside them; its ε is the shadow's. */
const FLAG_TEXT = { clip_broken: "clip broken", not_visible: "agent not visible", other: "other" };

/** The run's flagged pairs: how many of each, and the latest with who and their note. */
function showFlags(flags) {
  const facts = [el("dt", {}, "Flagged answers"), el("dd", {}, num(flags.total),
    flags.total ? ` on ${num(flags.queries)} pair${flags.queries === 1 ? "" : "s"}` : "")];
  for (const [flag, count] of Object.entries(flags.by_flag)) {
    facts.push(el("dt", {}, FLAG_TEXT[flag] ?? flag), el("dd", { "data-flag": flag }, num(count)));
  }
  document.getElementById("flag-facts").replaceChildren(...facts);
  document.getElementById("flag-latest").replaceChildren(...flags.latest.map((f) => el("li", {},
    `pair ${f.query_id}: ${FLAG_TEXT[f.flag] ?? f.flag} (${f.labeller_name}, ${ago(f.answered_at)})`,
    f.note ? [": ", el("q", {}, f.note)] : null)));
}

/** What the run trains with, every field, those the run sets itself marked. */
async function showConfig() {
  let config;
  try {
    config = await get(`/api/runs/${runId}/config`);
  } catch (error) {
    if (!(error instanceof SignedOut)) {
      document.getElementById("config-summary").textContent = error.message;
    }
    return;
  }
  const own = new Set(config.overridden);
  document.getElementById("config-summary").textContent = own.size
    ? `set by this run: ${config.overridden.join(", ")}` : "presets and defaults only";
  document.getElementById("config-note").textContent = config.stored
    ? "Stored when the run was created: a preset changed since does not change it."
    : "Stored before configurations were kept: its worker resolves it against today's presets, as shown.";
  document.getElementById("config-rows").replaceChildren(
    ...Object.entries(config.values).map(([path, value]) => {
      const text = Array.isArray(value) ? value.join(", ") : String(value);
      return el("tr", own.has(path) ? { "data-own": true } : {},
        el("td", {}, own.has(path) ? el("mark", {}, path) : path), el("td", {}, text));
    }));
}

// The statuses in which a run's teacher may change (labelqueue.TEACHABLE): a run that ended,
// or is ending, keeps the teacher it trained with (PUT /teacher is a 409).
const TEACHABLE = ["queued", "running", "paused"];

/** The run's teacher ε as set: by the teacher parameters or by a config override (a run holds
 * it once: a new run may not give both, and a switch's parameters replace the config's). */
const epsOf = (run) => run.teacher_params?.eps ?? run.config?.["teacher.eps"];

function teacherText(run) {
  const eps = epsOf(run);
  if (run.teacher === "human") {
    return `people${eps != null ? ` (scripted shadow teacher ε=${eps})` : ""}`;
  }
  return `scripted${eps != null ? ` (ε=${eps})` : ""}`;
}

const PHASES = {
  queued: "Queued:", starting: "Starting:", pretraining: "Pretraining:",
  labelling: "Waiting for answers:", exploring: "Exploring:", training: "Training:",
  paused: "Paused:", stopping: "Stopping:", silent: "Worker silent:",
};

/** The line under the title: what the run does or waits for, and why. */
function showActivity(activity) {
  const line = document.getElementById("run-activity");
  const phase = PHASES[activity.phase];
  line.hidden = !phase;
  if (!phase) return;
  line.dataset.phase = activity.phase;
  document.getElementById("activity-phase").textContent = phase;
  document.getElementById("activity-text").textContent = activity.text;
}

function bucketFor(run) {
  const spanS = (Date.now() - Date.parse(run.created_at)) / 1000;
  return BUCKETS_S.find((b) => spanS / b <= 120) ?? BUCKETS_S.at(-1);
}

function showRun(run) {
  document.title = `${run.name} · S-EPOA`;
  document.getElementById("run-title").textContent = `${run.id} · ${run.name}`;
  const badge = document.getElementById("run-status");
  badge.textContent = run.status;
  badge.className = `badge ${run.status}`;
  const facts = [
    ["Task", run.task], ["Algorithm", run.algo], ["Preset", run.preset], ["Seed", run.seed],
    ["Teacher", teacherText(run)],
    ["Step", num(run.step)], ["Labels", `${num(run.labels_used)} / ${num(run.budget)}`],
    ["Last return", `${num(run.progress?.last_return, 4)} (episode) · `
      + `${num(run.progress?.eval_return, 4)} (evaluation)`],
    ["Round", num(run.progress?.round)],
    ["Worker", run.worker_id || "–"], ["Heartbeat", ago(run.heartbeat_at)],
    ["Created", ago(run.created_at)], ["Finished", ago(run.finished_at)],
  ];
  document.getElementById("run-facts").replaceChildren(
    ...facts.flatMap(([name, value]) => [el("dt", {}, name), el("dd", {}, String(value))]));
  const error = document.getElementById("run-error");
  error.textContent = run.error || "";
  error.hidden = !run.error;
  document.getElementById("controls").replaceChildren(
    ...runActions(run.status).map(([label, action, ask]) => el("button", {
      type: "button",
      onclick: () => control(run, label, action, ask),
    }, label)));
  showInstruction(run);
  const form = document.getElementById("teacher-form");
  const teachable = TEACHABLE.includes(run.status);
  form.hidden = !teachable;
  const closed = document.getElementById("teacher-closed");
  closed.hidden = teachable;
  closed.textContent = teachable ? ""
    : `This run is ${run.status}: it keeps the teacher it trained with, ${teacherText(run)}.`;
  if (!form.contains(document.activeElement)) { // leave what the operator is typing alone
    form.elements.teacher.value = run.teacher;
    form.elements.eps.value = epsOf(run) ?? "";
  }
}

async function control(run, label, action, ask) {
  if (ask && !confirm(`${label} run ${run.id} (${run.name})?`)) return;
  try {
    await post(`/api/runs/${run.id}/${action}`);
    notify(`${label}: done.`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`${label}: ${error.message}`, "error");
  }
  refresh();
}

async function switchTeacher(event) {
  event.preventDefault();
  const form = event.target;
  const eps = form.elements.eps.value.trim();
  const body = { teacher: form.elements.teacher.value, params: eps === "" ? {} : { eps: Number(eps) } };
  try {
    await request("PUT", `/api/runs/${runId}/teacher`, body);
    notify(`Teacher: ${body.teacher}${eps === "" ? "" : ` (ε=${eps})`}.`);
    document.activeElement.blur();
    showConfig();
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`Teacher: ${error.message}`, "error");
  }
  refresh();
}

async function exportLabels(format) {
  try {
    await download(`/api/export?format=${format}&run_id=${runId}`, `run-${runId}-labels.${format}`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`Export (${format}): ${error.message}`, "error");
  }
}

/** [[x, y]] of one metric key; x is the step, or the round number for per-round series. */
const points = (rows, key, x = (row) => row.step) =>
  rows.map((row, i) => [x(row, i), row.values[key]]).filter(([, y]) => typeof y === "number");
const roundOf = (row, i) => row.values.round ?? i;

function drawCurves(run, episodes, evals, rounds) {
  const chart = (id) => document.getElementById(id);
  drawChart(chart("chart-return"), {
    title: "True return", xLabel: "step", yLabel: "return",
    series: [
      { name: "evaluation", points: points(evals, "return") },
      { name: "training episodes", points: points(episodes, "return"), width: 1 },
    ],
  });
  const used = new Map();
  for (const row of [...episodes, ...evals, ...rounds]) {
    if (typeof row.values.labels_used === "number") used.set(row.step, row.values.labels_used);
  }
  const usedPoints = [...used].sort((a, b) => a[0] - b[0]);
  const steps = usedPoints.map(([x]) => x);
  drawChart(chart("chart-labels"), {
    title: "Labels used", xLabel: "step", yLabel: "labels", yMin: 0,
    series: [
      { name: "labels used", points: usedPoints },
      { name: "budget", color: "#adb5bd", width: 1, points: steps.length
        ? [[Math.min(...steps), run.budget], [Math.max(...steps), run.budget]] : [] },
    ],
  });
  drawChart(chart("chart-distinguishable"), {
    title: "Distinguishable pairs per round", xLabel: "round", xInteger: true, yLabel: "ratio", yMin: 0, yMax: 1,
    series: [{ name: "", points: points(rounds, "distinguishable_ratio", roundOf) }],
  });
  drawChart(chart("chart-agreement"), {
    title: "Agreement per round", xLabel: "round", xInteger: true, yLabel: "fraction", yMin: 0, yMax: 1,
    series: [
      { name: "reward model vs shadow label", points: points(rounds, "model_agreement", roundOf) },
      { name: "given labels vs shadow label", points: points(rounds, "shadow_agreement", roundOf) },
      { name: "teacher vs ground truth", points: points(rounds, "teacher_accuracy", roundOf) },
    ],
  });
  drawChart(chart("chart-reward-corr"), {
    title: "Learned reward vs true reward", xLabel: "round", xInteger: true, yLabel: "correlation",
    note: "over the replay buffer, after each round", yMin: -1, yMax: 1,
    series: [{ name: "", points: points(rounds, "reward_corr", roundOf) }],
  });
}

function drawThroughput(stats, run) {
  const sources = Object.entries(stats.by_source).filter(([, n]) => n > 0)
    .map(([source, n]) => `${num(n)} ${source}`).join(", ");
  const median = stats.median_answer_s == null ? "–" : `${num(stats.median_answer_s, 3)} s`;
  const bars = stats.buckets.map((b) => [Date.parse(b.t), (b.labels * 60) / stats.bucket_s]);
  const end = run.finished_at ? Date.parse(run.finished_at) : Date.now();
  drawChart(document.getElementById("chart-throughput"), {
    title: "Label throughput",
    note: `${num(stats.total)} label${stats.total === 1 ? "" : "s"}${sources ? ` (${sources})` : ""}`
      + ` · median answer time ${median} · ${stats.bucket_s / 60}-minute bars`,
    xLabel: "time", yLabel: "labels / min", time: true,
    xMin: Math.min(end - MIN_SPAN_MS, ...bars.map(([t]) => t)),
    xMax: Math.max(end, ...bars.map(([t]) => t + stats.bucket_s * 1000)),
    series: [{ name: "", kind: "bars", barWidth: stats.bucket_s * 1000, points: bars }],
  });
}

start(() => {
  document.getElementById("teacher-form").addEventListener("submit", switchTeacher);
  startInstructionForm(runId, refresh);
  showConfig();
  for (const button of document.querySelectorAll("[data-export]")) {
    button.addEventListener("click", () => exportLabels(button.dataset.export));
  }
  refresh();
});
