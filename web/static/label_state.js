// The label page's state, owned here and shared by its modules: the pairs in hand, the counts,
// the runs' instructions, the last answer, and the clock both clips play from.

export const state = {
  runId: new URLSearchParams(location.search).get("run"), // an invite's run replaces it
  current: null, // the Pair on screen
  next: null, // the preloaded Pair, hidden
  submitting: false,
  timer: null,
  chain: Promise.resolve(),
  session: 0,
  total: null,
  clockOffsetMs: 0,
  speed: 1, // playback speed of both clips: 0.5, 1 or 2
  briefs: new Map(), // run id -> its instruction and clip timing (GET /api/label/runs/<id>)
  shownRun: null, // the run whose instruction is on screen
  briefedRuns: new Set(), // runs a pair of which was shown with the instruction open
  keptOpen: false, // the labeller opened the instruction: it stays open until they fold it
  target: null, // answers after which the caller's invite shows a completion code
  entryTest: false, // the caller's invite makes the practice round a test: no Undo there
  last: null, // the last answer, while it may be taken back: {pair, counted}
  progressDue: false, // an answer counted towards the study's target: its progress is asked
  stopped: false, // paused, refused, signed out or the study complete: no pairs, no keys
};

/** One master time for both clips: where the timeline is, full passes of the shown pair. */
export const clock = { t: 0, passes: 0, last: performance.now(), paused: false };

/** The browser's clock corrected by the server's (Date header, whole seconds), when far off:
 * shown_at is compared with the server's answered_at. */
export function serverNow() {
  return new Date(Date.now() + state.clockOffsetMs);
}

export function noteServerClock(response) {
  const server = Date.parse(response.headers.get("date"));
  if (Number.isNaN(server)) return;
  const offset = server - Date.now();
  state.clockOffsetMs = Math.abs(offset) > 5000 ? offset : 0;
}
