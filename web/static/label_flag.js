// Flagging a pair nobody can judge (clip broken, agent not visible, other, with a note): a
// dialog that pauses the clips; its answer is a skip that carries the flag.

import { state } from "./label_state.js";
import { setPaused } from "./label_player.js";
import { notice } from "./label_screen.js";
import { answer } from "./label_answer.js";

const FLAG_TEXT = { clip_broken: "clip broken", not_visible: "agent not visible", other: "other" };

const $ = (id) => document.getElementById(id);

export function openFlag() {
  if (!state.current || $("flag").disabled || $("flag-dialog").open) return;
  $("flag-form").reset();
  setPaused(true); // look at the frame that shows the problem
  $("flag-dialog").showModal();
  $("flag-dialog").querySelector("input[name=flag]").focus();
}

/** The dialog's answer: the pair is skipped with the flag and the note. */
export function sendFlag(event) {
  event.preventDefault();
  const form = $("flag-form");
  const flag = form.querySelector("input[name=flag]:checked")?.value;
  if (!flag) return; // the radios are required: the browser says so
  const note = $("flag-note").value.trim();
  $("flag-dialog").close();
  if (!answer("skip", { flag, flag_note: note || null })) return; // no pair to flag any more
  notice(`Pair flagged (${FLAG_TEXT[flag]}) and skipped: thank you.`);
}
