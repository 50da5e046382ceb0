// Answering the shown pair: the preloaded next pair is swapped in at once, then the answer is
// sent (in turn with the page's other calls), then the pair after it is preloaded.

import { SignedOut, request } from "./api.js";
import { serverNow, state } from "./label_state.js";
import { notice, showCounts, updateButtons } from "./label_screen.js";
import { show } from "./label_pair.js";
import { attempt, loadCurrent, loadProgress, preload, serial } from "./label_calls.js";
import { explainPractice } from "./label_practice.js";
import { offerUndo, withholdUndo } from "./label_undo.js";

const $ = (id) => document.getElementById(id);

/** Answers the shown pair; `flag` ({flag, flag_note}) goes with a skip, allowed before the
 * clips have played through (a broken clip may never play). */
export function answer(choice, flag = null) {
  const done = state.current;
  const button = document.querySelector(`[data-choice="${choice}"]`);
  if (!done || state.submitting || (button.disabled && !flag)) return;
  state.submitting = true;
  clearTimeout(state.timer);
  const body = {
    choice,
    left_is_first: done.query.left_is_first,
    shown_at: (done.shownAt ?? serverNow()).toISOString(),
    ...(flag || {}),
  };
  // A practice answer's explanation is a screen of its own: the next pair waits behind it.
  const practising = done.query.practice != null;
  if (state.next) {
    show(state.next); // at once; the answer is sent below
    state.next = null;
  }
  if (practising) $("stage").hidden = true;
  updateButtons();
  withholdUndo(); // the last answer's offer ends; this one's comes once it is saved
  serial(() => attempt(async () => {
    try {
      const status = await submit(done.query.query_id, body);
      // An entry test measures the first try: its practice answers cannot be taken back.
      if (status != null && !(practising && state.entryTest)) offerUndo(done, status === 201);
    } finally {
      state.submitting = false;
      if (practising && !$("practice-dialog").open) $("stage").hidden = false;
    }
    if (state.current === done) await loadCurrent(); // nothing was preloaded
    else {
      updateButtons();
      await preload();
    }
  }));
}

/** Sends the answer; its status when stored (201, or 200 for one stored before), null when
 * refused or not saved (said on screen). */
async function submit(queryId, body) {
  try {
    const { status, data } = await request("POST", `/api/label/${queryId}`, body);
    if (data?.practice_feedback && status === 201) explainPractice(data.practice_feedback, data.choice);
    if (status === 201) {
      state.session += 1;
      if (state.total != null) state.total += 1;
      showCounts();
      if (state.target != null) await loadProgress(); // decisive answers on the run count
    }
    return status;
  } catch (error) {
    if (error instanceof SignedOut) throw error;
    if (error.status === 409) notice(`That pair can no longer be answered (${error.message}): moving on.`);
    else notice(`Your answer could not be saved: ${error.message}`, "error");
    return null;
  }
}
