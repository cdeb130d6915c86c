// One subject: notes, and its sessions, recordings, classifiers, HF models and jobs.

import { all, get, patch, post } from "../api.js";
import { downloadButton, field, fmtBytes, fmtDateTime, fmtNumber, h, messageBox, oneAtATime, shortId, statusBadge, table } from "../dom.js";
import { offersLiveView } from "./live.js";

function notesForm(subject, canEdit) {
  if (!canEdit) {
    return h("section", {}, h("h2", {}, "Notes"), h("p", { class: "pre" }, subject.notes || "–"));
  }
  const notes = h("textarea", { name: "notes", rows: 4, maxlength: 10000, value: subject.notes });
  const message = messageBox();
  const save = h("button", { type: "submit", class: "btn primary" }, "Save notes");
  const notesField = field("Notes", notes);
  const form = h("form", { class: "card" }, h("h2", {}, "Notes"), notesField, save, message);
  form.addEventListener("submit", oneAtATime([save], async () => {
    message.clear();
    notesField.setError("");
    try {
      await patch(`/api/v1/subjects/${subject.id}`, { notes: notes.value });
      message.show("Notes saved.");
    } catch (err) {
      if (err.fields?.notes) notesField.setError(err.fields.notes);
      message.error(err);
    }
  }));
  return form;
}

function section(title, ...content) {
  return h("section", {}, h("h2", {}, title), ...content);
}

/** Staff: export the subject's sessions as BIDS (a job; its zip downloads from the job page). */
function bidsExport(subject) {
  const message = messageBox();
  const button = h("button", { type: "button", class: "btn" }, "Export as BIDS");
  button.addEventListener("click", async () => {
    message.clear();
    button.disabled = true;
    try {
      const job = await post("/api/v1/jobs", { kind: "bids_export", config: { subject_id: subject.id } });
      message.replaceChildren("Export started: ", h("a", { href: `/jobs/${job.id}` }, `job ${job.id.slice(0, 8)}`),
        " (the zip downloads from there when it is done).");
      message.hidden = false;
    } catch (err) {
      message.error(err);
    } finally {
      button.disabled = false;
    }
  });
  return h("div", { class: "bids-export" }, button, " ", message);
}

export async function subjectPage(root, { canEdit }, subjectId) {
  const subject = await get(`/api/v1/subjects/${subjectId}`);
  document.title = `Subject ${subject.code} · Brain-guided RL platform`;
  const [sessions, recordings, classifiers, hfModels, calibrationJobs, rigs] = await Promise.all([
    all("/api/v1/sessions", { subject_id: subject.id }),
    all("/api/v1/recordings", { subject_id: subject.id }),
    all("/api/v1/classifiers", { subject_id: subject.id }),
    all("/api/v1/hf-models"),
    all("/api/v1/jobs", { kind: "eeg_calibration" }),
    all("/api/v1/rigs"),
  ]);
  const rigName = new Map(rigs.map((r) => [r.id, r.name]));
  const sessionIds = new Set(sessions.map((s) => s.id));
  const recordingIds = new Set(recordings.map((r) => r.id));
  const classifierJobs = new Set(classifiers.map((c) => c.job_id));
  const jobs = calibrationJobs.filter(
    (j) => recordingIds.has(j.config.recording_id) || classifierJobs.has(j.id),
  );
  const models = hfModels.filter((m) => sessionIds.has(m.session_id));

  root.append(
    h("p", { class: "crumbs" }, h("a", { href: "/subjects" }, "Subjects"), " / ", subject.code),
    h("h1", {}, `Subject ${subject.code}`),
    h("p", { class: "muted" }, `Registered ${fmtDateTime(subject.created_at)}`),
    notesForm(subject, canEdit),
    canEdit ? bidsExport(subject) : null,
    section(
      "Sessions",
      table(sessions, [
        { label: "When", cell: (s) => fmtDateTime(s.scheduled_at) },
        { label: "Kind", cell: (s) => s.kind },
        {
          label: "Live",
          cell: (s) => (offersLiveView(s, canEdit)
            ? h("a", { href: `/sessions/${s.id}/live` }, "Live view") : "–"),
        },
        { label: "Minutes", cell: (s) => s.duration_minutes },
        { label: "Rig", cell: (s) => rigName.get(s.rig_id) || "–" },
        { label: "Status", cell: (s) => statusBadge(s.status) },
        { label: "Notes", cell: (s) => s.notes },
      ], { empty: "No sessions." }),
    ),
    section(
      "Recordings",
      table(recordings, [
        { label: "File", cell: (r) => r.filename },
        { label: "Session", cell: (r) => `#${r.session_id}` },
        {
          label: "Validation",
          cell: (r) => [statusBadge(r.validation_status), r.validation_reason ? ` ${r.validation_reason}` : ""],
        },
        { label: "Synthetic", cell: (r) => (r.synthetic === null ? "–" : r.synthetic ? "yes" : "no") },
        { label: "Channels", cell: (r) => r.n_channels ?? "–" },
        { label: "Hz", cell: (r) => r.sfreq ?? "–" },
        { label: "Seconds", cell: (r) => fmtNumber(r.duration_s, 0) },
        { label: "Size", cell: (r) => fmtBytes(r.size_bytes) },
        { label: "", cell: (r) => downloadButton("Download", `/api/v1/recordings/${r.id}/file`, r.filename) },
      ], { empty: "No recordings." }),
      h("p", {}, h("a", { href: `/recordings?subject_id=${subject.id}` }, "Upload, calibrate or delete recordings")),
    ),
    section(
      "Classifiers",
      table(classifiers, [
        { label: "Name", cell: (c) => h("a", { href: `/classifiers/${c.id}` }, c.name) },
        { label: "Balanced accuracy", cell: (c) => fmtNumber(c.metrics.balanced_accuracy) },
        { label: "ROC AUC", cell: (c) => fmtNumber(c.metrics.roc_auc) },
        { label: "Made", cell: (c) => fmtDateTime(c.created_at) },
      ], { empty: "No classifiers." }),
    ),
    section(
      "Human-feedback models",
      table(models, [
        { label: "Name", cell: (m) => m.name },
        { label: "Task", cell: (m) => m.task.toUpperCase() },
        { label: "Labels", cell: (m) => m.n_labels ?? "–" },
        { label: "Made", cell: (m) => fmtDateTime(m.created_at) },
      ], { empty: "No human-feedback models from this subject's sessions." }),
    ),
    section(
      "Jobs",
      table(jobs, [
        { label: "Job", cell: (j) => shortId(j.id, `/jobs/${j.id}`) },
        { label: "Kind", cell: (j) => j.kind },
        { label: "Recording", cell: (j) => `#${j.config.recording_id}` },
        { label: "Status", cell: (j) => statusBadge(j.status) },
        { label: "Submitted", cell: (j) => fmtDateTime(j.created_at) },
      ], { empty: "No calibration jobs on this subject's recordings." }),
    ),
  );
}
