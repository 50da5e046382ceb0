// The run's instruction above the clips: open for a run's first pair on the page, folded to one
// line from its second; opened and kept open (or folded) by the labeller; a change of run is
// made hard to miss.

import { state } from "./label_state.js";
import { fitClips } from "./label_player.js";

const NEW_TASK_MS = 4000; // how long "New task" stays up after the run changes

const $ = (id) => document.getElementById(id);

/** The run's instruction above the clips; a change of run is made hard to miss. */
export function showInstruction(brief) {
  const box = $("instruction");
  const [goal, ...rest] = brief.instruction.split("\n");
  $("instruction-body").replaceChildren(
    Object.assign(document.createElement("p"), { className: "goal", textContent: goal }),
    ...rest.filter((line) => line.trim()).map((line) =>
      Object.assign(document.createElement("p"), { textContent: line })),
  );
  $("instruction-task").textContent = taskTitle(brief.task);
  box.dataset.run = brief.run_id;
  box.dataset.sha256 = brief.instruction_sha256;
  // Open for a run's first pair on this page, folded to one line from its second pair on.
  const first = !state.briefedRuns.has(brief.run_id);
  state.briefedRuns.add(brief.run_id);
  setFolded(!first && !state.keptOpen);
  const changed = state.shownRun !== null && state.shownRun !== brief.run_id;
  state.shownRun = brief.run_id;
  if (!changed) return;
  box.classList.remove("changed");
  void box.offsetWidth; // restart the flash
  box.classList.add("changed");
  $("instruction-new").hidden = false;
  clearTimeout(showInstruction.timer);
  showInstruction.timer = setTimeout(() => {
    $("instruction-new").hidden = true;
    box.classList.remove("changed");
  }, NEW_TASK_MS);
}

function setFolded(folded) {
  $("instruction").classList.toggle("folded", folded);
  $("instruction-more").setAttribute("aria-expanded", String(!folded));
  $("instruction-more-label").textContent = folded ? "Show all" : "Fold";
  fitClips();
}

/** The button or I: the labeller opens the instruction (kept open) or folds it. */
export function toggleInstruction() {
  const open = $("instruction").classList.contains("folded");
  state.keptOpen = open;
  setFolded(!open);
}

/** "dmc:cheetah_run" -> "cheetah run"; "metaworld:door-open" -> "door open". */
function taskTitle(task) {
  return (task.split(":")[1] || task).replace(/[_-]+/g, " ");
}
