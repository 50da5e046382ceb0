// What the label page says around the clips: its notices, the counts, the waiting screen and
// whether the answer buttons may be pressed.

import { clock, state } from "./label_state.js";

const $ = (id) => document.getElementById(id);

/** A passing message (it hides after a while); none replaces a standing alert (showStopped). */
export function notice(message, kind = "info") {
  const box = $("notice");
  if (box.getAttribute("role") === "alert") return;
  box.textContent = message;
  box.className = `notice ${kind}`;
  box.hidden = false;
  clearTimeout(notice.timer);
  notice.timer = setTimeout(() => (box.hidden = true), 5000);
}

/** Labelling stopped for a reason asking again cannot change (a pause, a run that cannot be
 * labelled here): the reason as an alert that stays, in place of the pairs. */
export function showStopped(message) {
  const box = $("notice");
  clearTimeout(notice.timer);
  box.textContent = message.charAt(0).toUpperCase() + message.slice(1);
  box.className = "notice error stopped";
  box.setAttribute("role", "alert");
  box.hidden = false;
  $("waiting").hidden = true;
  $("stage").hidden = true;
}

export function showCounts() {
  $("count-session").textContent = state.session;
  $("count-total").textContent = state.total ?? "–";
}

export function showWaiting() {
  state.current?.remove();
  state.current = null;
  $("stage").hidden = true;
  $("waiting").hidden = false;
}

/** Answers need one full pass of both clips; a broken clip lets "Can't tell" and "Skip" by. */
export function updateButtons() {
  const pair = state.current;
  const watched = clock.passes >= 1;
  for (const button of document.querySelectorAll("[data-choice]")) {
    const escape = pair?.broken && ["cant_tell", "skip"].includes(button.dataset.choice);
    button.disabled = !pair || state.submitting || !(watched || escape);
  }
  $("watch-hint").classList.toggle("watched", watched);
  $("flag").disabled = !pair || state.submitting;
}
