// Taking the last answer back: the Undo button (Backspace, U) for UNDO_MS after an answer is
// saved; the server has the last word on whether the answer can still be withdrawn.

import { SignedOut, request } from "./api.js";
import { state } from "./label_state.js";
import { notice, showCounts } from "./label_screen.js";
import { Pair, show } from "./label_pair.js";
import { RENEW_MS, preload, runBrief, schedule, serial } from "./label_calls.js";

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
 * completed a study stands. */
export function undo() {
  if (state.stopped) return;
  const last = state.last;
  if (!last) {
    notice("There is no answer to take back.");
    return;
  }
  state.last = null;
  $("undo").hidden = true;
  serial(async () => {
    if (state.stopped) return; // the answer's progress, asked before this, completed the study
    const shown = state.current;
    try {
      const { data } = await request("POST", `/api/label/${last.pair.query.query_id}/withdraw`,
        shown ? { keep: shown.query.query_id } : {});
      data.query.brief = await runBrief(data.query.run_id);
      if (last.counted) {
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
      show(new Pair(data.query, data.query.brief));
      notice("Answer taken back: the pair is shown again.");
      schedule(preload, RENEW_MS);
    } catch (error) {
      if (error instanceof SignedOut) throw error;
      notice(`Undo refused: ${error.message}.`, "error");
    }
  }).catch(() => {});
}
