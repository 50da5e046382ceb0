// Small DOM and formatting helpers for the operator pages.

/** `el("td", {class: "num"}, "42")`: an element with attributes (or handlers) and children. */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (value == null || value === false) continue;
    if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value === true ? "" : value);
  }
  node.append(...children.flat().filter((c) => c != null));
  return node;
}

/** A number for people: "1,234", "12.3", "0.123"; "–" for missing. */
export function num(value, digits = 3) {
  if (value == null || Number.isNaN(value)) return "–";
  if (Number.isInteger(value)) return value.toLocaleString("en-US");
  return Number(value.toPrecision(digits)).toLocaleString("en-US", { maximumFractionDigits: 6 });
}

/** "12 s ago", "5 min ago", or a date; "–" for missing. */
export function ago(iso) {
  if (!iso) return "–";
  const seconds = (Date.now() - Date.parse(iso)) / 1000;
  if (seconds < 90) return `${Math.max(0, Math.round(seconds))} s ago`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min ago`;
  return new Date(iso).toLocaleString();
}

/** The latest true return in a run's `progress` (the worker's heartbeat): the last training
 * episode's, else the last evaluation's. */
export function lastReturn(progress) {
  for (const key of ["last_return", "eval_return"]) {
    if (typeof progress?.[key] === "number") return progress[key];
  }
  return null;
}

/** Show a short message in the page's #notice for a while (kind: "info" or "error"). */
export function notify(message, kind = "info", seconds = 6) {
  const notice = document.getElementById("notice");
  notice.textContent = message;
  notice.className = `notice ${kind}`;
  notice.hidden = false;
  clearTimeout(notify.timer);
  notify.timer = setTimeout(() => (notice.hidden = true), seconds * 1000);
}

/** The controls an operator has for a run in each status: [label, path suffix, confirm?]. */
export function runActions(status) {
  return {
    queued: [["Stop", "stop", true]],
    running: [["Pause", "pause"], ["Stop", "stop", true]],
    paused: [["Resume", "resume"], ["Stop", "stop", true]],
    stopping: [["Force stop", "stop?force=true", true]],
    stopped: [["Requeue", "requeue"]],
    failed: [["Requeue", "requeue"]],
  }[status] || [];
}

/** `refresh = poller(load, ms)`: runs `load()` now and then every `ms` while the tab is visible
 * and `load` returns true; a call during a load runs once more right after it (no overlap). */
export function poller(load, ms) {
  let timer = null, busy = false, again = false;
  async function refresh() {
    if (busy) {
      again = true;
      return;
    }
    busy = true;
    clearTimeout(timer);
    let more = true;
    try {
      if (!document.hidden) more = await load();
    } finally {
      busy = false;
    }
    if (again) {
      again = false;
      refresh();
    } else if (more) {
      timer = setTimeout(refresh, ms);
    }
  }
  document.addEventListener("visibilitychange", () => !document.hidden && refresh());
  return refresh;
}

/** A refused form's errors as list items in `list` (an API 422: one per field). */
export function listErrors(list, error) {
  list.replaceChildren(...error.message.split("\n").map((line) => el("li", {}, line)));
  list.hidden = false;
}
