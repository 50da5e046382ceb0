// The run page's instruction editor: what labellers are told "better" means for this run.

import { SignedOut, request } from "./api.js";
import { notify } from "./dom.js";

const $ = (id) => document.getElementById(id);

/** The run's instruction in the form, unless the operator is editing it. */
export function showInstruction(run) {
  if ($("instruction-form").contains(document.activeElement)) return;
  $("instruction-text").value = run.instruction_text;
  $("instruction-origin").textContent = run.instruction == null ? "the task's own" : "the operator's";
}

async function save(runId, instruction, refresh) {
  try {
    await request("PUT", `/api/runs/${runId}/instruction`, { instruction });
    notify(instruction == null ? "Instruction: the task's own from now on." : "Instruction saved.");
    document.activeElement.blur();
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`Instruction: ${error.message}`, "error");
  }
  refresh();
}

export function startInstructionForm(runId, refresh) {
  $("instruction-form").addEventListener("submit", (event) => {
    event.preventDefault();
    save(runId, $("instruction-text").value, refresh);
  });
  $("instruction-reset").addEventListener("click", () => save(runId, null, refresh));
}
