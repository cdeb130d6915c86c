// Recordings: upload one to a session (drag and drop or the file input, with the upload's
// and the validation's progress and the refusal's reason at the field), list them per
// subject and session with their validation status, download, calibrate (an
// eeg_calibration job) and delete (admin; refused while a job uses the recording).

import { all, post, request, uploadFile } from "../api.js";
import {
  downloadButton, field, fmtBytes, fmtDateTime, fmtNumber, h, messageBox, oneAtATime, shortId, statusBadge, table,
} from "../dom.js";
import { jobForm, jobKinds } from "./jobform.js";

/** The file types the EEG service reads (the API's RECORDING_SUFFIXES). */
export const RECORDING_TYPES = [".bdf", ".edf", ".fif", ".set", ".xdf", ".zip"];

function suffixOf(name) {
  const dot = name.lastIndexOf(".");
  return dot < 0 ? "" : name.slice(dot).toLowerCase();
}

function uploadForm(subjects, chosenSubject, onUploaded) {
  const subject = h("select", { name: "subject", required: true },
    h("option", { value: "" }, "Choose…"),
    subjects.map((s) => h("option", { value: s.id, selected: String(s.id) === chosenSubject }, s.code)));
  const session = h("select", { name: "session_id", required: true, disabled: true }, h("option", { value: "" }, "Choose a subject first"));
  const input = h("input", { type: "file", name: "file", accept: RECORDING_TYPES.join(","), required: true });
  const drop = h("div", { class: "dropzone", id: "dropzone" },
    h("p", {}, "Drop a recording here, or choose it below."), input,
    h("p", { class: "muted small" }, `${RECORDING_TYPES.join(", ")} (.zip: a BrainVision set or an EEGLAB .set with its .fdt)`));
  const fields = {
    subject: field("Subject", subject),
    session_id: field("Session", session),
    filename: field("File", drop),
  };
  const bar = h("progress", { max: 100, value: 0, hidden: true, id: "upload-progress" });
  const phase = h("span", { class: "muted small", id: "upload-phase", "aria-live": "polite" });
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Upload");
  let file = null;

  async function loadSessions() {
    session.replaceChildren(h("option", { value: "" }, subject.value ? "Choose…" : "Choose a subject first"));
    session.disabled = !subject.value;
    if (!subject.value) return;
    const sessions = await all("/api/v1/sessions", { subject_id: subject.value });
    session.append(...sessions.filter((s) => s.status !== "cancelled").map((s) =>
      h("option", { value: s.id }, `#${s.id} ${s.kind}, ${fmtDateTime(s.scheduled_at)} (${s.status})`)));
  }
  function choose(chosen) {
    file = chosen;
    fields.filename.setError("");
    phase.textContent = file ? `${file.name}, ${fmtBytes(file.size)}` : "";
    if (file && !RECORDING_TYPES.includes(suffixOf(file.name))) {
      fields.filename.setError(`${file.name} is not a recording the EEG service reads: send one of ${RECORDING_TYPES.join(", ")}`);
    }
  }
  subject.addEventListener("change", loadSessions);
  input.addEventListener("change", () => choose(input.files[0] || null));
  drop.addEventListener("dragover", (event) => { event.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (event) => {
    event.preventDefault();
    drop.classList.remove("over");
    if (event.dataTransfer.files.length) choose(event.dataTransfer.files[0]);
  });

  const form = h("form", { class: "card", id: "upload-form", "aria-labelledby": "upload-title", novalidate: true },
    h("h2", { id: "upload-title" }, "Upload a recording"), ...Object.values(fields),
    h("div", {}, bar, " ", phase), submit, message);
  form.addEventListener("submit", oneAtATime([submit], async () => {
    for (const f of Object.values(fields)) f.setError("");
    message.clear();
    if (!subject.value) fields.subject.setError("choose the subject");
    if (!session.value) fields.session_id.setError("choose the session it was recorded in");
    if (!file) fields.filename.setError("choose or drop a file");
    else if (!RECORDING_TYPES.includes(suffixOf(file.name))) choose(file);
    if (form.querySelector("[aria-invalid=true]")) return null;
    bar.hidden = false;
    bar.value = 0;
    try {
      const recording = await uploadFile(`/api/v1/sessions/${session.value}/recordings`, file, {
        query: { filename: file.name },
        onProgress: (sent, total) => {
          bar.value = total ? Math.round((100 * sent) / total) : 0;
          phase.textContent = `uploading ${file.name}: ${fmtBytes(sent)} of ${fmtBytes(total)}`;
        },
        onSent: () => {
          bar.removeAttribute("value"); // indeterminate: the EEG service reads the file
          phase.textContent = "uploaded; the EEG service is validating it…";
        },
      });
      bar.hidden = true;
      if (recording.validation_status === "invalid") {
        fields.filename.setError(`stored, but refused by the validation: ${recording.validation_reason}`);
        phase.textContent = "";
      } else {
        phase.textContent = "";
        message.show(`${recording.filename} uploaded: ${recording.validation_status}` +
          (recording.validation_reason ? ` (${recording.validation_reason})` : "") + ".");
      }
      await onUploaded(recording);
    } catch (err) {
      bar.hidden = true;
      phase.textContent = "";
      fields.filename.setError(err.fields?.filename || err.fields?.body || err.message);
      if (err.fields?.session_id) fields.session_id.setError(err.fields.session_id);
    }
    return null;
  }));
  if (chosenSubject) loadSessions();
  return form;
}

/** The eeg_calibration job form (generated from its schema) for one recording. */
async function calibrateForm(recording, onSubmitted) {
  const kinds = (await jobKinds()).filter((k) => k.name === "eeg_calibration");
  return jobForm(kinds, {
    fixed: { recording_id: recording.id }, compact: true, title: `Calibrate on recording ${recording.id}`,
    submitLabel: "Submit calibration", onSubmitted,
  });
}

export async function recordingsPage(root, { user, canEdit, query }) {
  document.title = "Recordings · Brain-guided RL platform";
  const isAdmin = user.role === "admin";
  const subjects = await all("/api/v1/subjects");
  const code = new Map(subjects.map((s) => [s.id, s.code]));
  const subjectFilter = h("select", { id: "filter-subject", name: "subject_id" }, h("option", { value: "" }, "every subject"),
    subjects.map((s) => h("option", { value: s.id, selected: String(s.id) === query.get("subject_id") }, s.code)));
  const statusFilter = h("select", { id: "filter-validation", name: "validation_status" }, h("option", { value: "" }, "any"),
    ["valid", "invalid", "pending"].map((v) => h("option", { value: v, selected: v === query.get("validation_status") }, v)));
  const message = messageBox();
  const list = h("div");
  const highlighted = query.get("recording");

  async function load() {
    const [recordings, sessions] = await Promise.all([
      all("/api/v1/recordings", { subject_id: subjectFilter.value, validation_status: statusFilter.value }),
      all("/api/v1/sessions", { subject_id: subjectFilter.value }),
    ]);
    const sessionOf = new Map(sessions.map((s) => [s.id, s]));
    const rows = highlighted ? [...recordings].sort((a, b) => (String(b.id) === highlighted) - (String(a.id) === highlighted)) : recordings;
    list.replaceChildren(table(rows, [
      { label: "#", cell: (r) => String(r.id) },
      { label: "File", cell: (r) => [r.filename, h("div", { class: "muted small" }, fmtBytes(r.size_bytes), r.synthetic ? ", synthetic" : "")] },
      {
        label: "Subject / session",
        cell: (r) => {
          const s = sessionOf.get(r.session_id);
          return s ? [h("a", { href: `/subjects/${s.subject_id}` }, code.get(s.subject_id) || `#${s.subject_id}`),
            ` / #${s.id} ${s.kind}`] : `session #${r.session_id}`;
        },
      },
      { label: "Uploaded", cell: (r) => fmtDateTime(r.created_at) },
      {
        label: "Validation",
        cell: (r) => [statusBadge(r.validation_status), r.validation_reason ? h("div", { class: "small" }, r.validation_reason) : null],
      },
      {
        label: "Signal",
        cell: (r) => (r.validation_status === "valid"
          ? `${r.n_channels ?? "–"} ch, ${fmtNumber(r.sfreq, 0)} Hz, ${fmtNumber(r.duration_s, 0)} s` : "–"),
      },
      { label: "", cell: (r) => actions(r) },
    ], { caption: `${recordings.length} recording(s)`, empty: "No recordings match." }));
    for (const tr of list.querySelectorAll("tbody tr")) {
      if (tr.firstChild.textContent === highlighted) tr.classList.add("highlight");
    }
  }

  function actions(recording) {
    const box = h("div", { class: "row-actions", "data-recording": recording.id });
    box.append(downloadButton("Download", `/api/v1/recordings/${recording.id}/file`, recording.filename));
    if (canEdit && recording.validation_status === "valid") {
      const calibrate = h("button", { type: "button", class: "btn small" }, "Calibrate…");
      calibrate.addEventListener("click", oneAtATime([calibrate], async () => {
        try {
          calibrate.replaceWith(await calibrateForm(recording, (job, note) => {
            note.show("Calibration job submitted: ");
            note.append(shortId(job.id, `/jobs/${job.id}`));
          }));
        } catch (err) {
          message.error(err);
        }
        return "leaving"; // replaced by the form
      }));
      box.append(" ", calibrate);
    }
    if (canEdit && recording.validation_status === "pending") {
      const again = h("button", { type: "button", class: "btn small" }, "Validate again");
      again.addEventListener("click", oneAtATime([again], async () => {
        try {
          const checked = await post(`/api/v1/recordings/${recording.id}/validate`);
          message.show(`Recording ${recording.id}: ${checked.validation_status}${checked.validation_reason ? ` (${checked.validation_reason})` : ""}.`);
          await load();
        } catch (err) {
          message.error(err);
        }
      }));
      box.append(" ", again);
    }
    if (isAdmin) {
      const remove = h("button", { type: "button", class: "btn small danger" }, "Delete");
      remove.addEventListener("click", oneAtATime([remove], async () => {
        if (!confirm(`Delete recording ${recording.id} (${recording.filename}) and its file? This cannot be undone.`)) return;
        try {
          await request(`/api/v1/recordings/${recording.id}`, { method: "DELETE" });
          message.show(`Recording ${recording.id} (${recording.filename}) deleted.`);
          await load();
        } catch (err) {
          message.error(err); // e.g. a calibration job still uses it
        }
      }));
      box.append(" ", remove);
    }
    return box;
  }

  function remember() {
    const params = new URLSearchParams();
    if (subjectFilter.value) params.set("subject_id", subjectFilter.value);
    if (statusFilter.value) params.set("validation_status", statusFilter.value);
    history.replaceState(null, "", `/recordings${params.size ? `?${params}` : ""}`);
  }
  subjectFilter.addEventListener("change", () => { remember(); load(); });
  statusFilter.addEventListener("change", () => { remember(); load(); });
  const form = canEdit ? uploadForm(subjects, query.get("subject_id"), async () => load()) : null;
  root.append(
    h("h1", {}, "Recordings"),
    h("div", { class: "inline" },
      h("label", { for: "filter-subject" }, "Subject"), subjectFilter,
      h("label", { for: "filter-validation" }, "Validation"), statusFilter),
    message,
    h("div", { class: "columns" }, h("section", { class: "wide scroll-x" }, list), form ? h("aside", {}, form) : null),
  );
  await load();
  if (highlighted) list.querySelector("tr.highlight")?.scrollIntoView({ block: "center" });
}
