// The labeller's page: two clips side by side driven by one clock, answered by button or key,
// under the instruction of the pair's run (it flashes when the next pair is another run's).
//
// The next pair is leased and loaded (hidden) while the current one is shown (`ahead_of`), and
// swapped in the moment an answer is given; the answer is sent after the swap. With nothing to
// label the page polls until the trainer pushes work. API calls run one at a time, in order, so
// an answer is stored before the next preload asks the server what this labeller holds.
//
// This module holds the keys and the page's controls; the rest is in modules of one idea each:
// label_state.js (the shared state and clock), label_player.js (the clock driving both clips,
// pause, scrub, frame steps, speed, the clips' size), label_pair.js (a pair's clips, loaded
// hidden and shown), label_instruction.js, label_screen.js (notices, counts, the waiting
// screen, the answer buttons), label_calls.js (the API calls in turn: leasing, preloading,
// progress), label_answer.js, label_undo.js, label_flag.js and label_practice.js.

import { start } from "./api.js";
import { startStudy, study } from "./study.js";
import { clock, state } from "./label_state.js";
import { showCounts, showStopped } from "./label_screen.js";
import {
  fitClips, replay, seekFrame, setPaused, setSpeed, startClock, stepFrames,
} from "./label_player.js";
import { toggleInstruction } from "./label_instruction.js";
import { attempt, loadCurrent, loadProgress, schedule } from "./label_calls.js";
import { answer } from "./label_answer.js";
import { undo } from "./label_undo.js";
import { openFlag, sendFlag } from "./label_flag.js";

const KEYS = {
  ArrowLeft: "left", 1: "left",
  ArrowRight: "right", 2: "right",
  ArrowUp: "equal", 3: "equal",
  ArrowDown: "cant_tell", 4: "cant_tell",
  s: "skip", S: "skip", 5: "skip",
};
const JUMP_FRAMES = 10; // J and L move the timeline this many frames

const $ = (id) => document.getElementById(id);

// ---- input ----------------------------------------------------------------------------------

function onKey(event) {
  if (event.repeat || event.ctrlKey || event.metaKey || event.altKey) return;
  // Signed out (the sign-in form has the keys) or labelling stopped: the page's keys are off.
  if ($("app").hidden || state.stopped) return;
  if ($("flag-dialog").open || $("practice-dialog").open) return; // a dialog has the keys
  if (event.target.closest?.("input, textarea, select")) return; // typing, not a shortcut
  if (event.key === "f" || event.key === "F") {
    event.preventDefault();
    openFlag();
    return;
  }
  if (event.key === "r" || event.key === "R") {
    event.preventDefault();
    replay();
    return;
  }
  if (event.key === "i" || event.key === "I") {
    event.preventDefault();
    toggleInstruction();
    return;
  }
  const player = {
    " ": () => setPaused(!clock.paused), k: () => setPaused(!clock.paused),
    ",": () => stepFrames(-1), ".": () => stepFrames(1),
    j: () => stepFrames(-JUMP_FRAMES), l: () => stepFrames(JUMP_FRAMES),
    Home: () => seekFrame(0), End: () => seekFrame(Infinity),
  }[event.key.length === 1 ? event.key.toLowerCase() : event.key];
  if (player) {
    event.preventDefault(); // Space would scroll or press a focused button
    player();
    return;
  }
  if (event.key === "Backspace" || event.key === "u" || event.key === "U") {
    event.preventDefault();
    undo();
    return;
  }
  const choice = KEYS[event.key];
  if (!choice) return;
  event.preventDefault(); // arrows would scroll
  const button = document.querySelector(`[data-choice="${choice}"]`);
  button.classList.add("pressed");
  setTimeout(() => button.classList.remove("pressed"), 150);
  answer(choice);
}

start(() => {
  if (state.runId !== null && !/^\d+$/.test(state.runId)) {
    showStopped(`“?run=${state.runId}” is not a run id.`);
    return;
  }
  if (state.runId) {
    $("scope").innerHTML = `Run ${state.runId} only · <a href="/label">all runs</a>`;
  }
  for (const button of document.querySelectorAll("[data-choice]")) {
    button.addEventListener("click", () => {
      button.blur(); // so Space or Enter cannot answer the next pair by accident
      answer(button.dataset.choice);
    });
  }
  $("replay").addEventListener("click", (event) => {
    event.currentTarget.blur();
    replay();
  });
  $("undo").addEventListener("click", (event) => {
    event.currentTarget.blur();
    undo();
  });
  $("flag").addEventListener("click", (event) => {
    event.currentTarget.blur();
    openFlag();
  });
  $("flag-form").addEventListener("submit", sendFlag);
  $("flag-cancel").addEventListener("click", () => $("flag-dialog").close());
  $("practice-dialog").addEventListener("close", () => {
    $("stage").hidden = study.complete; // the next pair, once the explanation is read (none
    // for one let go by the entry test: their study's end is shown instead)
    setPaused(false);
  });
  $("play").addEventListener("click", (event) => {
    event.currentTarget.blur();
    setPaused(!clock.paused);
  });
  $("frame-back").addEventListener("click", (event) => {
    event.currentTarget.blur();
    stepFrames(-1);
  });
  $("frame-next").addEventListener("click", (event) => {
    event.currentTarget.blur();
    stepFrames(1);
  });
  $("scrub").addEventListener("input", (event) => seekFrame(Number(event.target.value)));
  $("scrub").addEventListener("change", (event) => event.target.blur()); // keys answer again
  document.addEventListener("keydown", onKey);
  startClock();
  showCounts();
  for (const button of document.querySelectorAll("[data-speed]")) {
    button.addEventListener("click", () => {
      button.blur();
      setSpeed(Number(button.dataset.speed));
    });
  }
  $("instruction-more").addEventListener("click", (event) => {
    event.currentTarget.blur();
    toggleInstruction();
  });
  addEventListener("resize", fitClips);
  startStudy(() => { // past the target, by choice
    state.stopped = false;
    schedule(loadCurrent, 0);
  });
  // The progress first, asked until it comes: it says an invited participant's run, target
  // and entry test, which the pairs leased and the answers' Undo depend on.
  schedule(async () => {
    await loadProgress();
    await attempt(loadCurrent);
  }, 0);
});
