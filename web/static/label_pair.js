// One query's two clips: loaded in a hidden element (the preloaded next pair), then shown with
// its run's instruction, on a fresh timeline.

import { clock, state } from "./label_state.js";
import { fitClips, setPaused, showClipInfo, showSpeedNote, sizeVideo } from "./label_player.js";
import { showInstruction } from "./label_instruction.js";
import { notice, updateButtons } from "./label_screen.js";

const $ = (id) => document.getElementById(id);

/** One query's two clips, in a hidden element until shown. */
export class Pair {
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

/** Puts `pair` on screen in place of the one there, from its first frame. */
export function show(pair) {
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
