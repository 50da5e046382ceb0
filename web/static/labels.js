// The label browser (operators): stored labels, newest first, filtered by run, labeller,
// correctness against the hidden truth, flag and gold; a row opens its pair: both clips side by
// side as the labeller saw them, the answer, the scripted shadow label and the true returns.
// The filters live in the address (?run=3&flagged=true), so a view can be linked to.

import { SignedOut, get, start } from "./api.js";
import { ago, el, notify, num } from "./dom.js";

const $ = (id) => document.getElementById(id);
const FILTERS = ["run_id", "labeller_id", "correct", "flagged", "gold", "withdrawn"];
const ALIASES = { run: "run_id", labeller: "labeller_id" }; // short names in the address
const FLAG_TEXT = { clip_broken: "clip broken", not_visible: "agent not visible", other: "other" };
const SEGMENT = { first: "first", second: "second", equal: "equal", cant_tell: "can't tell", skip: "skip" };
let nextBefore = null;

/** The filters as query parameters, from the form. */
function params() {
  const form = $("filters");
  const out = new URLSearchParams();
  for (const name of FILTERS) {
    const field = form.elements[name];
    const value = field.type === "checkbox" ? (field.checked ? "true" : "") : field.value;
    if (value) out.set(name, value);
  }
  return out;
}

/** The form from the address: ?run=3 (or run_id=3), labeller=, correct=, flagged=, gold=. */
function readAddress() {
  const query = new URLSearchParams(location.search);
  for (const [key, value] of query) {
    const field = $("filters").elements[ALIASES[key] ?? key];
    if (!field) continue;
    if (field.type === "checkbox") field.checked = value === "true";
    else {
      if (field.tagName === "SELECT" && ![...field.options].some((o) => o.value === value)) {
        field.append(el("option", { value }, `#${value}`)); // not listed (yet): still filter on it
      }
      field.value = value;
    }
  }
}

/** "left (first)": what was clicked, and the segment it names. */
function answerText(label) {
  if (label.choice === "left" || label.choice === "right") {
    return `${label.choice} (${label.answer})`;
  }
  return SEGMENT[label.answer] ?? label.answer;
}

function truthCell(label) {
  if (label.correct == null) return el("td", { class: "muted" }, "–");
  return el("td", { class: label.correct ? "ok" : "bad", "data-correct": String(label.correct) },
    label.correct ? "correct" : "incorrect");
}

function row(label) {
  const tr = el("tr", {
    tabindex: "0", "data-label-id": label.label_id, class: label.withdrawn ? "withdrawn" : null,
    onclick: () => openLabel(label.label_id),
    onkeydown: (event) => { if (event.key === "Enter") openLabel(label.label_id); },
  },
  el("td", { class: "num" }, String(label.label_id)),
  el("td", {}, el("a", { href: `/runs/${label.run_id}` }, `${label.run_id} ${label.run_name}`)),
  el("td", {}, label.labeller_name),
  el("td", {}, answerText(label), label.withdrawn ? el("span", { class: "muted small" }, " taken back") : null),
  truthCell(label),
  el("td", {}, label.shadow_choice ? SEGMENT[label.shadow_choice] : "–"),
  el("td", {}, label.flag ? FLAG_TEXT[label.flag] ?? label.flag : ""),
  el("td", {}, label.gold ? "gold" : ""),
  el("td", {}, ago(label.answered_at)));
  return tr;
}

async function load(append = false) {
  const query = params();
  if (append && nextBefore) query.set("before", nextBefore);
  history.replaceState(null, "", `/labels${[...params()].length ? `?${params()}` : ""}`);
  try {
    const page = await get(`/api/labels?${query}`);
    const body = $("labels-body");
    const rows = page.labels.map(row);
    if (append) body.append(...rows);
    else body.replaceChildren(...(rows.length ? rows
      : [el("tr", {}, el("td", { colspan: "9", class: "muted" }, "No label matches."))]));
    nextBefore = page.next_before;
    $("more").hidden = nextBefore == null;
    $("matching").textContent = `${num(page.matching)} label${page.matching === 1 ? "" : "s"} match`;
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(error.message, "error");
  }
}

function fact(term, ...value) {
  return [el("dt", {}, term), el("dd", {}, ...value)];
}

/** One label: its clips on the sides the labeller saw, and everything the truth says. */
async function openLabel(id) {
  let view;
  try {
    view = await get(`/api/labels/${id}`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(error.message, "error");
    return;
  }
  const label = view.label;
  const [leftSide, rightSide] = label.left_is_first ? ["first", "second"] : ["second", "first"];
  const start = (side) => (side === "first" ? view.first_start : view.second_start);
  const ret = (side) => (side === "first" ? view.first_segment_return : view.second_segment_return);
  $("detail-title").textContent = `Label ${label.label_id} · pair ${label.query_id} · run ${label.run_id}`;
  for (const [where, side] of [["left", leftSide], ["right", rightSide]]) {
    $(`${where}-caption`).textContent =
      `${where === "left" ? "Left" : "Right"}: ${side} segment, steps ${start(side)}–${start(side) + view.segment_length - 1}, true return ${num(ret(side), 4)}`;
    const video = $(`${where}-video`);
    const url = view[`${side}_clip_url`];
    video.hidden = !url;
    if (url) video.src = url;
    else video.removeAttribute("src");
  }
  $("no-clips").hidden = view.has_clips;
  const facts = [
    ...fact("Labeller", label.labeller_name),
    ...fact("Answer", answerText(label), label.withdrawn ? " (taken back)" : ""),
    ...fact("True answer", view.true_answer ? SEGMENT[view.true_answer] : "–",
      label.correct == null ? "" : label.correct ? " · the answer is correct" : " · the answer is incorrect"),
    ...fact("Shadow label", label.shadow_choice ? SEGMENT[label.shadow_choice] : "–",
      el("span", { class: "muted small" }, " (the scripted teacher's hidden answer)")),
    ...fact("True segment returns", `first ${num(view.first_segment_return, 4)} · second ${num(view.second_segment_return, 4)}`),
    ...fact("Model P(second)", view.model_p == null ? "–" : num(view.model_p, 3)),
    ...fact("Gold pair", label.gold ? "yes" : "no"),
    ...fact("Round", String(view.round)),
    ...fact("Answered", new Date(label.answered_at).toLocaleString(),
      view.shown_at ? ` (shown ${((Date.parse(label.answered_at) - Date.parse(view.shown_at)) / 1000).toFixed(1)} s before)` : ""),
  ];
  if (label.flag) {
    facts.push(...fact("Flag", FLAG_TEXT[label.flag] ?? label.flag, label.flag_note ? [": ", el("q", {}, label.flag_note)] : ""));
  }
  $("detail-facts").replaceChildren(...facts);
  $("detail").hidden = false;
  $("detail").dataset.labelId = String(label.label_id);
  $("detail").scrollIntoView({ block: "nearest" });
}

async function fillChoices() {
  const [runs, labellers] = await Promise.all([get("/api/runs"), get("/api/labellers")]);
  const runSelect = $("filter-run");
  for (const run of runs) runSelect.append(el("option", { value: run.id }, `${run.id} ${run.name}`));
  const who = $("filter-labeller");
  for (const labeller of labellers) who.append(el("option", { value: labeller.id }, labeller.name));
}

start(async () => {
  try {
    await fillChoices();
  } catch (error) {
    if (error instanceof SignedOut) return;
    notify(error.message, "error");
  }
  readAddress();
  $("filters").addEventListener("change", () => load());
  $("more").addEventListener("click", () => load(true));
  $("detail-close").addEventListener("click", () => {
    $("detail").hidden = true;
    for (const where of ["left", "right"]) $(`${where}-video`).pause();
  });
  await load();
});
