// Sessions: a week per rig; schedule, reschedule and cancel (staff). Overlaps are refused by
// the API (409) and its message is shown in the form the user acted in.

import { all, ApiError, patch, post, request } from "../api.js";
import {
  field, fmtDateTime, fmtTime, h, messageBox, oneAtATime, showRefusal, statusBadge, timeZone,
} from "../dom.js";
import { offersLiveView } from "./live.js";

const KINDS = ["calibration", "test", "online", "rl"];
const DAY_MS = 86_400_000;
const WORKDAY_START_HOUR = 9; // a new session's default start on a day still to come

/** ISO week ("2026-W49") of a local date. */
export function isoWeek(date) {
  const t = new Date(Date.UTC(date.getFullYear(), date.getMonth(), date.getDate()));
  const day = t.getUTCDay() || 7;
  t.setUTCDate(t.getUTCDate() + 4 - day);
  const year = t.getUTCFullYear();
  const week = Math.ceil(((t - Date.UTC(year, 0, 1)) / DAY_MS + 1) / 7);
  return `${year}-W${String(week).padStart(2, "0")}`;
}

/** Local midnight of the Monday of an ISO week. */
function mondayOf(week) {
  const [year, number] = week.split("-W").map(Number);
  const jan4 = new Date(year, 0, 4);
  const day = jan4.getDay() || 7;
  return new Date(year, 0, 4 - day + 1 + (number - 1) * 7);
}

function addDays(date, days) {
  return new Date(date.getFullYear(), date.getMonth(), date.getDate() + days);
}

function dateInput(date) {
  const pad = (n) => String(n).padStart(2, "0");
  return `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}`;
}

function timeInput(date) {
  return date.toTimeString().slice(0, 5);
}

/** The start as an ISO timestamp with the browser's zone resolved to UTC. */
function startOf(dateValue, timeValue) {
  const start = new Date(`${dateValue}T${timeValue}`);
  if (Number.isNaN(start.getTime())) {
    throw Object.assign(new Error(`${dateValue} ${timeValue} is not a date and time`),
      { fields: { scheduled_at: "not a date and time" } });
  }
  return start.toISOString();
}

function rigOptions(rigs, selected) {
  return [
    h("option", { value: "", selected: selected === null }, "No rig"),
    ...rigs.map((r) =>
      h("option", { value: r.id, selected: r.id === selected, disabled: !r.active }, r.name),
    ),
  ];
}

/** Date, time, duration and rig inputs shared by the schedule and reschedule forms. */
function timingFields(rigs, { start, duration = 60, rig = null }) {
  const date = h("input", { type: "date", name: "date", required: true, value: dateInput(start) });
  const time = h("input", { type: "time", name: "time", required: true, value: timeInput(start) });
  const minutes = h("input", {
    type: "number", name: "duration_minutes", min: 1, max: 1440, step: 1, required: true,
    value: duration,
  });
  const rigSelect = h("select", { name: "rig_id" }, rigOptions(rigs, rig));
  const fields = {
    date: field("Date", date),
    scheduled_at: field("Start", time),
    duration_minutes: field("Minutes", minutes, "1 to 1440"),
    rig_id: field("Rig", rigSelect),
  };
  return {
    nodes: Object.values(fields),
    fields,
    values: () => ({
      scheduled_at: startOf(date.value, time.value),
      duration_minutes: Number(minutes.value),
      rig_id: rigSelect.value ? Number(rigSelect.value) : null,
    }),
  };
}

function clearErrors(fields, message) {
  for (const f of Object.values(fields)) f.setError("");
  message.clear();
}

/** A new session's suggested start: the next full hour today when the week shown is this
 *  one (at 09:00 the next day if that is past the evening), else 09:00 on its Monday. */
export function defaultStart(monday, now = new Date()) {
  if (now < monday) {
    const start = new Date(monday);
    start.setHours(WORKDAY_START_HOUR, 0, 0, 0);
    return start;
  }
  const start = new Date(now);
  start.setHours(start.getHours() + 1, 0, 0, 0);
  if (start.getHours() >= 20 || start.getDate() !== now.getDate()) {
    const tomorrow = addDays(now, 1);
    tomorrow.setHours(WORKDAY_START_HOUR, 0, 0, 0);
    return tomorrow;
  }
  return start;
}

/**
 * A start in the past is asked about once. The API refuses it (422 at scheduled_at, naming
 * ``allow_past``) unless the request confirms it; that refusal is shown at the start field
 * in the browser's time and the button becomes "Schedule in the past"; submitting again
 * (same start) sends ``allow_past: true``. Returns true when ``err`` was that refusal.
 */
function askAboutPast(err, startIso, field, button, state) {
  const past = err instanceof ApiError && err.status === 422 && err.field === "scheduled_at" &&
    err.message.includes("allow_past");
  if (!past) return false;
  state.confirmed = startIso;
  field.setError(`${fmtDateTime(startIso)} (${timeZone()}) is in the past: submit again to record a session that has happened.`);
  button.textContent = `${state.label} in the past`;
  return true;
}

/** The body's ``allow_past``: whether the user confirmed this start in the past. */
const allowPast = (state, startIso) => state.confirmed === startIso;

function scheduleForm(subjects, rigs, monday, onDone) {
  const subject = h(
    "select",
    { name: "subject_id", required: true },
    h("option", { value: "" }, "Choose…"),
    subjects.map((s) => h("option", { value: s.id }, s.code)),
  );
  const kind = h("select", { name: "kind" }, KINDS.map((k) => h("option", { value: k }, k)));
  const timing = timingFields(rigs, { start: defaultStart(monday) });
  const notes = h("input", { name: "notes", maxlength: 10000 });
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Schedule");
  const fields = {
    subject_id: field("Subject", subject),
    kind: field("Kind", kind),
    ...timing.fields,
    notes: field("Notes", notes),
  };
  const form = h(
    "form",
    { class: "card", id: "schedule-form", "aria-labelledby": "schedule-title" },
    h("h2", { id: "schedule-title" }, "Schedule a session"),
    ...Object.values(fields),
    submit,
    message,
  );
  // one session per click: a second click while the first is on its way sends nothing
  const past = { label: "Schedule", confirmed: null };
  form.addEventListener("submit", oneAtATime([submit], async () => {
    clearErrors(fields, message);
    let values = null;
    try {
      values = timing.values();
      const created = await post("/api/v1/sessions", {
        subject_id: Number(subject.value),
        kind: kind.value,
        notes: notes.value,
        ...values,
        allow_past: allowPast(past, values.scheduled_at),
      });
      const when = new Date(created.scheduled_at) < new Date() ? " (in the past)" : "";
      onDone(
        `Session ${created.id} scheduled for ${fmtDateTime(created.scheduled_at)} ${timeZone()}${when}.`,
        isoWeek(new Date(created.scheduled_at)),
      );
      return "leaving";
    } catch (err) {
      if (!askAboutPast(err, values?.scheduled_at, fields.scheduled_at, submit, past)) {
        showRefusal(err, fields, message);
      }
      return null;
    }
  }));
  return form;
}


function editDialog(session, subjectCode, rigs, canEdit, onDone) {
  const dialog = h("dialog", { class: "card", "aria-labelledby": "edit-title" });
  const close = h("button", { type: "button", class: "btn small" }, "Close");
  close.addEventListener("click", () => dialog.close());
  dialog.addEventListener("close", () => dialog.remove());
  const header = [
    h("h2", { id: "edit-title" }, `Session ${session.id}: ${subjectCode}, ${session.kind}`),
    h("p", {}, statusBadge(session.status), ` ${fmtDateTime(session.scheduled_at)} (${timeZone()}), `,
      `${session.duration_minutes} min`),
    session.notes ? h("p", { class: "pre" }, session.notes) : null,
    offersLiveView(session, canEdit)
      ? h("p", {}, h("a", { href: `/sessions/${session.id}/live` }, "Live view"), " · ",
        h("a", { href: `/sessions/${session.id}/display`, target: "_blank" }, "Subject display"))
      : null,
  ];
  const shown = header.filter(Boolean); // DOM append writes null as the text "null"
  if (!canEdit || session.status !== "scheduled") {
    dialog.append(...shown, close);
    return dialog;
  }
  const timing = timingFields(rigs, {
    start: new Date(session.scheduled_at), duration: session.duration_minutes, rig: session.rig_id,
  });
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Reschedule");
  const form = h("form", { "aria-label": "Reschedule" }, ...timing.nodes, submit);
  const cancel = h("button", { type: "button", class: "btn danger" }, "Cancel session");
  const past = { label: "Reschedule", confirmed: null };
  form.addEventListener("submit", oneAtATime([submit, cancel], async () => {
    clearErrors(timing.fields, message);
    let values = null;
    try {
      values = timing.values();
      await patch(`/api/v1/sessions/${session.id}`,
        { ...values, allow_past: allowPast(past, values.scheduled_at) });
      dialog.close();
      onDone(`Session ${session.id} rescheduled.`);
      return "leaving";
    } catch (err) {
      if (!askAboutPast(err, values?.scheduled_at, timing.fields.scheduled_at, submit, past)) {
        showRefusal(err, timing.fields, message);
      }
      return null;
    }
  }));
  cancel.addEventListener("click", oneAtATime([submit, cancel], async () => {
    clearErrors(timing.fields, message);
    try {
      await request(`/api/v1/sessions/${session.id}/cancel`, { method: "POST" });
      dialog.close();
      onDone(`Session ${session.id} cancelled.`);
      return "leaving";
    } catch (err) {
      message.error(err);
      return null;
    }
  }));
  dialog.append(...shown, form, message, h("div", { class: "actions" }, cancel, " ", close));
  return dialog;
}

export async function sessionsPage(root, { canEdit, query }) {
  document.title = "Sessions · Brain-guided RL platform";
  const asked = query.get("week");
  // a week that exists (not 2026-W00, 2026-W99 or 2025-W53): else this week, and say so
  const valid = /^\d{4}-W\d{2}$/.test(asked || "") && isoWeek(mondayOf(asked)) === asked;
  const week = valid ? asked : isoWeek(new Date());
  const monday = mondayOf(week);
  const tz = timeZone();
  const [rigs, subjects, sessions] = await Promise.all([
    all("/api/v1/rigs"),
    all("/api/v1/subjects"),
    all("/api/v1/sessions", { week, tz }),
  ]);
  const code = new Map(subjects.map((s) => [s.id, s.code]));
  const days = [...Array(7).keys()].map((i) => addDays(monday, i));
  const rows = [...rigs.map((r) => ({ id: r.id, name: r.name })), { id: null, name: "No rig" }];
  const status = messageBox();

  function reload(text, toWeek = week) {
    sessionStorage.setItem("bgrl.flash", text);
    location.assign(`/sessions?week=${toWeek}`);
  }

  function sessionButton(session) {
    const label = `${fmtTime(session.scheduled_at)}–${fmtTime(session.ends_at)} ` +
      `${code.get(session.subject_id) || `#${session.subject_id}`} ${session.kind}`;
    const button = h(
      "button",
      { type: "button", class: `slot status-${session.status}`, "data-session": session.id },
      label,
      h("span", { class: "visually-hidden" }, ` (${session.status})`),
    );
    button.addEventListener("click", () => {
      const dialog = editDialog(session, code.get(session.subject_id), rigs, canEdit, reload);
      root.append(dialog);
      dialog.showModal();
    });
    return button;
  }

  const grid = h(
    "table",
    { class: "week" },
    h("caption", {}, `Week ${week} (${tz})`),
    h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Rig"),
      days.map((d) => h("th", { scope: "col" },
        d.toLocaleDateString(undefined, { weekday: "short", day: "numeric", month: "short" }))))),
    h("tbody", {}, rows.map((rig) => h("tr", {},
      h("th", { scope: "row" }, rig.name),
      days.map((day) => h("td", {}, sessions
        .filter((s) => s.rig_id === rig.id)
        .filter((s) => {
          const start = new Date(s.scheduled_at);
          return start >= day && start < addDays(day, 1);
        })
        .map(sessionButton))),
    ))),
  );
  const nav = h(
    "nav",
    { class: "inline", "aria-label": "Weeks" },
    h("a", { class: "btn small", href: `/sessions?week=${isoWeek(addDays(monday, -7))}` }, "← Previous week"),
    h("a", { class: "btn small", href: "/sessions" }, "This week"),
    h("a", { class: "btn small", href: `/sessions?week=${isoWeek(addDays(monday, 7))}` }, "Next week →"),
  );
  root.append(
    h("h1", {}, "Sessions"),
    nav,
    status,
    h(
      "div",
      { class: "columns" },
      h("section", { class: "wide scroll-x" }, grid),
      canEdit ? h("aside", {}, scheduleForm(subjects, rigs, monday, reload)) : null,
    ),
  );
  const flash = sessionStorage.getItem("bgrl.flash");
  if (flash) {
    sessionStorage.removeItem("bgrl.flash");
    status.show(flash);
  } else if (asked !== null && !valid) {
    status.show(`There is no week ${asked}: this is week ${week}.`, "warning");
  }
}
