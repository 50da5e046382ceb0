// Answering the shown pair: the preloaded next pair is swapped in at once, then the answer is
// sent (in turn with the page's other calls), then the study's progress is asked for (when the
// answer counts towards a target) and the pair after it preloaded. Each step is asked again on
// its own when it fails for a while: the answer is sent again only while it has no answer (sent
// again, it is stored once: 200 with the answer stored before), never after a later step fails.

import { ApiError, request } from "./api.js";
import { serverNow, state } from "./label_state.js";
import { notice, showCounts, updateButtons } from "./label_screen.js";
import { show } from "./label_pair.js";
import { attempt, loadCurrent, loadProgress, preload, serial } from "./label_calls.js";
import { explainPractice } from "./label_practice.js";
import { offerUndo, withholdUndo } from "./label_undo.js";

const $ = (id) => document.getElementById(id);

/** Answers the shown pair; `flag` ({flag, flag_note}) goes with a skip, allowed before the
 * clips have played through (a broken clip may never play). False when nothing was answered. */
export function answer(choice, flag = null) {
  const done = state.current;
  const button = document.querySelector(`[data-choice="${choice}"]`);
  if (!done || state.stopped || state.submitting || (button.disabled && !flag)) return false;
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
  const sent = { done, body, practising, tried: false };
  serial(() => attempt(() => store(sent)));
  return true;
}

/** The answer's POST (asked again by `attempt` while it fails for a while), then what follows
 * it: the Undo offer, the progress and the next pair. */
async function store(sent) {
  const counted = await submit(sent);
  state.submitting = false;
  if (sent.practising && !$("practice-dialog").open) $("stage").hidden = false;
  // An entry test measures the first try: its practice answers cannot be taken back.
  if (counted != null && !(sent.practising && state.entryTest)) offerUndo(sent.done, counted);
  if (counted && state.target != null) state.progressDue = true; // decisive answers count
  await attempt(() => carryOn(sent.done));
}

/** Sends the answer; whether it added to the counts (stored now, or by an earlier try whose
 * answer was lost: 200 after a failed try), null when refused (said on screen). No answer, or
 * a failing server's, is thrown: the answer is sent again. */
async function submit(sent) {
  const tried = sent.tried;
  sent.tried = true;
  try {
    const { status, data } = await request("POST", `/api/label/${sent.done.query.query_id}`,
      sent.body);
    const counted = status === 201 || tried;
    if (counted) {
      if (data?.practice_feedback) explainPractice(data.practice_feedback, data.choice);
      state.session += 1;
      if (state.total != null) state.total += 1;
      showCounts();
    }
    return counted;
  } catch (error) {
    if (!(error instanceof ApiError) || error.transient) throw error;
    if (error.status === 409) notice(`That pair can no longer be answered (${error.message}): moving on.`);
    else notice(`Your answer could not be saved: ${error.message}`, "error");
    return null;
  }
}

/** After an answer: the study's progress, when an answer counted towards its target (it may
 * now be complete), then the next pair. */
async function carryOn(done) {
  if (state.progressDue) {
    await loadProgress();
    state.progressDue = false;
  }
  await attempt(async () => {
    if (state.current === done) await loadCurrent(); // nothing was preloaded
    else {
      updateButtons();
      await preload();
    }
  });
}
