// The practice round: after a practice answer, whether it was right and why, in a dialog that
// holds the next pair back until it is read.

import { setPaused } from "./label_player.js";

const CLICKED = { left: "left", right: "right", equal: "equally good", cant_tell: "can't tell", skip: "skip" };

const $ = (id) => document.getElementById(id);

/** After a practice answer: whether it was right and why, until Continue (Enter). */
export function explainPractice(practice, choice) {
  const verdict = $("practice-verdict");
  verdict.className = `verdict ${practice.correct === true ? "right" : practice.correct === false ? "wrong" : ""}`;
  const said = `you answered “${CLICKED[choice] ?? choice}”`;
  verdict.textContent = practice.correct === true ? `Right: ${said}.`
    : practice.correct === false ? `Not this time: ${said}.` : `No preference given: ${said}.`;
  $("practice-title").textContent = `Practice pair ${practice.index} of ${practice.of}`;
  $("practice-explanation").textContent = practice.explanation;
  $("practice-next").textContent = practice.entry_test === "failed"
    ? "That was the last practice pair, and you did not pass this study's entry test: your part "
      + "in it is over."
    : practice.entry_test === "passed" ? "You passed this study's entry test: the next pairs count."
      : practice.index >= practice.of
        ? "That was the last practice pair: the next pairs count." : "Next: another practice pair.";
  if (!$("practice-dialog").open) $("practice-dialog").showModal();
  setPaused(true);
}
