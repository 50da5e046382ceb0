// Shared by every page: the bearer token and JSON requests that carry it.
//
// The token comes from the URL fragment (`#token=...`: a fragment never reaches a server or its
// logs), is kept in localStorage (one slot per role, so an operator can also label), and is then
// removed from the address bar. Without one, or when the API refuses it (401/403), the page
// shows the sign-in form with the API's message.

const STORAGE = { labeller: "sepoa.labeller-token", operator: "sepoa.operator-token" };
const role = document.body.dataset.role;
let token = null;

const TIMEOUT_MS = 15_000; // a request with no whole answer by then is given up (asked again)

/** A request that failed: `status` is the HTTP status, or 0 when no answer came (the server
 * could not be reached, or did not answer within TIMEOUT_MS). */
export class ApiError extends Error {
  constructor(status, detail) {
    super(describe(detail) || `HTTP ${status}`);
    this.status = status;
  }

  /** Worth asking again: no answer, the server failing or busy (5xx), or asking to be asked
   * later (408, 429); any other refusal stands until something else changes. */
  get transient() {
    return this.status === 0 || this.status >= 500 || this.status === 408 || this.status === 429;
  }
}

/** Thrown once the token was refused: the page should stop its loops (sign-in reloads it). */
export class SignedOut extends Error {}

/** A labeller the run's check pairs paused (403 "paused: …"), or one an invite's entry test let
 * go (403 "entry test not passed: …"): still signed in, just not served. */
export class Paused extends Error {}

/** Keeps a token for `role` in this browser (an invite link's new labeller). */
export function keepToken(tokenRole, value) {
  localStorage.setItem(STORAGE[tokenRole], value);
}

/** Reads the token and calls `ready()` once signed in; otherwise shows the sign-in form. */
export function start(ready) {
  const fragment = new URLSearchParams(location.hash.slice(1)).get("token");
  if (fragment) {
    localStorage.setItem(STORAGE[role], fragment);
    history.replaceState(null, "", location.pathname + location.search);
  }
  token = localStorage.getItem(STORAGE[role]);
  document.getElementById("signin-form").addEventListener("submit", (event) => {
    event.preventDefault();
    localStorage.setItem(STORAGE[role], document.getElementById("signin-token").value.trim());
    location.reload(); // a clean start: no half-run loops from before
  });
  const signOutButton = document.getElementById("sign-out");
  signOutButton.addEventListener("click", () => signOut(""));
  if (!token) {
    signOut("");
    return;
  }
  signOutButton.hidden = false;
  ready();
}

function signOut(message) {
  token = null;
  localStorage.removeItem(STORAGE[role]);
  document.getElementById("app").hidden = true;
  document.getElementById("sign-out").hidden = true;
  document.getElementById("signin").hidden = false;
  const error = document.getElementById("signin-error");
  error.textContent = message;
  error.hidden = !message;
  document.getElementById("signin-token").focus();
}

/** `{status, data, response}`; data is the parsed JSON body (null for 204). */
export async function request(method, path, body) {
  return send(method, path, body, async (response) => {
    const data = response.status === 204 ? null : await response.json();
    return { status: response.status, data, response };
  });
}

/** A binary resource (an image) as a Blob, with the same sign-in and error handling. */
export async function getBlob(path) {
  return send("GET", path, undefined, (response) => response.blob());
}

/** The request, its refusals turned into errors, and its body as `read` reads it; all of it
 * within TIMEOUT_MS, else an ApiError of status 0 (as when the server cannot be reached). */
async function send(method, path, body, read, { retry = true } = {}) {
  if (!token) throw new SignedOut();
  const abort = new AbortController();
  const timer = setTimeout(() => abort.abort(), TIMEOUT_MS);
  const call = (bearer) => fetch(path, {
    method,
    headers: { Authorization: `Bearer ${bearer}`,
      ...(body === undefined ? {} : { "Content-Type": "application/json" }) },
    body: body === undefined ? undefined : JSON.stringify(body),
    signal: abort.signal,
  });
  try {
    const sent = token;
    let response = await call(sent);
    // Refused at the door (nothing was done): perhaps this page's token was just replaced.
    const other = response.status === 401 && retry ? await tokenAfter(sent) : null;
    if (other) {
      response = await call(other);
      if (response.ok && token !== other) adopt(other);
    }
    await refuse(response);
    return await read(response);
  } catch (error) {
    if (error instanceof ApiError || error instanceof SignedOut || error instanceof Paused)
      throw error;
    throw new ApiError(0, abort.signal.aborted
      ? `no answer from the server within ${TIMEOUT_MS / 1000} s`
      : "the server could not be reached");
  } finally {
    clearTimeout(timer);
  }
}

// A labeller's new token (POST /api/labellers/{id}/token) stops the old one at once. When the
// labeller is the operator signed in here, the page goes on with the new token, not signed out.
let replacing = null; // while this page gives a labeller a new token: a promise of that token

/** After a 401 to a request sent with `sent`, the token to try instead, if any: the page's own
 * when it took another meanwhile, else the one it is giving a labeller now (its own if the
 * labeller is the one signed in here: the retry says). */
async function tokenAfter(sent) {
  if (token && token !== sent) return token;
  const fresh = replacing && (await replacing);
  return fresh && fresh !== sent ? fresh : null;
}

function adopt(fresh) {
  token = fresh;
  localStorage.setItem(STORAGE[role], fresh);
}

/** A new token for labeller `id` ({id, name, role, token}, shown once); `own` when it was the
 * labeller signed in here, whose old token is refused from now on: the page (and this browser,
 * next time) signs in with the new one instead. */
export async function newLabellerToken(id) {
  const sent = token;
  const made = send("POST", `/api/labellers/${id}/token`, undefined, (r) => r.json(),
    { retry: false });
  replacing = made.then((data) => data.token, () => null);
  try {
    const data = await made;
    await get("/api/runs?limit=1"); // is the old token refused now? (then the new one is ours)
    return { ...data, own: token === data.token && token !== sent };
  } finally {
    replacing = null;
  }
}

/** Throws what a refused request means: signed out (the sign-in form), paused, or an ApiError. */
async function refuse(response) {
  if (response.status === 401 || response.status === 403) {
    const data = await response.json().catch(() => null);
    const detail = describe(data && data.detail);
    if (response.status === 403 && (detail.startsWith("paused") || detail.startsWith("entry test")))
      throw new Paused(detail);
    // A one-run participant asked for another run (a stale address): refused, still signed in.
    if (response.status === 403 && detail.startsWith("you joined this study for run"))
      throw new ApiError(response.status, detail);
    signOut(detail || `HTTP ${response.status}`);
    throw new SignedOut();
  }
  if (!response.ok) {
    const data = await response.json().catch(() => null);
    throw new ApiError(response.status, data && data.detail);
  }
}

export const get = (path) => request("GET", path).then((r) => r.data);
export const post = (path, body) => request("POST", path, body).then((r) => r.data);

/** A file from an authenticated endpoint, saved by the browser (a plain link sends no token). */
export async function download(path, fallbackName) {
  if (!token) throw new SignedOut();
  const response = await fetch(path, { headers: { Authorization: `Bearer ${token}` } });
  if (!response.ok) {
    const data = await response.json().catch(() => null);
    throw new ApiError(response.status, data && data.detail);
  }
  const disposition = response.headers.get("content-disposition") || "";
  const name = /filename="?([^";]+)"?/.exec(disposition)?.[1] || fallbackName;
  const url = URL.createObjectURL(await response.blob());
  const link = Object.assign(document.createElement("a"), { href: url, download: name });
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10_000);
}

/** An API error body as text: a string as it is; FastAPI's 422 list as "field: message" lines. */
export function describe(detail) {
  if (detail == null) return "";
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail
      .map((e) => {
        const where = (e.loc || []).filter((part) => part !== "body").join(".");
        const msg = String(e.msg).replace(/^Value error, /, ""); // pydantic's prefix says nothing
        return where ? `${where}: ${msg}` : msg;
      })
      .join("\n");
  }
  return JSON.stringify(detail);
}
