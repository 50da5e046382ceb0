// The label page's player: one clock drives both clips of the shown pair (they loop together),
// paused, scrubbed or stepped a frame at a time on their shared timeline, at 0.5, 1 or 2x; and
// the clips' size on screen, fitted to the window's room beside the instruction and answers.

import { clock, serverNow, state } from "./label_state.js";
import { updateButtons } from "./label_screen.js";

const SEEK_S = 0.3; // a clip this far off the clock is seeked; nearer, its rate is nudged
const END_HOLD_S = 0.3; // both clips hold their last frame this long before looping
const MAX_TICK_S = 0.1; // a long frame (a background tab) does not make the clock jump
const MAX_ZOOM = 2; // a clip is shown at most twice its own size
const FIT_SPARE_PX = 4; // room left below the answers when the clips fit the window

const $ = (id) => document.getElementById(id);

/** Its shape, and at most MAX_ZOOM times its own width on screen (CSS does the rest). */
export function sizeVideo(video, width, height) {
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
export function fitClips() {
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

/** Starts the clock, which moves on every animation frame from now on. */
export function startClock() {
  requestAnimationFrame(tick);
}

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
  // First frame in view: the answer time starts here (not behind a practice explanation).
  if (!pair.shownAt && inView()) pair.shownAt = serverNow();
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

/** The stage is on screen, with no dialog over it. */
function inView() {
  return !$("stage").hidden && !$("practice-dialog").open && !$("flag-dialog").open;
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
  $("frame-info").textContent = `frame ${frame + 1} of ${count}`;
}

/** Pauses or plays both clips; paused, the timeline stays where it is. */
export function setPaused(paused) {
  clock.paused = paused;
  $("play").setAttribute("aria-pressed", String(paused));
  $("play-label").textContent = paused ? "Play" : "Pause";
  if (!paused && state.current) {
    const length = Math.max(...state.current.videos.map((v) => v.duration));
    if (clock.t >= length) clock.t = 0; // from the end, play from the start
  }
}

/** Puts the timeline on a frame (0-based, clamped) and pauses there. */
export function seekFrame(frame) {
  const pair = state.current;
  if (!pair) return;
  const { count, fps } = frames(pair);
  const clamped = Math.max(0, Math.min(count - 1, frame));
  setPaused(true);
  clock.t = (clamped + 0.5) / fps;
  hold(pair, clock.t);
}

export const stepFrames = (n) => state.current && seekFrame(frameAt(state.current) + n);

/** The clip's length and, when the server knows it, where each clip starts in its episode
 * (top and bottom on a phone); an external run's clips are its client's, of no known step. */
export function showClipInfo(pair) {
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

export function replay() {
  clock.t = 0;
  setPaused(false);
  for (const video of state.current?.videos || []) video.currentTime = 0;
}

export function setSpeed(speed) {
  state.speed = speed;
  for (const button of document.querySelectorAll("[data-speed]")) {
    button.setAttribute("aria-pressed", String(Number(button.dataset.speed) === speed));
  }
  showSpeedNote();
}

/** How the clips' speed relates to the task's own time, at the chosen speed: one sentence. */
export function showSpeedNote() {
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
