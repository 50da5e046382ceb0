// The labeller's page: two clips side by side driven by one clock, answered by button or key,
// under the instruction of the pair's run (it flashes when the next pair is another run's).
//
// The next pair is leased and loaded (hidden) while the current one is shown (`ahead_of`), and
// swapped in the moment an answer is given; the answer is sent after the swap. With nothing to
// label the page polls until the trainer pushes work. API calls run one at a time, in order, so
// an answer is stored before the next preload asks the server what this labeller holds.

import { Paused, SignedOut, request, start } from "./api.js";
import { explainPause, explainWait, showProgress, startStudy, study } from "./study.js";

const KEYS = {
  ArrowLeft: "left", 1: "left",
  ArrowRight: "right", 2: "right",
  ArrowUp: "equal", 3: "equal",
  ArrowDown: "cant_tell", 4: "cant_tell",
  s: "skip", S: "skip", 5: "skip",
};
const POLL_MS = 2000; // nothing to label, or nothing preloaded yet: ask again this often
const RENEW_MS = 30_000; // both pairs in hand: renew their leases (120 s) this often
const RETRY_MS = 5000; // after a failed request
const SEEK_S = 0.3; // a clip this far off the clock is seeked; nearer, its rate is nudged
const END_HOLD_S = 0.3; // both clips hold their last frame this long before looping
const MAX_TICK_S = 0.1; // a long frame (a background tab) does not make the clock jump
const MAX_ZOOM = 2; // a clip is shown at most twice its own size
const FIT_SPARE_PX = 4; // room left below the answers when the clips fit the window
const NEW_TASK_MS = 4000; // how long "New task" stays up after the run changes
const UNDO_MS = 10_000; // an answer can be taken back this long (the server has the last word)
const JUMP_FRAMES = 10; // J and L move the timeline this many frames

const $ = (id) => document.getElementById(id);
let runId = new URLSearchParams(location.search).get("run"); // an invite's run replaces it

const state = {
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
  last: null, // the last answer, while it may be taken back: {pair, counted}
};
const clock = { t: 0, passes: 0, last: performance.now(), paused: false };

/** One query's two clips, in a hidden element until shown. */
class Pair {
  constructor(query, brief) {
    this.query = query;
    this.brief = brief;
    this.shownAt = null;
    this.broken = false;
    this.root = $("pair-template").content.firstElementChild.cloneNode(true);
    this.root.hidden = true;
    this.root.dataset.queryId = query.query_id;
    this.root.dataset.leftIsFirst = query.left_is_first;
    this.videos = [...this.root.querySelectorAll("video")];
    const urls = [query.left_clip_url, query.right_clip_url];
    this.videos.forEach((video, i) => {
      video.muted = true; // muted clips may play without a click
      video.setAttribute("aria-label", i === 0 ? "Left (top) clip" : "Right (bottom) clip");
      sizeVideo(video, brief.clip_width, brief.clip_height);
      video.addEventListener("loadedmetadata", () =>
        sizeVideo(video, video.videoWidth, video.videoHeight));
      video.addEventListener("error", () => this.failed());
      video.src = urls[i];
      video.load(); // start fetching now, even while hidden
    });
    $("pairs").append(this.root);
  }

  failed() {
    this.broken = true;
    if (this === state.current) {
      notice("A clip could not be loaded: answer “Can’t tell” or “Skip” to move on.", "error");
      updateButtons();
    }
  }

  remove() {
    for (const video of this.videos) {
      video.pause();
      video.removeAttribute("src");
      video.load(); // frees the decoder
    }
    this.root.remove();
  }
}

/** Its shape, and at most MAX_ZOOM times its own width on screen (CSS does the rest). */
function sizeVideo(video, width, height) {
  if (!(width > 0 && height > 0)) return;
  video.style.setProperty("--aspect", `${width / height}`);
  video.style.setProperty("--max-width", `${MAX_ZOOM * width}px`);
  fitClips();
}

/**
 * The clips' height (--fit-room, per clip): what the window leaves beside the page above them
 * and the answer bar under them (the player and the answers), whose heights vary with the
 * run's instruction, whether it is folded and the window's width, so that clips, player and
 * answers are all in view. CSS keeps a least height, below which a short window scrolls (the
 * instruction and the answer bar stay in view, sticky). A phone's clips take the full width.
 */
function fitClips() {
  cancelAnimationFrame(fitClips.frame);
  fitClips.frame = requestAnimationFrame(() => {
    const videos = [...document.querySelectorAll("#pairs .pair:not([hidden]) video")];
    if ($("stage").hidden || videos.length !== 2) return;
    const [a, b] = videos.map((video) => video.getBoundingClientRect());
    const stacked = b.top >= a.bottom - 1; // a phone's layout: one above the other
    const clips = stacked ? a.height + b.height : Math.max(a.height, b.height);
    // The page above the clips and around them, down to where the answer bar starts (it holds
    // the player and the answers; sticky, so its own place on screen is not where it starts).
    const above = $("pairs").getBoundingClientRect().bottom + scrollY - clips;
    const rest = above + $("answer-bar").offsetHeight;
    const room = (innerHeight - rest - FIT_SPARE_PX) / (stacked ? 2 : 1);
    $("stage").style.setProperty("--fit-room", `${Math.floor(room)}px`);
  });
}

// ---- the clock: one master time for both clips ----------------------------------------------

function playable(video) {
  const atEnd = video.currentTime >= video.duration - 0.05;
  return !video.seeking && (video.readyState >= 3 || (video.readyState >= 2 && atEnd));
}

function tick(now) {
  const dt = Math.min((now - clock.last) / 1000, MAX_TICK_S);
  clock.last = now;
  if (state.current) advance(state.current, dt);
  requestAnimationFrame(tick);
}

/** Moves the clock while both clips can play, and keeps each clip on it. */
function advance(pair, dt) {
  const videos = pair.videos;
  const length = Math.max(...videos.map((v) => v.duration)); // NaN until both have metadata
  if (!(length > 0) || !videos.every(playable)) {
    videos.forEach((v) => v.pause()); // the clock waits for the slower clip
    return;
  }
  pair.shownAt ??= serverNow(); // first frame on screen: the answer time starts here
  if (clock.paused) { // held on one frame: both clips shown at the clock's time, not playing
    hold(pair, Math.min(clock.t, length));
    return;
  }
  clock.t += dt * state.speed;
  if (clock.t >= length + END_HOLD_S) {
    if (videos.every((v) => v.ended || v.currentTime >= v.duration - 0.1)) clock.passes += 1;
    clock.t = 0;
    updateButtons();
  }
  for (const video of videos) {
    const target = Math.min(clock.t, video.duration);
    const drift = video.currentTime - target;
    if (video.paused || Math.abs(drift) > SEEK_S * state.speed) {
      if (Math.abs(drift) > 0.04) video.currentTime = target;
      video.playbackRate = state.speed;
    } else { // catch up smoothly, at the chosen speed
      video.playbackRate = state.speed * Math.min(1.5, Math.max(0.5, 1 - (2 * drift) / state.speed));
    }
    if (video.paused && target < video.duration - 0.04) video.play().catch(() => {});
  }
  showFrame(pair);
}

// ---- the player: pause, scrub, frame steps on the shared timeline ---------------------------

/** Frames of the shown pair's clips (one per step) and their rate. */
function frames(pair) {
  return { count: pair.query.segment_length, fps: pair.brief.fps };
}

/** The frame the timeline is on, 0-based. */
function frameAt(pair) {
  const { count, fps } = frames(pair);
  return Math.max(0, Math.min(count - 1, Math.floor(clock.t * fps + 1e-6)));
}

/** Paused: each clip shows the clock's time (the middle of a frame, so no decoder rounds it
 * into the next one). */
function hold(pair, t) {
  for (const video of pair.videos) {
    if (!video.paused) video.pause();
    const target = Math.min(t, video.duration - 1e-3);
    if (Math.abs(video.currentTime - target) > 1e-3 && !video.seeking) video.currentTime = target;
  }
  showFrame(pair);
}

function showFrame(pair) {
  const { count } = frames(pair);
  const length = Math.max(...pair.videos.map((v) => v.duration));
  if (length > 0) $("clock-bar").style.width = `${Math.min(100, (100 * clock.t) / length)}%`;
  const frame = frameAt(pair);
  const scrub = $("scrub");
  scrub.max = String(count - 1);
  if (document.activeElement !== scrub || clock.paused) scrub.value = String(frame);
  const q = pair.query;
  $("frame-info").textContent = `frame ${frame + 1} of ${count}`;
}

/** Pauses or plays both clips; paused, the timeline stays where it is. */
function setPaused(paused) {
  clock.paused = paused;
  $("play").setAttribute("aria-pressed", String(paused));
  $("play-label").textContent = paused ? "Play" : "Pause";
  if (!paused && state.current) {
    const length = Math.max(...state.current.videos.map((v) => v.duration));
    if (clock.t >= length) clock.t = 0; // from the end, play from the start
  }
}

/** Puts the timeline on a frame (0-based, clamped) and pauses there. */
function seekFrame(frame) {
  const pair = state.current;
  if (!pair) return;
  const { count, fps } = frames(pair);
  const clamped = Math.max(0, Math.min(count - 1, frame));
  setPaused(true);
  clock.t = (clamped + 0.5) / fps;
  hold(pair, clock.t);
}

const stepFrames = (n) => state.current && seekFrame(frameAt(state.current) + n);

/** The clip's length and, when the server knows it, where each clip starts in its episode
 * (top and bottom on a phone); an external run's clips are its client's, of no known step. */
function showClipInfo(pair) {
  const { count } = frames(pair);
  const q = pair.query;
  if (q.left_start_step == null || q.right_start_step == null) {
    $("clip-info").replaceChildren(`Each clip: ${count} steps`);
    return;
  }
  const side = (wide, narrow) => [
    Object.assign(document.createElement("span"), { className: "wide", textContent: wide }),
    Object.assign(document.createElement("span"), { className: "narrow", textContent: narrow }),
  ];
  $("clip-info").replaceChildren(`Each clip: ${count} steps · `, ...side("left", "top"),
    ` starts at step ${q.left_start_step} of its episode, `, ...side("right", "bottom"),
    ` at step ${q.right_start_step}`);
}

function replay() {
  clock.t = 0;
  setPaused(false);
  for (const video of state.current?.videos || []) video.currentTime = 0;
}

function setSpeed(speed) {
  state.speed = speed;
  for (const button of document.querySelectorAll("[data-speed]")) {
    button.setAttribute("aria-pressed", String(Number(button.dataset.speed) === speed));
  }
  showSpeedNote();
}

/** How the clips' speed relates to the task's own time, at the chosen speed: one sentence. */
function showSpeedNote() {
  const brief = state.current?.brief;
  if (!brief) return;
  $("speed-note").textContent = brief.real_time_ratio == null
    ? `One frame per step, ${round(brief.fps * state.speed)} frames a second.`
    : `${speedWords(brief.real_time_ratio * state.speed)}.`;
}

/** 1/3 -> "Slowed to 1/3 of real time"; 1 -> "Real time"; 4/3 -> "Sped up to 1.3× real time". */
function speedWords(ratio) {
  if (Math.abs(ratio - 1) < 0.03) return "Real time";
  if (ratio > 1) return `Sped up to ${round(ratio)}× real time`;
  return `Slowed to ${fraction(ratio)} of real time`;
}

/** A share below 1 as the simplest fraction within 2% of it ("1/3", "5/6"), else a percentage. */
function fraction(x) {
  for (let below = 2; below <= 12; below += 1) {
    const above = Math.round(x * below);
    if (above >= 1 && Math.abs(above / below - x) <= 0.02 * x) return `${above}/${below}`;
  }
  return `${Math.round(100 * x)}%`;
}

const round = (x) => Number(x.toPrecision(2));

// ---- what is on screen ----------------------------------------------------------------------

function show(pair) {
  if (state.current && state.current !== pair) state.current.remove();
  state.current = pair;
  pair.root.hidden = false;
  clock.t = 0;
  clock.passes = 0;
  setPaused(false);
  showClipInfo(pair);
  $("pair-id").textContent = `${pair.query.query_id} · run ${pair.query.run_id}`;
  $("waiting").hidden = true;
  $("stage").hidden = $("practice-dialog").open; // shown once a practice explanation is read
  const practice = pair.query.practice;
  $("practice-banner").hidden = !practice;
  if (practice) {
    $("practice-index").textContent = practice.index;
    $("practice-of").textContent = practice.of;
  }
  showInstruction(pair.brief);
  showSpeedNote();
  updateButtons();
  fitClips();
  if (pair.broken) pair.failed();
}

/** The run's instruction above the clips; a change of run is made hard to miss. */
function showInstruction(brief) {
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
function toggleInstruction() {
  const open = $("instruction").classList.contains("folded");
  state.keptOpen = open;
  setFolded(!open);
}

/** "dmc:cheetah_run" -> "cheetah run"; "metaworld:door-open" -> "door open". */
function taskTitle(task) {
  return (task.split(":")[1] || task).replace(/[_-]+/g, " ");
}

function showWaiting() {
  state.current?.remove();
  state.current = null;
  $("stage").hidden = true;
  $("waiting").hidden = false;
}

function updateButtons() {
  const pair = state.current;
  const watched = clock.passes >= 1;
  for (const button of document.querySelectorAll("[data-choice]")) {
    const escape = pair?.broken && ["cant_tell", "skip"].includes(button.dataset.choice);
    button.disabled = !pair || state.submitting || !(watched || escape);
  }
  $("watch-hint").classList.toggle("watched", watched);
  $("flag").disabled = !pair || state.submitting;
}

// ---- the practice round ---------------------------------------------------------------------

const CLICKED = { left: "left", right: "right", equal: "equally good", cant_tell: "can't tell", skip: "skip" };

/** After a practice answer: whether it was right and why, until Continue (Enter). */
function explainPractice(practice, choice) {
  const verdict = $("practice-verdict");
  verdict.className = `verdict ${practice.correct === true ? "right" : practice.correct === false ? "wrong" : ""}`;
  const said = `you answered “${CLICKED[choice] ?? choice}”`;
  verdict.textContent = practice.correct === true ? `Right: ${said}.`
    : practice.correct === false ? `Not this time: ${said}.` : `No preference given: ${said}.`;
  $("practice-title").textContent = `Practice pair ${practice.index} of ${practice.of}`;
  $("practice-explanation").textContent = practice.explanation;
  $("practice-next").textContent = practice.index >= practice.of
    ? "That was the last practice pair: the next pairs count." : "Next: another practice pair.";
  if (!$("practice-dialog").open) $("practice-dialog").showModal();
  setPaused(true);
}

// ---- flagging a pair nobody can judge -------------------------------------------------------

const FLAG_TEXT = { clip_broken: "clip broken", not_visible: "agent not visible", other: "other" };

function openFlag() {
  if ($("flag").disabled || $("flag-dialog").open) return;
  $("flag-form").reset();
  setPaused(true); // look at the frame that shows the problem
  $("flag-dialog").showModal();
  $("flag-dialog").querySelector("input[name=flag]").focus();
}

/** The dialog's answer: the pair is skipped with the flag and the note. */
function sendFlag(event) {
  event.preventDefault();
  const form = $("flag-form");
  const flag = form.querySelector("input[name=flag]:checked")?.value;
  if (!flag) return; // the radios are required: the browser says so
  const note = $("flag-note").value.trim();
  $("flag-dialog").close();
  answer("skip", { flag, flag_note: note || null });
  notice(`Pair flagged (${FLAG_TEXT[flag]}) and skipped: thank you.`);
}

function showCounts() {
  $("count-session").textContent = state.session;
  $("count-total").textContent = state.total ?? "–";
}

function notice(message, kind = "info") {
  const box = $("notice");
  box.textContent = message;
  box.className = `notice ${kind}`;
  box.hidden = false;
  clearTimeout(notice.timer);
  notice.timer = setTimeout(() => (box.hidden = true), 5000);
}

// ---- talking to the API, one call at a time -------------------------------------------------

function serial(task) {
  const run = state.chain.then(task);
  state.chain = run.catch(() => {});
  return run;
}

/** Runs `task` in turn; a failure is shown and retried, a refused token stops everything. */
async function attempt(task) {
  try {
    await task();
  } catch (error) {
    if (error instanceof SignedOut || error instanceof Paused) {
      stopLabelling();
      if (error instanceof Paused) {
        showPaused(error.message);
        // One who joined by an invite: the study's end, with their code or the operator's word.
        if (await explainPause().catch(() => false)) $("notice").hidden = true;
      }
      return;
    }
    notice(`${error.message} (retrying)`, "error");
    schedule(task, RETRY_MS);
  }
}

/** No more pairs: the loops stop and the pairs in hand are let go (their leases run out). */
function stopLabelling() {
  clearTimeout(state.timer);
  state.next?.remove();
  state.current?.remove();
  state.current = state.next = null;
}

function schedule(task, ms) {
  clearTimeout(state.timer);
  state.timer = setTimeout(() => serial(() => attempt(task)), ms);
}

/** The browser's clock corrected by the server's (Date header, whole seconds), when far off:
 * shown_at is compared with the server's answered_at. */
function serverNow() {
  return new Date(Date.now() + state.clockOffsetMs);
}

function noteServerClock(response) {
  const server = Date.parse(response.headers.get("date"));
  if (Number.isNaN(server)) return;
  const offset = server - Date.now();
  state.clockOffsetMs = Math.abs(offset) > 5000 ? offset : 0;
}

async function fetchNext(aheadOf) {
  const params = new URLSearchParams();
  if (runId) params.set("run_id", runId);
  if (aheadOf != null) params.set("ahead_of", aheadOf);
  const { data, response } = await request("GET", `/api/label/next?${params}`);
  noteServerClock(response);
  if (data) data.brief = await runBrief(data.run_id);
  return data; // null: nothing to label (204)
}

function showPaused(message) {
  const box = $("notice");
  clearTimeout(notice.timer);
  box.textContent = message.charAt(0).toUpperCase() + message.slice(1);
  box.className = "notice error paused";
  box.setAttribute("role", "alert");
  box.hidden = false;
  $("waiting").hidden = true;
  $("stage").hidden = true;
}

/** The run's instruction and clip timing, asked once per run and page (a reload asks again). */
async function runBrief(id) {
  if (!state.briefs.has(id)) {
    const { data } = await request("GET", `/api/label/runs/${id}`);
    state.briefs.set(id, data);
  }
  return state.briefs.get(id);
}

/** Nothing on screen: lease a pair and show it, or wait and ask again. */
async function loadCurrent() {
  if (study.complete) return;
  const query = await fetchNext(null);
  if (!query) {
    showWaiting();
    if (await explainWait(runId)) return; // the study is complete: nothing more to ask for
    schedule(loadCurrent, POLL_MS);
    return;
  }
  show(new Pair(query, query.brief));
  await preload();
}

/** A pair on screen: keep its lease and lease (or renew) the next one, loaded hidden. */
async function preload() {
  const shown = state.current;
  if (!shown || state.submitting || study.complete) return; // the answer's task preloads later
  const query = await fetchNext(shown.query.query_id);
  if (state.current !== shown || state.submitting) return; // answered meanwhile: stale
  if (query?.query_id !== state.next?.query.query_id) {
    state.next?.remove();
    state.next =
      query && query.query_id !== shown.query.query_id ? new Pair(query, query.brief) : null;
  }
  schedule(preload, state.next ? RENEW_MS : POLL_MS);
}

/** Answers the shown pair; `flag` ({flag, flag_note}) goes with a skip, allowed before the
 * clips have played through (a broken clip may never play). */
function answer(choice, flag = null) {
  const done = state.current;
  const button = document.querySelector(`[data-choice="${choice}"]`);
  if (!done || state.submitting || (button.disabled && !flag)) return;
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
  offerUndo(done);
  serial(() => attempt(async () => {
    try {
      await submit(done.query.query_id, body);
    } finally {
      state.submitting = false;
      if (practising && !$("practice-dialog").open) $("stage").hidden = false;
    }
    if (state.current === done) await loadCurrent(); // nothing was preloaded
    else {
      updateButtons();
      await preload();
    }
  }));
}

async function submit(queryId, body) {
  try {
    const { status, data } = await request("POST", `/api/label/${queryId}`, body);
    if (state.last?.pair.query.query_id === queryId) state.last.counted = status === 201;
    if (data?.practice_feedback && status === 201) explainPractice(data.practice_feedback, data.choice);
    if (status === 201) {
      state.session += 1;
      if (state.total != null) state.total += 1;
      showCounts();
      if (state.target != null) await loadProgress(); // decisive answers on the run count
    }
  } catch (error) {
    if (error instanceof SignedOut) throw error;
    if (error.status === 409) notice(`That pair can no longer be answered (${error.message}): moving on.`);
    else notice(`Your answer could not be saved: ${error.message}`, "error");
  }
}

/** The caller's labels over all runs, once; later answers are added as they are stored. An
 * invited labeller labels their invite's run, sees how far they are towards its target, and
 * the study's end once there (study.js). */
async function loadProgress() {
  const { data } = await request("GET", "/api/label/progress");
  state.total = data.labels;
  state.target = data.target_answers;
  $("count-target").textContent = state.target == null ? ""
    : ` · ${data.counted} of ${state.target} towards the study`;
  if (data.invited) {
    if (data.run_id != null) runId = String(data.run_id);
    $("scope").textContent = runId ? `Run ${runId}` : "All runs";
  }
  showCounts();
  if (showProgress(data)) stopLabelling();
}

// ---- taking the last answer back --------------------------------------------------------------

/** The Undo button, for UNDO_MS after an answer. */
function offerUndo(pair) {
  state.last = { pair, counted: false };
  $("undo").hidden = false;
  clearTimeout(offerUndo.timer);
  offerUndo.timer = setTimeout(() => ($("undo").hidden = true), UNDO_MS);
}

/** Backspace, U or the button: the server withdraws the last answer (within its window and
 * while the trainer has not taken it) and leases the pair back, which is shown again; the pair
 * on screen waits, hidden, as the next one. Refusals are said as the server says them. */
function undo() {
  const last = state.last;
  if (!last) {
    notice("There is no answer to take back.");
    return;
  }
  state.last = null;
  $("undo").hidden = true;
  serial(async () => {
    const shown = state.current;
    try {
      const { data } = await request("POST", `/api/label/${last.pair.query.query_id}/withdraw`,
        shown ? { keep: shown.query.query_id } : {});
      data.query.brief = await runBrief(data.query.run_id);
      if (last.counted) {
        state.session -= 1;
        if (state.total != null) state.total -= 1;
        showCounts();
      }
      state.next?.remove(); // its lease was released
      state.next = null;
      if (shown) {
        for (const video of shown.videos) video.pause();
        shown.root.hidden = true;
        state.current = null; // kept, not removed: it comes back next
        state.next = shown;
      }
      show(new Pair(data.query, data.query.brief));
      notice("Answer taken back: the pair is shown again.");
      schedule(preload, RENEW_MS);
    } catch (error) {
      if (error instanceof SignedOut) throw error;
      notice(`Undo refused: ${error.message}.`, "error");
    }
  }).catch(() => {});
}

// ---- input ----------------------------------------------------------------------------------

function onKey(event) {
  if (event.repeat || event.ctrlKey || event.metaKey || event.altKey) return;
  if ($("flag-dialog").open || $("practice-dialog").open) return; // a dialog has the keys
  if (event.key === "f" || event.key === "F") {
    event.preventDefault();
    openFlag();
    return;
  }
  if (event.target.closest?.("input, textarea, select")) return;
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
  if (runId !== null && !/^\d+$/.test(runId)) {
    notice(`“?run=${runId}” is not a run id.`, "error");
    return;
  }
  if (runId) {
    $("scope").innerHTML = `Run ${runId} only · <a href="/label">all runs</a>`;
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
    $("stage").hidden = false; // the next pair, once the explanation is read
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
  requestAnimationFrame(tick);
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
  startStudy(() => schedule(loadCurrent, 0));
  serial(() => loadProgress().catch(() => {})); // a nicety: "–" if it fails
  schedule(loadCurrent, 0);
});
