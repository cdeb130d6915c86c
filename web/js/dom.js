// Small DOM helpers: element building, messages, dates, downloads.

import { download } from "./api.js";

/** Build an element: h("a", {href: "/x", class: "btn", onclick: fn}, "text", child, ...). */
export function h(tag, attrs = {}, ...children) {
  const svg = ["svg", "g", "path", "line", "text", "rect", "title", "polyline", "circle"];
  const el = svg.includes(tag)
    ? document.createElementNS("http://www.w3.org/2000/svg", tag)
    : document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === undefined || value === null || value === false) continue;
    if (key.startsWith("on") && typeof value === "function") {
      el.addEventListener(key.slice(2), value);
    } else if (key === "value" && "value" in el && !(el instanceof SVGElement)) {
      el.value = value;
    } else if (key === "checked" || key === "selected") {
      el[key] = Boolean(value);
    } else {
      el.setAttribute(key, value === true ? "" : String(value));
    }
  }
  append(el, children);
  return el;
}

function append(el, children) {
  for (const child of children) {
    if (child === null || child === undefined || child === false) continue;
    if (Array.isArray(child)) append(el, child);
    else el.append(child instanceof Node ? child : String(child));
  }
}

/** A live region for an action's outcome (errors are announced, role="alert"). */
export function messageBox() {
  const box = h("p", { class: "message", role: "status", "aria-live": "polite", hidden: true });
  box.show = (text, kind = "ok") => {
    box.hidden = !text;
    box.textContent = text || "";
    box.className = `message ${kind}`;
    box.setAttribute("role", kind === "error" ? "alert" : "status");
  };
  box.error = (err) => box.show(localTimes(err?.message || String(err)), "error");
  box.clear = () => box.show("");
  return box;
}

export function fmtDateTime(iso) {
  if (!iso) return "–";
  return new Date(iso).toLocaleString(undefined, {
    year: "numeric", month: "short", day: "numeric", hour: "2-digit", minute: "2-digit",
  });
}

/** Month, day and time (no year): for lists of recent things. */
export function fmtShort(iso) {
  if (!iso) return "–";
  return new Date(iso).toLocaleString(undefined, {
    month: "short", day: "numeric", hour: "2-digit", minute: "2-digit",
  });
}

export function fmtTime(iso) {
  return new Date(iso).toLocaleTimeString(undefined, { hour: "2-digit", minute: "2-digit" });
}

export function fmtBytes(n) {
  if (n === null || n === undefined) return "–";
  const units = ["B", "KB", "MB", "GB"];
  let i = 0;
  let value = n;
  while (value >= 1024 && i < units.length - 1) {
    value /= 1024;
    i += 1;
  }
  return `${value.toFixed(i ? 1 : 0)} ${units[i]}`;
}

export function fmtNumber(value, digits = 2) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

/** A button that downloads an API file route and reports the checksum check beside it. */
export function downloadButton(label, path, fallbackName) {
  const note = h("span", { class: "muted small", "aria-live": "polite" });
  const button = h("button", { type: "button", class: "btn small" }, label);
  button.addEventListener("click", async () => {
    button.disabled = true;
    note.textContent = "downloading…";
    try {
      const got = await download(path, fallbackName);
      note.textContent =
        got.checksum === "mismatch"
          ? "checksum mismatch: file discarded"
          : `${got.filename} (${fmtBytes(got.size)}${got.checksum === "verified" ? ", SHA-256 verified" : ""})`;
    } catch (err) {
      note.textContent = err.message;
      note.classList.add("error-text");
    } finally {
      button.disabled = false;
    }
  });
  return h("span", { class: "download" }, button, " ", note);
}

/** A table from column specs [{label, cell(row) -> node|string}] (empty text when no rows). */
export function table(rows, columns, { caption, empty = "Nothing yet." } = {}) {
  if (!rows.length) return h("p", { class: "muted" }, empty);
  return h(
    "table",
    { class: "grid" },
    caption ? h("caption", {}, caption) : null,
    h("thead", {}, h("tr", {}, columns.map((c) => h("th", { scope: "col" }, c.label)))),
    h("tbody", {}, rows.map((row) => h("tr", {}, columns.map((c) => h("td", {}, c.cell(row)))))),
  );
}

export function statusBadge(status) {
  return h("span", { class: `badge status-${status}` }, status);
}

/** A labelled form field: {label, input, hint} with an error line tied by aria-describedby. */
export function field(label, input, hint = "") {
  const id = input.id || `f-${Math.random().toString(36).slice(2, 9)}`;
  input.id = id;
  const error = h("span", { class: "field-error", id: `${id}-error`, "aria-live": "polite" });
  const describedBy = [`${id}-error`];
  let hintEl = null;
  if (hint) {
    hintEl = h("span", { class: "hint", id: `${id}-hint` }, hint);
    describedBy.push(`${id}-hint`);
  }
  input.setAttribute("aria-describedby", describedBy.join(" "));
  const wrapper = h("div", { class: "field" }, h("label", { for: id }, label), input, hintEl, error);
  wrapper.setError = (message) => {
    error.textContent = message ? localTimes(message) : "";
    if (message) input.setAttribute("aria-invalid", "true");
    else input.removeAttribute("aria-invalid");
  };
  wrapper.input = input;
  return wrapper;
}

/** Show the API's refusal at the fields it names (e.g. scheduled_at: the start) and below. */
export function showRefusal(err, fields, message) {
  for (const [name, f] of Object.entries(fields)) f.setError(err.fields?.[name] || "");
  message.error(err);
}

/**
 * One request at a time from a form or a button: ``buttons`` are disabled while ``action``
 * runs, so a double click or a second Enter sends nothing more. They are enabled again when
 * it ends, unless it returns ``"leaving"`` (the page is reloading: nothing more to send).
 */
export function oneAtATime(buttons, action) {
  let pending = false;
  return async (event) => {
    event?.preventDefault();
    if (pending) return;
    pending = true;
    for (const b of buttons) b.disabled = true;
    let outcome;
    try {
      outcome = await action(event);
    } finally {
      pending = false;
      if (outcome !== "leaving") for (const b of buttons) b.disabled = false;
    }
  };
}

export const SHORT_ID_CHARS = 8; // the API and `bgrl` take any unique prefix of 6 or more

/**
 * A long id (a job's: 32 hex digits) as people read it: its first characters, linked when
 * ``href`` is given, with a button copying the whole id (the API and the CLI take either).
 */
export function shortId(id, href = null) {
  const text = id.slice(0, SHORT_ID_CHARS);
  const shown = href ? h("a", { href, title: id }, text) : h("code", { title: id }, text);
  const copy = h("button", {
    type: "button", class: "copy-id", title: `Copy the full id ${id}`, "aria-label": `Copy the full id ${id}`,
  }, "copy");
  copy.addEventListener("click", async () => {
    try {
      await navigator.clipboard.writeText(id);
      copy.textContent = "copied";
    } catch {
      // no clipboard here (not a secure context): select the id for Ctrl+C instead
      const field = h("input", { class: "copy-field", value: id, readonly: true, "aria-label": "Full id" });
      copy.replaceWith(field);
      field.select();
      return;
    }
    setTimeout(() => { copy.textContent = "copy"; }, 1500);
  });
  return h("span", { class: "short-id", "data-id": id }, shown, copy);
}

/** The browser's time zone, as people name it ("Europe/Berlin"). */
export function timeZone() {
  return Intl.DateTimeFormat().resolvedOptions().timeZone || "UTC";
}

const ISO_IN_TEXT = /\d{4}-\d{2}-\d{2}T\d{2}:\d{2}(?::\d{2}(?:\.\d+)?)?(?:Z|[+-]\d{2}:\d{2})/g;

/** An API message with its ISO timestamps (UTC) written in the browser's time zone, named. */
export function localTimes(text) {
  let found = false;
  const local = String(text).replace(ISO_IN_TEXT, (iso) => {
    found = true;
    return fmtDateTime(iso);
  });
  return found ? `${local} (times in ${timeZone()})` : local;
}
