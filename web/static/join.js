// The invite link's page: join once (a new labeller, signed in in this browser), then offer the
// label page. A reload, or opening the link again in this browser, keeps the labeller it made,
// for the same participant only: another participant's link (a shared browser) joins anew.
// A study with a consent text joins only once the person agrees to it. The participant's id
// comes from `?participant=`, or a platform's own parameter (Prolific's PROLIFIC_PID, MTurk's
// workerId).

import { describe, keepToken } from "./api.js";

const $ = (id) => document.getElementById(id);
const code = document.body.dataset.code;
const joinedKey = `sepoa.invite.${code}`;

const PARTICIPANT_PARAMS = ["participant", "PROLIFIC_PID", "workerId"];

function ready(name) {
  $("join-status").textContent =
    `You are signed in as “${name}”. Read how it works below, then start.`;
  if ($("consent")) $("consent").hidden = true;
  $("join-start").hidden = false;
  $("join-start").focus();
}

function participantId() {
  const params = new URLSearchParams(location.search);
  return PARTICIPANT_PARAMS.map((name) => params.get(name)).find((value) => value) || null;
}

/** Who joined this link in this browser before, {name, participant}; null if nobody did. */
function joinedBefore() {
  const stored = localStorage.getItem(joinedKey);
  if (!stored) return null;
  try {
    const joined = JSON.parse(stored);
    if (typeof joined?.name === "string") return joined;
  } catch {
    // a name alone, kept before the participant was kept with it
  }
  return { name: stored, participant: null };
}

async function join() {
  const earlier = joinedBefore();
  if (earlier && earlier.participant === participantId()
      && localStorage.getItem("sepoa.labeller-token")) {
    ready(earlier.name);
    return;
  }
  if (document.body.dataset.consent === "required") {
    $("consent-agree").addEventListener("click", () => joinNow(true).catch(failed), { once: true });
    $("consent-decline").addEventListener("click", decline, { once: true });
    return;
  }
  await joinNow(false);
}

async function joinNow(consent) {
  const participant = participantId();
  const body = participant ? { participant } : {};
  if (consent) body.consent = true;
  const response = await fetch(`/api/join/${encodeURIComponent(code)}`, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  const data = await response.json().catch(() => null);
  if (response.status === 429) { // the link is joined fast just now: wait as the server says
    const seconds = Number(response.headers.get("retry-after")) || 5;
    $("join-status").textContent = `Many people are joining right now: trying again in ${seconds} s…`;
    setTimeout(() => joinNow(consent).catch(failed), seconds * 1000);
    return;
  }
  if (!response.ok) {
    $("join-status").hidden = true;
    $("join-error").textContent = describe(data?.detail) || `HTTP ${response.status}`;
    $("join-error").hidden = false;
    return;
  }
  keepToken("labeller", data.token);
  localStorage.setItem(joinedKey, JSON.stringify({ name: data.name, participant }));
  ready(data.name);
}

/** Declining the consent text: nothing is sent, nobody joins. */
function decline() {
  $("consent-agree").disabled = $("consent-decline").disabled = true;
  $("join-status").hidden = true;
  $("declined").hidden = false;
}

function failed(error) {
  $("join-status").hidden = true;
  $("join-error").textContent = `Could not join: ${error.message}. Reload the page to try again.`;
  $("join-error").hidden = false;
}

join().catch(failed);
