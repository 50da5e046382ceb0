// The invite link's page: join once (a new labeller, signed in in this browser), then offer the
// label page. A reload, or opening the link again in this browser, keeps the labeller it made.

import { describe, keepToken } from "./api.js";

const $ = (id) => document.getElementById(id);
const code = document.body.dataset.code;
const joinedKey = `sepoa.invite.${code}`;

function ready(name) {
  $("join-status").textContent = `You are signed in as “${name}”. Read the above, then start.`;
  $("join-start").hidden = false;
  $("join-start").focus();
}

async function join() {
  const earlier = localStorage.getItem(joinedKey);
  if (earlier && localStorage.getItem("sepoa.labeller-token")) {
    ready(earlier);
    return;
  }
  const participant = new URLSearchParams(location.search).get("participant");
  const response = await fetch(`/api/join/${encodeURIComponent(code)}`, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(participant ? { participant } : {}),
  });
  const data = await response.json().catch(() => null);
  if (!response.ok) {
    $("join-status").hidden = true;
    $("join-error").textContent = describe(data?.detail) || `HTTP ${response.status}`;
    $("join-error").hidden = false;
    return;
  }
  keepToken("labeller", data.token);
  localStorage.setItem(joinedKey, data.name);
  ready(data.name);
}

join().catch((error) => {
  $("join-status").hidden = true;
  $("join-error").textContent = `Could not join: ${error.message}. Reload the page to try again.`;
  $("join-error").hidden = false;
});
