// Sessions: a week per rig; schedule, reschedule and cancel (staff). Overlaps are refused by
// the API (409) and its message is shown in the form the user acted in.

import { all, patch, post, request } from "../api.js";
import { field, fmtDateTime, fmtTime, h, messageBox, statusBadge } from "../dom.js";
import { offersLiveView } from "./live.js";

const KINDS = ["calibration", "test", "online", "rl"];
const DAY_MS = 86_400_000;

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
  return new Date(`${dateValue}T${timeValue}`).toISOString();
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
  return {
    nodes: [field("Date", date), field("Start", time), field("Minutes", minutes, "1 to 1440"),
      field("Rig", rigSelect)],
    values: () => ({
      scheduled_at: startOf(date.value, time.value),
      duration_minutes: Number(minutes.value),
      rig_id: rigSelect.value ? Number(rigSelect.value) : null,
    }),
  };
}

function scheduleForm(subjects, rigs, monday, onDone) {
  const subject = h(
    "select",
    { name: "subject_id", required: true },
    h("option", { value: "" }, "Choose…"),
    subjects.map((s) => h("option", { value: s.id }, s.code)),
  );
  const kind = h("select", { name: "kind" }, KINDS.map((k) => h("option", { value: k }, k)));
  const start = new Date(Math.max(Date.now(), monday.getTime()));
  start.setHours(start.getHours() + 1, 0, 0, 0);
  const timing = timingFields(rigs, { start });
  const notes = h("input", { name: "notes", maxlength: 10000 });
  const message = messageBox();
  const form = h(
    "form",
    { class: "card", id: "schedule-form", "aria-labelledby": "schedule-title" },
    h("h2", { id: "schedule-title" }, "Schedule a session"),
    field("Subject", subject),
    field("Kind", kind),
    ...timing.nodes,
    field("Notes", notes),
    h("button", { type: "submit", class: "btn primary" }, "Schedule"),
    message,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    message.clear();
    try {
      const created = await post("/api/v1/sessions", {
        subject_id: Number(subject.value),
        kind: kind.value,
        notes: notes.value,
        ...timing.values(),
      });
      onDone(
        `Session ${created.id} scheduled for ${fmtDateTime(created.scheduled_at)}.`,
        isoWeek(new Date(created.scheduled_at)),
      );
    } catch (err) {
      message.error(err);
    }
  });
  return form;
}

function editDialog(session, subjectCode, rigs, canEdit, onDone) {
  const dialog = h("dialog", { class: "card", "aria-labelledby": "edit-title" });
  const close = h("button", { type: "button", class: "btn small" }, "Close");
  close.addEventListener("click", () => dialog.close());
  dialog.addEventListener("close", () => dialog.remove());
  const header = [
    h("h2", { id: "edit-title" }, `Session ${session.id}: ${subjectCode}, ${session.kind}`),
    h("p", {}, statusBadge(session.status), ` ${fmtDateTime(session.scheduled_at)}, `,
      `${session.duration_minutes} min`),
    session.notes ? h("p", { class: "pre" }, session.notes) : null,
    offersLiveView(session, canEdit)
      ? h("p", {}, h("a", { href: `/sessions/${session.id}/live` }, "Live view"), " · ",
        h("a", { href: `/sessions/${session.id}/display`, target: "_blank" }, "Subject display"))
      : null,
  ];
  if (!canEdit || session.status !== "scheduled") {
    dialog.append(...header, close);
    return dialog;
  }
  const timing = timingFields(rigs, {
    start: new Date(session.scheduled_at), duration: session.duration_minutes, rig: session.rig_id,
  });
  const message = messageBox();
  const form = h(
    "form",
    { "aria-label": "Reschedule" },
    ...timing.nodes,
    h("button", { type: "submit", class: "btn primary" }, "Reschedule"),
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    message.clear();
    try {
      await patch(`/api/v1/sessions/${session.id}`, timing.values());
      dialog.close();
      onDone(`Session ${session.id} rescheduled.`);
    } catch (err) {
      message.error(err);
    }
  });
  const cancel = h("button", { type: "button", class: "btn danger" }, "Cancel session");
  cancel.addEventListener("click", async () => {
    message.clear();
    try {
      await request(`/api/v1/sessions/${session.id}/cancel`, { method: "POST" });
      dialog.close();
      onDone(`Session ${session.id} cancelled.`);
    } catch (err) {
      message.error(err);
    }
  });
  dialog.append(...header, form, message, h("div", { class: "actions" }, cancel, " ", close));
  return dialog;
}

export async function sessionsPage(root, { canEdit, query }) {
  document.title = "Sessions · Brain-guided RL platform";
  const week = /^\d{4}-W\d{2}$/.test(query.get("week") || "") ? query.get("week") : isoWeek(new Date());
  const monday = mondayOf(week);
  const tz = Intl.DateTimeFormat().resolvedOptions().timeZone || "UTC";
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
  }
}
