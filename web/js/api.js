// Calls to the platform API (/api/v1) with the signed-in user's bearer token.

const TOKEN_KEY = "bgrl.access_token";
const SIGNIN_REASON_KEY = "bgrl.signin_reason";

/** An API answer that was not 2xx: status, the API's message and the field it names. */
export class ApiError extends Error {
  constructor(status, message, field = null, fields = {}) {
    super(message);
    this.status = status;
    this.field = field;
    this.fields = fields; // field name -> message (422 lists one per field)
  }
}

export function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function signOut() {
  sessionStorage.removeItem(TOKEN_KEY);
}

// Once this page has started to leave, a request answering 401 afterwards (a poll sent
// without the token just removed) must not send the user somewhere else instead.
let leaving = false;

function leave(url) {
  if (leaving) return;
  leaving = true;
  location.assign(url);
}

/** The Sign out button: forget the token and open the sign-in page. */
export function signOutToSignIn() {
  signOut();
  leave("/signin");
}

/** Send the user to the sign-in page, coming back here afterwards; ``reason`` (e.g. the
 *  API's "access token expired; log in again") is shown there. */
export function toSignIn(reason = "") {
  if (leaving) return;
  if (reason) sessionStorage.setItem(SIGNIN_REASON_KEY, reason);
  const here = location.pathname + location.search;
  leave(`/signin?next=${encodeURIComponent(here)}`);
}

/** Why the user was sent to sign in (once: read and forgotten), or "". */
export function takeSignInReason() {
  const reason = sessionStorage.getItem(SIGNIN_REASON_KEY) || "";
  sessionStorage.removeItem(SIGNIN_REASON_KEY);
  return reason;
}

async function errorOf(response) {
  return errorFromText(response.status, response.statusText, await response.text());
}

/** The ApiError of an answer's status and body text (the API's JSON error, or not JSON). */
function errorFromText(status, statusText, text) {
  let message = `${status} ${statusText}`;
  let field = null;
  const fields = {};
  try {
    const body = JSON.parse(text);
    if (Array.isArray(body.detail)) {
      for (const entry of body.detail) fields[entry.field] = entry.msg;
      field = body.detail.length ? body.detail[0].field : null;
      message = body.message || message;
    } else if (body.detail) {
      message = String(body.detail);
      field = body.field ?? null;
      if (field) fields[field] = message;
    }
  } catch {
    // not JSON: keep the status line
  }
  return new ApiError(status, message, field, fields);
}

/** Exchange e-mail and password for an access token (kept for this browser tab). */
export async function signIn(email, password) {
  const response = await fetch("/api/v1/auth/token", {
    method: "POST",
    body: new URLSearchParams({ username: email, password }),
  });
  if (!response.ok) throw await errorOf(response);
  const data = await response.json();
  sessionStorage.setItem(TOKEN_KEY, data.access_token);
}

/** fetch() with the token; a 401 (expired or revoked) sends the user to sign in. */
export async function request(path, { method = "GET", json, query } = {}) {
  const url = new URL(path, location.origin);
  for (const [key, value] of Object.entries(query || {})) {
    if (value !== undefined && value !== null && value !== "") url.searchParams.set(key, value);
  }
  const headers = { Authorization: `Bearer ${token()}` };
  const init = { method, headers };
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(json);
  }
  const response = await fetch(url, init);
  if (response.status === 401) {
    const { message } = await errorOf(response);
    signOut();
    toSignIn(`Signed out: ${message}.`);
    throw new ApiError(401, "signed out: sign in again");
  }
  if (!response.ok) throw await errorOf(response);
  return response;
}

/**
 * Send a file as the raw body of a POST (XMLHttpRequest: fetch cannot report upload
 * progress). ``onProgress(sent, total)`` follows the upload; ``onSent()`` is called once
 * every byte is sent (the API then validates it before answering). Resolves with the JSON
 * answer; rejects with an ApiError (a 401 sends the user to sign in, as request() does).
 */
export function uploadFile(path, file, { query = {}, onProgress = () => {}, onSent = () => {} } = {}) {
  const url = new URL(path, location.origin);
  for (const [key, value] of Object.entries(query)) url.searchParams.set(key, value);
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", url);
    xhr.setRequestHeader("Authorization", `Bearer ${token()}`);
    xhr.setRequestHeader("Content-Type", "application/octet-stream");
    xhr.upload.addEventListener("progress", (event) => onProgress(event.loaded, event.total || file.size));
    xhr.upload.addEventListener("load", () => onSent());
    xhr.addEventListener("error", () => reject(new ApiError(0, "the upload was cut off (network error): try again")));
    xhr.addEventListener("load", () => {
      const error = xhr.status >= 200 && xhr.status < 300
        ? null : errorFromText(xhr.status, xhr.statusText, xhr.responseText);
      if (xhr.status === 401) {
        signOut();
        toSignIn(`Signed out: ${error.message}.`);
        reject(new ApiError(401, "signed out: sign in again"));
      } else if (error) {
        reject(error);
      } else {
        resolve(JSON.parse(xhr.responseText));
      }
    });
    xhr.send(file);
  });
}

export async function get(path, query) {
  return (await request(path, { query })).json();
}

export async function post(path, json) {
  return (await request(path, { method: "POST", json })).json();
}

export async function patch(path, json) {
  return (await request(path, { method: "PATCH", json })).json();
}

/** Every item of a list route (pages of 500), up to ``max`` items. */
export async function all(path, query = {}, max = 2000) {
  const items = [];
  for (let offset = 0; offset < max; offset += 500) {
    const page = await get(path, { ...query, limit: 500, offset });
    items.push(...page.items);
    if (items.length >= page.total || page.items.length === 0) break;
  }
  return items;
}

/** An image route (e.g. a plot) as an object URL an <img> can show. */
export async function imageUrl(path) {
  const blob = await (await request(path)).blob();
  return URL.createObjectURL(blob);
}

function filenameOf(response, fallback) {
  const header = response.headers.get("Content-Disposition") || "";
  const star = /filename\*=UTF-8''([^;]+)/i.exec(header);
  if (star) return decodeURIComponent(star[1]);
  const plain = /filename="?([^";]+)"?/i.exec(header);
  return plain ? plain[1] : fallback;
}

async function sha256Hex(blob) {
  if (!globalThis.crypto?.subtle) return null; // not a secure context: cannot check here
  const digest = await crypto.subtle.digest("SHA-256", await blob.arrayBuffer());
  return [...new Uint8Array(digest)].map((b) => b.toString(16).padStart(2, "0")).join("");
}

/**
 * Download a file route as the browser's download, checking X-Checksum-Sha256 when sent.
 * Returns {filename, size, checksum: "verified" | "mismatch" | "unchecked"}.
 */
export async function download(path, fallbackName) {
  const response = await request(path);
  const blob = await response.blob();
  const expected = response.headers.get("X-Checksum-Sha256");
  let checksum = "unchecked";
  if (expected) {
    const actual = await sha256Hex(blob);
    if (actual !== null) checksum = actual === expected ? "verified" : "mismatch";
  }
  const filename = filenameOf(response, fallbackName);
  if (checksum !== "mismatch") {
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = filename;
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10_000);
  }
  return { filename, size: blob.size, checksum };
}

/** A websocket to ``path`` of this host, signed in with the user's token as the
 *  subprotocol ``bearer.<token>`` beside ``bgrl`` (browsers cannot send headers, and a
 *  token in the URL would be logged: the API refuses it there). */
function openSocket(path) {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  return new WebSocket(`${scheme}://${location.host}${path}`, ["bgrl", `bearer.${token()}`]);
}

/** A websocket of a job's progress events. */
export function jobEventsSocket(jobId) {
  return openSocket(`/api/v1/jobs/${encodeURIComponent(jobId)}/events`);
}

/** The websocket relaying a live session's robot frames (the sim is not reachable directly). */
export function framesSocket(sessionId) {
  return openSocket(`/api/v1/sessions/${encodeURIComponent(sessionId)}/frames`);
}
