// The labellers table on the runs page (refreshed every 30 s): revoke or restore access, switch
// role, give a new token; below it, each labeller's quality for all runs or one (quality.js).

import { SignedOut, get, newLabellerToken, request } from "./api.js";
import { el, notify, poller } from "./dom.js";
import { startQuality } from "./quality.js";

const REFRESH_MS = 30_000; // others' changes (a revocation by the CLI, a participant joining)

const refreshLabellers = poller(async () => {
  try {
    render(await get("/api/labellers"));
  } catch (error) {
    if (error instanceof SignedOut) return false;
    notify(`Could not load the labellers: ${error.message}`, "error");
  }
  return true;
}, REFRESH_MS);

/** The table now, and every REFRESH_MS from then on while the tab is visible; the quality
 * table too (started by the first call, refreshed by later ones). */
export function loadLabellers() {
  startQuality();
  refreshLabellers();
}

function render(labellers) {
  const body = document.getElementById("labellers-body");
  if (labellers.length === 0) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: 5, class: "muted" },
      "No labellers yet: `sepoa labeller create NAME` or POST /api/labellers.")));
    return;
  }
  body.replaceChildren(...labellers.map((who) => who.scripted ? scriptedRow(who) : el("tr",
    { "data-labeller": who.name },
    el("td", {}, String(who.id)),
    el("td", { class: "name" }, who.name),
    el("td", {}, who.role),
    el("td", {}, el("span", { class: `badge ${who.active ? "running" : "stopped"}` },
      who.active ? "active" : "revoked")),
    el("td", { class: "actions" },
      button(who.active ? "Revoke" : "Activate", () =>
        change(who, { active: !who.active }, who.active ? "revoked" : "activated",
          who.active && `Revoke ${who.name}? Their answers stop being accepted at once.`)),
      button(who.role === "operator" ? "Make labeller" : "Make operator", () =>
        change(who, { role: who.role === "operator" ? "labeller" : "operator" }, "role changed",
          `Change ${who.name}'s role?`)),
      button("New token", () => newToken(who))),
  )));
}

/** The runs' scripted teacher answers as a labeller, but is no person: nothing to revoke. */
function scriptedRow(who) {
  return el("tr", { "data-labeller": who.name, class: "scripted" },
    el("td", {}, String(who.id)),
    el("td", { class: "name" }, who.name),
    el("td", {}, "scripted teacher"),
    el("td", {}, el("span", { class: "badge" }, "not a person")),
    el("td", { class: "muted small" }, "answers the runs a scripted teacher teaches"));
}

function button(label, onclick) {
  return el("button", { type: "button", class: "small", onclick }, label);
}

async function change(who, body, done, ask) {
  if (ask && !confirm(ask)) return;
  try {
    await request("PATCH", `/api/labellers/${who.id}`, body);
    notify(`${who.name}: ${done}.`);
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`${who.name}: ${error.message}`, "error");
  }
  loadLabellers();
}

async function newToken(who) {
  if (!confirm(`Give ${who.name} a new token? The old one stops working.`)) return;
  try {
    // When `who` is the operator signed in here, the page goes on with the new token.
    const data = await newLabellerToken(who.id);
    const shown = document.getElementById("new-token");
    shown.replaceChildren(`New token for ${data.name} (shown once): `, el("code", {}, data.token),
      data.own ? ". It was this page's own token: this page now signs in with it; keep it "
        + "to sign in elsewhere." : null);
    shown.hidden = false;
  } catch (error) {
    if (!(error instanceof SignedOut)) notify(`${who.name}: ${error.message}`, "error");
  }
}
