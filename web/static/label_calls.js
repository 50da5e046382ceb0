// The label page's calls to the label API, run one at a time and in order, so an answer is
// stored before the next preload asks the server what this labeller holds: leasing the pair to
// show, preloading (and renewing) the next one with `ahead_of`, polling while there is nothing
// to label, and the labeller's progress. A call that got no answer, or a failing or busy
// server's, is shown and asked again; a refusal that stands (an unknown run, one taught by a
// script) is shown for good and, as a refused token or a pause does, stops them all.

import { ApiError, Paused, SignedOut, request } from "./api.js";
import { explainPause, explainWait, showProgress, study } from "./study.js";
import { noteServerClock, state } from "./label_state.js";
import { notice, showCounts, showStopped, showWaiting, updateButtons } from "./label_screen.js";
import { Pair, show } from "./label_pair.js";

export const POLL_MS = 2000; // nothing to label, or nothing preloaded yet: ask again this often
export const RENEW_MS = 30_000; // both pairs in hand: renew their leases (120 s) this often
const RETRY_MS = 5000; // after a failed request

const $ = (id) => document.getElementById(id);

/** Runs `task` after every call before it; its promise is the task's. */
export function serial(task) {
  const run = state.chain.then(task);
  state.chain = run.catch(() => {});
  return run;
}

/** Runs `task` in turn; a passing failure is shown and the task retried, one that stands (or
 * a refused token, or a pause) stops everything. */
export async function attempt(task) {
  try {
    await task();
  } catch (error) {
    if (error instanceof ApiError && error.transient) {
      notice(`${error.message} (retrying)`, "error");
      schedule(task, RETRY_MS);
      return;
    }
    stopLabelling();
    if (error instanceof SignedOut) return;
    showStopped(error.message);
    // One who joined by an invite: the study's end, with their code or the operator's word.
    if (error instanceof Paused && await explainPause().catch(() => false)) {
      $("notice").hidden = true;
    }
  }
}

/** No more pairs: the loops stop and the pairs in hand are let go (their leases run out). The
 * last answer is no longer offered back: its pair would have nowhere to be shown. Keys do
 * nothing until labelling resumes (past a study's target, by choice). */
function stopLabelling() {
  clearTimeout(state.timer);
  state.stopped = true;
  state.submitting = false;
  state.last = null;
  $("undo").hidden = true;
  state.next?.remove();
  state.current?.remove();
  state.current = state.next = null;
  updateButtons();
  if ($("flag-dialog").open) $("flag-dialog").close(); // its pair is gone
}

export function schedule(task, ms) {
  clearTimeout(state.timer);
  state.timer = setTimeout(() => serial(() => attempt(task)), ms);
}

export async function fetchNext(aheadOf) {
  const params = new URLSearchParams();
  if (state.runId) params.set("run_id", state.runId);
  if (aheadOf != null) params.set("ahead_of", aheadOf);
  const { data, response } = await request("GET", `/api/label/next?${params}`);
  noteServerClock(response);
  if (data) data.brief = await runBrief(data.run_id);
  return data; // null: nothing to label (204)
}

/** The run's instruction and clip timing, asked once per run and page (a reload asks again). */
export async function runBrief(id) {
  if (!state.briefs.has(id)) {
    const { data } = await request("GET", `/api/label/runs/${id}`);
    state.briefs.set(id, data);
  }
  return state.briefs.get(id);
}

/** Nothing on screen: lease a pair and show it, or wait and ask again. */
export async function loadCurrent() {
  if (study.complete || state.stopped || state.submitting) return; // an undo asks again later
  const query = await fetchNext(null);
  if (!query) {
    showWaiting();
    if (await explainWait(state.runId)) { // the study is complete: nothing more to ask for
      stopLabelling();
      return;
    }
    schedule(loadCurrent, POLL_MS);
    return;
  }
  show(new Pair(query, query.brief));
  await preload();
}

/** A pair on screen: keep its lease and lease (or renew) the next one, loaded hidden. */
export async function preload() {
  const shown = state.current;
  if (!shown || state.submitting || study.complete) return; // the answer's task preloads later
  const query = await fetchNext(shown.query.query_id);
  if (state.current !== shown || state.submitting) return; // answered meanwhile: stale
  if (query?.query_id !== state.next?.query.query_id) {
    state.next?.remove();
    state.next =
      query && query.query_id !== shown.query.query_id ? new Pair(query, query.brief) : null;
  }
  schedule(preload, state.next ? RENEW_MS : POLL_MS);
}

/** The caller's labels over all runs, once; later answers are added as they are stored. An
 * invited labeller labels their invite's run, sees how far they are towards its target, and
 * the study's end once there (study.js); whether their practice round is an entry test. */
export async function loadProgress() {
  const { data } = await request("GET", "/api/label/progress");
  state.total = data.labels;
  state.target = data.target_answers;
  state.entryTest = data.entry_pass != null;
  $("count-target").textContent = state.target == null ? ""
    : ` · ${data.counted} of ${state.target} towards the study`;
  if (data.invited) {
    if (data.run_id != null) state.runId = String(data.run_id);
    $("scope").textContent = state.runId ? `Run ${state.runId}` : "All runs";
  }
  showCounts();
  if (showProgress(data)) stopLabelling();
}
