// The runs table (refreshed every few seconds), its controls, and the new-run form.

import { SignedOut, get, post, start } from "./api.js";
import { el, lastReturn, listErrors, notify, num, poller, runActions } from "./dom.js";
import { loadInvites, startInvites } from "./invites.js";
import { loadLabellers } from "./labellers.js";

const refresh = poller(async () => {
  try {
    render(await get("/api/runs"));
    document.getElementById("updated").textContent =
      `updated ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    if (error instanceof SignedOut) return false;
    notify(`Could not load the runs: ${error.message}`, "error");
  }
  return true;
}, 5000);

function render(runs) {
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
    el("td", {}, el("span", { class: `badge ${run.status}` }, run.status)),
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
  const eps = run.teacher_params?.eps;
  return run.teacher === "scripted" && eps != null ? `scripted ε=${eps}` : run.teacher;
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
  const body = {
    task: text("task"),
    algo: text("algo"),
    budget: number("budget"),
    preset: text("preset"),
    seed: number("seed") ?? 0,
    teacher: text("teacher"),
    teacher_params: number("eps") == null ? {} : { eps: number("eps") },
    config,
  };
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

start(() => {
  document.getElementById("new-run").addEventListener("submit", createRun);
  refresh();
  loadLabellers();
  startInvites();
});
