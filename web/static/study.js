// The label page's study screens: why it waits (GET /api/label/status), and the end of a
// participant's study: "study complete" with their own completion code, a copy button and the
// invite's redirect, or, for one paused by check pairs, the code or the operator's message; for one
// an invite's entry test let go, that they did not pass and have no code.

import { request } from "./api.js";

const $ = (id) => document.getElementById(id);

const WHY = {
  target: "You gave all the answers this study asks for.",
  runs_over: "The training run behind this study has ended, so there are no more clips to "
    + "label. Your answers are kept.",
  paused: "Your answers on the check pairs (pairs whose better clip is known) did not match "
    + "often enough, so this study gives you no more pairs. Your answers so far are kept.",
  nothing_left: "You waited a while and there was nothing left for you to label: thank you "
    + "for your time. Your answers so far are kept.",
  entry_failed: "Your practice is over and you did not pass, so your part in this study ends "
    + "here, with no completion code. Thank you for your time.",
};

/** The page's state for the study: what the last status said. */
export const study = { complete: false, keepLabelling: false };

/** Asks why there is nothing to label and says it on the waiting screen; shows the study's end
 * instead when it is complete. True when the study is complete (stop asking for pairs). */
export async function explainWait(runId) {
  const params = runId ? `?run_id=${runId}` : "";
  const { data } = await request("GET", `/api/label/status${params}`);
  // Nothing to label and the study complete: the end screen, even for one who chose to keep
  // labelling past the target (their run may have ended since).
  if (showProgress(data.progress, true)) return true;
  const waiting = data.waiting;
  $("waiting-title").textContent = waiting.reason === "no_run" ? "No run to label right now"
    : waiting.reason === "entry_test" ? "Waiting for the study's practice pairs"
      : "Waiting for the trainer…";
  $("waiting-why").textContent = waiting.text;
  $("waiting").dataset.reason = waiting.reason;
  return false;
}

/** A paused labeller: the study's end, with the code or the operator's message, when they
 * joined by an invite; false otherwise (the page's own notice says what happened). */
export async function explainPause() {
  const { data } = await request("GET", "/api/label/status");
  return showProgress(data.progress);
}

/** Shows the completion screen when `progress` says the study is complete (once the target is
 * reached the participant may keep labelling, unless `always`). True when the screen is up. */
export function showProgress(progress, always = false) {
  if (!progress.complete) return false;
  if (progress.why === "target" && study.keepLabelling && !always) return false;
  study.complete = true;
  const box = $("completion");
  box.dataset.why = progress.why;
  $("completion-title").textContent = progress.why === "entry_failed"
    ? "Practice over: you did not pass the entry test"
    : progress.why === "paused" ? "Your part in this study has ended"
    : progress.why === "nothing_left" ? "Finished: nothing left to label"
      : "Study complete: thank you";
  $("completion-why").textContent = progress.why === "entry_failed"
    ? `You got ${progress.entry_correct ?? 0} practice pair${progress.entry_correct === 1 ? "" : "s"} `
      + `right; this study asks for ${progress.entry_pass}. ${WHY.entry_failed}`
    : WHY[progress.why] || "";
  const code = progress.completion_code;
  $("completion-code-row").hidden = !code;
  $("completion-hint").hidden = !code;
  $("completion-code").textContent = code || "";
  $("completion-message").hidden = !progress.pause_message;
  $("completion-message").textContent = progress.pause_message || "";
  const redirect = $("completion-redirect");
  redirect.hidden = !progress.redirect_url;
  if (progress.redirect_url) redirect.href = progress.redirect_url;
  $("completion-more").hidden = progress.why !== "target";
  for (const id of ["stage", "waiting"]) $(id).hidden = true;
  box.hidden = false;
  return true;
}

/** The copy button, and "keep labelling" (after the target only), which calls `resume`. */
export function startStudy(resume) {
  $("completion-copy").addEventListener("click", async () => {
    const code = $("completion-code").textContent;
    const button = $("completion-copy");
    try {
      await navigator.clipboard.writeText(code);
      button.textContent = "Copied";
    } catch {
      getSelection().selectAllChildren($("completion-code")); // copy it by hand
      button.textContent = "Selected: copy it";
    }
    setTimeout(() => (button.textContent = "Copy"), 3000);
  });
  $("completion-more").addEventListener("click", () => {
    study.keepLabelling = true;
    study.complete = false;
    $("completion").hidden = true;
    resume();
  });
}
