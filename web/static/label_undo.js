// Taking the last answer back: the Undo button (Backspace, U) for UNDO_MS after an answer is
// saved; the server has the last word on whether the answer can still be withdrawn.

import { ApiError, request } from "./api.js";
import { state } from "./label_state.js";
import { notice, showCounts, updateButtons } from "./label_screen.js";
import { Pair, show } from "./label_pair.js";
import {
  POLL_MS, RENEW_MS, attempt, fetchNext, loadCurrent, preload, runBrief, schedule, serial,
} from "./label_calls.js";

const UNDO_MS = 10_000; // an answer can be taken back this long (the server has the last word)

const $ = (id) => document.getElementById(id);

/** The Undo button, for UNDO_MS after an answer was saved; `counted`: whether it added to the
 * page's counts (taken back, it comes off them). */
export function offerUndo(pair, counted) {
  state.last = { pair, counted };
  $("undo").hidden = false;
  clearTimeout(offerUndo.timer);
  offerUndo.timer = setTimeout(() => ($("undo").hidden = true), UNDO_MS);
}

/** No Undo for the answer just given: an entry test's practice answer stands. */
export function withholdUndo() {
  state.last = null;
  $("undo").hidden = true;
  clearTimeout(offerUndo.timer);
}

/** Backspace, U or the button: the server withdraws the last answer (within its window and
 * while the trainer has not taken it) and leases the pair back, which is shown again; the pair
 * on screen waits, hidden, as the next one. Refusals are said as the server says them. Once
 * labelling has stopped (the study complete, a pause) nothing is taken back: the answer that
 * completed a study stands. A try that got no answer is made again, as an answer's is; the
 * answers stay disabled meanwhile, and the page's other calls wait. */
export function undo() {
  if (state.stopped) return;
  const last = state.last;
  if (!last) {
    notice("There is no answer to take back.");
    return;
  }
  state.last = null;
  $("undo").hidden = true;
  state.submitting = true;
  updateButtons();
  const taking = { last, tried: false };
  serial(() => attempt(() => takeBack(taking))).catch(() => {});
}

/** The withdrawal (asked again by `attempt` while it fails for a while), then the pair shown
 * again and the counts put back; or the refusal said. Either way the page's calls go on. */
async function takeBack(taking) {
  if (state.stopped) return; // the answer's progress, asked before this, completed the study
  const shown = state.current;
  const query = await withdraw(taking, shown);
  if (query) query.brief = await runBrief(query.run_id);
  state.submitting = false;
  if (!query) {
    updateButtons();
    schedule(state.current ? preload : loadCurrent, POLL_MS);
    return;
  }
  if (taking.last.counted) {
    state.session -= 1;
    if (state.total != null) state.total -= 1;
    showCounts();
  }
  state.next?.remove(); // its lease was released
  state.next = null;
  if (shown) {
    for (const video of shown.videos) video.pause();
    shown.root.hidden = true;
    state.current = null; // kept, not removed: it comes back next
    state.next = shown;
  }
  show(new Pair(query, query.brief));
  notice("Answer taken back: the pair is shown again.");
  schedule(preload, RENEW_MS);
}

/** The pair taken back, leased to the labeller again; null when the server refused (said on
 * screen). No answer, or a failing server's, is thrown: it is asked again. Asked again after a
 * try whose answer was lost, there may be nothing left to take back (404): that try took the
 * answer back (one standing answer per pair, so none is taken back twice), and the pair it
 * leased back comes as the one besides the pair shown. */
async function withdraw(taking, shown) {
  const tried = taking.tried;
  taking.tried = true;
  try {
    const { data } = await request("POST",
      `/api/label/${taking.last.pair.query.query_id}/withdraw`,
      shown ? { keep: shown.query.query_id } : {});
    return data.query;
  } catch (error) {
    if (!(error instanceof ApiError) || error.transient) throw error;
    if (tried && error.status === 404) return fetchNext(shown?.query.query_id);
    notice(`Undo refused: ${error.message}.`, "error");
    return null;
  }
}
