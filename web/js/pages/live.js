// Live session (operator): frames, current action, per-action decoded feedback beside the
// oracle label, running accuracy, labels vs budget, latency per action, start and stop.

import { all, get, post } from "../api.js";
import { field, fmtNumber, h, messageBox, oneAtATime, statusBadge } from "../dom.js";
import { followEvents, followFrames, whenStarted } from "../frames.js";
import { jobKinds, stage2Methods } from "./jobform.js";

const ACTIONS = ["forward", "turn left", "turn right"];
const label = (correct) => (correct === null || correct === undefined ? "–" : correct ? "correct" : "error");

const DEFAULT_ACTIONS = { calibration: "600", test: "200", online: "up to 3 per label" };

/** Whether the dashboard links a session's live view and subject display: once it has
 *  started, and before that for staff, who start it there (a cancelled one never runs). */
export function offersLiveView(session, canEdit) {
  if (!["calibration", "test", "online"].includes(session.kind)) return false;
  if (session.status === "scheduled") return canEdit;
  return session.status !== "cancelled";
}

/** Links from a session to what it made: its live run's job, recording, follow-up
 *  calibration or online job, classifier and human-feedback model; for staff, once an
 *  online session has ended, its replay (the job form, prefilled). */
function sessionLinks(session, live, canEdit, classifiers = []) {
  const run = live.run;
  const links = [];
  if (run.job_id) links.push(["Run", h("a", { href: `/jobs/${run.job_id}` }, `live job ${run.job_id.slice(0, 8)}`)]);
  if (run.recording_id) links.push(["Recording", h("a", { href: `/recordings?recording=${run.recording_id}` }, `recording #${run.recording_id}`)]);
  if (run.follow_up_job_id) {
    links.push(["Follow-up job", h("a", { href: `/jobs/${run.follow_up_job_id}` }, `job ${run.follow_up_job_id.slice(0, 8)}`)]);
  }
  for (const c of classifiers) links.push(["Classifier", h("a", { href: `/classifiers/${c.id}` }, c.name)]);
  if (run.hf_model_id) links.push(["π_HF model", h("a", { href: "/models" }, `HF model #${run.hf_model_id}`)]);
  if (canEdit && session.kind === "online" && ENDED.has(run.status)) {
    links.push(["Replay", h("a", { href: `/jobs?new=session_replay&session_id=${session.id}#job-form` },
      "Replay this session…")]);
  }
  return links;
}

const ENDED = new Set(["completed", "stopped"]); // a failed run may be resumed

/** What the banner says of a run that has ended (null while it goes on: the messages of
 *  the operator's actions, "Session started.", "Stop requested", stay until then). */
function runBanner(live) {
  const { status, error } = live.run;
  if (status === "completed") return [`Session completed: ${live.markers} actions recorded.`, "ok"];
  if (status === "failed") return [`The session's run failed${error ? `: ${error}` : ""}.`, "error"];
  if (status === "stopped") return [`Session stopped after ${live.markers} actions.`, "ok"];
  return null;
}

function startForm(session, classifiers, methods, message, onStarted) {
  const classifier = h("select", { name: "classifier_id" },
    classifiers.map((c) => h("option", { value: c.id },
      `${c.name} (#${c.id}, balanced accuracy ${fmtNumber(c.metrics.balanced_accuracy)})`)));
  const actions = h("input", { type: "number", min: 1, max: 100000, name: "n_actions" });
  const budget = h("input", { type: "number", min: 1, max: 100000, name: "label_budget", value: 1000 });
  const hfMethod = h("select", { name: "hf_method" }, h("option", { value: "" }, "Recommended (default)"),
    methods.map((m) => h("option", { value: m }, m === "paper" ? "paper (the paper's Fhat)" : m)));
  const channel = h("select", { name: "label_channel" },
    h("option", { value: "" }, "Default: soft if the classifier is calibrated, else hard"),
    h("option", { value: "soft" }, "Soft: the calibrated likelihood ratio"),
    h("option", { value: "hard" }, "Hard: the thresholded feedback (the paper)"));
  const accelerated = h("input", { type: "checkbox", name: "accelerated", checked: true });
  const needsClassifier = session.kind !== "calibration";
  const submit = h("button", { type: "submit", class: "btn primary" }, "Start");
  const fields = {
    classifier_id: needsClassifier
      ? field("Classifier", classifier, classifiers.length ? "" : "This subject has no classifier yet: run a calibration session first.")
      : null,
    n_actions: field("Actions", actions, `empty: ${DEFAULT_ACTIONS[session.kind]}`),
    label_budget: session.kind === "online" ? field("Label budget", budget) : null,
    hf_method: session.kind === "online"
      ? field("Stage-2 method", hfMethod, "How pi_HF is learned from the labels (docs/stage2.md).")
      : null,
    label_channel: session.kind === "online"
      ? field("Label channel", channel, "How each decoded label enters Fhat (docs/live.md).")
      : null,
  };
  submit.disabled = needsClassifier && !classifiers.length;
  const form = h(
    "form",
    { class: "inline-form", "aria-label": "Start the session" },
    Object.values(fields),
    h("label", { class: "check" }, accelerated, " Accelerated (virtual subject)"),
    submit,
  );
  form.addEventListener("submit", oneAtATime([submit], async () => {
    message.clear();
    for (const f of Object.values(fields)) f?.setError("");
    const body = { accelerated: accelerated.checked };
    if (actions.value) body.n_actions = Number(actions.value);
    if (needsClassifier) body.classifier_id = Number(classifier.value);
    if (session.kind === "online") body.label_budget = Number(budget.value);
    if (session.kind === "online" && hfMethod.value) body.hf_method = hfMethod.value;
    if (session.kind === "online" && channel.value) body.label_channel = channel.value;
    try {
      await post(`/api/v1/sessions/${session.id}/start`, body);
      onStarted();
      return "leaving"; // started: the form is hidden for good
    } catch (err) {
      for (const [name, text] of Object.entries(err.fields || {})) fields[name]?.setError(text);
      message.error(err);
      return null;
    }
  }));
  return form;
}

export async function livePage(root, { canEdit }, sessionId) {
  const session = await get(`/api/v1/sessions/${sessionId}`);
  document.title = `Session ${session.id} live · Brain-guided RL platform`;
  const message = messageBox();
  const img = h("img", { class: "live-frame", alt: "The robot's view", id: "live-frame", hidden: true });
  const noFrame = h("p", { class: "no-frame" }, "The robot's frames appear here while the session runs.");
  const connection = h("span", { class: "muted", id: "live-connection" }, "connecting…");
  const current = h("p", { class: "current-action", id: "current-action", "aria-live": "polite" }, "No action yet.");
  const stats = h("dl", { class: "stats", id: "live-stats" });
  const rows = h("tbody", { id: "live-actions" });
  const made = h("dl", { class: "facts", id: "live-links", hidden: true });
  let banner = null; // the banner's text: changed only when the run's state changes
  let frames = null; // the frame stream while the run goes on
  let linked = "";
  const steps = new Map(); // step -> {marker, decision}: the view's history, kept on reconnect

  function statRow(name, value) {
    return [h("dt", {}, name), h("dd", {}, value)];
  }
  function renderRow(step) {
    const { marker, decision } = steps.get(step);
    const latency = decision && decision.epoch_end_ts !== null && decision.epoch_end_ts !== undefined
      ? `${fmtNumber((decision.decided_ts - decision.epoch_end_ts) * 1000, 1)} ms` : "–";
    // a calibration session only records: its epochs train the classifier afterwards
    const undecoded = session.kind === "calibration" ? "not decoded (calibration)" : "pending";
    const decoded = !decision ? undecoded : decision.status === "ok" ? decision.feedback : `rejected`;
    const agree = decision && decision.status === "ok" && marker.oracle_correct !== null
      ? (decision.feedback === "correct") === marker.oracle_correct : null;
    const tr = h(
      "tr",
      { "data-step": step, class: agree === false ? "miss" : "" },
      h("td", {}, String(step)),
      h("td", {}, ACTIONS[marker.action]),
      h("td", {}, label(marker.oracle_correct)),
      h("td", { class: "decoded", title: decision && decision.reason ? decision.reason : "" }, decoded),
      h("td", {}, decision && decision.p_error !== null ? fmtNumber(decision.p_error, 3) : "–"),
      h("td", {}, latency),
    );
    const old = rows.querySelector(`tr[data-step="${step}"]`);
    if (old) old.replaceWith(tr);
    else rows.prepend(tr);
  }

  let stopButton = null;
  let resumeButton = null;
  let form = null;
  let resumeBody = {};
  function showControls(live) {
    // the API resumes a failed run, or one whose job ended without finishing it
    const jobActive = ["queued", "running"].includes(live.job_status);
    const active = ["queued", "running"].includes(live.run.status) && jobActive;
    const resumable = live.run.status === "failed" || (["queued", "running"].includes(live.run.status) && !jobActive);
    if (stopButton) stopButton.hidden = !active;
    if (resumeButton) resumeButton.hidden = !resumable;
    if (form) form.hidden = true; // started
    const classifierId = live.run.options.classifier_id;
    resumeBody = classifierId ? { classifier_id: classifierId } : {};
  }
  async function refresh() {
    let live;
    try {
      live = await get(`/api/v1/sessions/${sessionId}/live`);
    } catch {
      return; // transient: the next refresh shows it
    }
    const latency = live.latency.epoch_end_to_decision || {};
    stats.replaceChildren(
      ...statRow("Status", statusBadge(live.run.status)),
      ...statRow("Actions", String(live.markers)),
      ...statRow("Running accuracy", live.running_accuracy === null ? "–" : `${fmtNumber(live.running_accuracy * 100, 1)} %`),
      ...statRow("Labels", live.label_budget ? `${live.labels} / ${live.label_budget}` : String(live.labels)),
      ...statRow("Decision latency p50 / p99", latency.n ? `${fmtNumber(latency.p50_ms, 1)} / ${fmtNumber(latency.p99_ms, 1)} ms` : "–"),
      ...(live.run.error || live.job_error ? statRow("Error", live.run.error || live.job_error) : []),
    );
    showControls(live);
    if (ENDED.has(live.run.status) && frames) {
      frames.stop(); // an ended run streams no more frames (none are kept)
      frames = null;
      connection.textContent = "none (the session has ended)";
      noFrame.textContent = "The session has ended; its frames are not kept.";
    }
    const [text, kind] = runBanner(live) || [null, "ok"];
    if (text && text !== banner) {
      banner = text;
      message.show(text, kind);
    }
    await showLinks(live);
  }

  /** Once the run has something to link (its job, recording, follow-up job, models). */
  async function showLinks(live) {
    const key = [live.run.job_id, live.run.recording_id, live.run.follow_up_job_id, live.run.hf_model_id,
      live.run.status].join();
    if (key === linked) return;
    linked = key;
    let classifiers = [];
    if (live.run.follow_up_job_id && session.kind === "calibration") {
      try {
        classifiers = (await all("/api/v1/classifiers", { subject_id: session.subject_id }))
          .filter((c) => c.job_id === live.run.follow_up_job_id);
      } catch {
        // the next refresh asks again
      }
      if (!classifiers.length) linked = ""; // its calibration job has not made it yet
    }
    const links = sessionLinks(session, live, canEdit, classifiers);
    made.hidden = !links.length;
    made.replaceChildren(...links.flatMap(([name, link]) => [h("dt", {}, name), h("dd", {}, link)]));
  }

  // Until the session has started there is no run to follow (the API answers 404): wait
  // for its status to change (here or elsewhere), then follow its rows, figures and frames.
  let stopFollowing = null;
  function follow() {
    if (stopFollowing) return;
    const stopMarkers = followEvents(get, sessionId, "markers", (items) => {
      for (const marker of items) {
        steps.set(marker.step, { ...(steps.get(marker.step) || {}), marker });
        renderRow(marker.step);
      }
    });
    const stopDecisions = followEvents(get, sessionId, "decisions", (items) => {
      for (const decision of items) {
        const entry = { ...(steps.get(decision.step) || {}), decision };
        steps.set(decision.step, entry);
        if (entry.marker) renderRow(decision.step); // else drawn when its marker arrives
      }
    });
    const timer = setInterval(refresh, 1000);
    frames = followFrames(sessionId, img, {
      onStatus: (text) => { connection.textContent = text; },
      onFrame: (frame) => {
        img.hidden = false;
        noFrame.remove();
        const marker = frame.state.last_marker;
        if (marker) {
          current.textContent = `Now: ${ACTIONS[marker.action]} (oracle: ${label(marker.correct)}), sim step ${marker.step}`;
        }
      },
    });
    window.bgrlLiveView = { frames, steps }; // for the browser tests: drop the connection
    stopFollowing = () => {
      frames?.stop(); stopMarkers(); stopDecisions(); clearInterval(timer);
    };
    return refresh();
  }

  const controls = h("div", { class: "live-controls" });
  if (canEdit) {
    stopButton = h("button", { type: "button", class: "btn", hidden: true }, "Stop");
    stopButton.addEventListener("click", oneAtATime([stopButton], async () => {
      message.clear();
      try {
        await post(`/api/v1/sessions/${sessionId}/stop`);
        message.show("Stop requested: the session ends after the current action.");
      } catch (err) {
        message.error(err);
      }
    }));
    resumeButton = h("button", { type: "button", class: "btn", hidden: true }, "Resume");
    resumeButton.addEventListener("click", oneAtATime([resumeButton], async () => {
      message.clear();
      try {
        await post(`/api/v1/sessions/${sessionId}/start`, resumeBody);
        message.show("Session resumed: it carries on from its last recorded action.");
        await refresh(); // hides Resume before it can be clicked again
      } catch (err) {
        message.error(err);
      }
    }));
    controls.append(stopButton, resumeButton);
    if (session.status === "scheduled") {
      const [classifiers, kinds] = await Promise.all([
        session.kind === "calibration" ? [] : all("/api/v1/classifiers", { subject_id: session.subject_id }),
        jobKinds(),
      ]);
      form = startForm(session, classifiers, stage2Methods(kinds), message, () => {
        banner = "Session started.";
        message.show(banner);
        form.hidden = true;
        stopWaiting();
        follow();
      });
      controls.append(form);
    }
  }
  const stopWaiting = whenStarted(get, session, follow);
  if (session.status === "scheduled") {
    stats.replaceChildren(...statRow("Status", "not started"));
    connection.textContent = "when the session starts";
  } else if (session.status === "cancelled") {
    stats.replaceChildren(...statRow("Status", statusBadge("cancelled")));
    connection.textContent = "none (cancelled)";
  }
  addEventListener("pagehide", () => {
    stopWaiting();
    if (stopFollowing) stopFollowing();
  });
  root.append(
    h("h1", {}, `Session ${session.id} live (${session.kind})`),
    h("p", {}, h("a", { href: `/sessions/${session.id}/display`, target: "_blank" }, "Open the subject display"), " · frames: ", connection),
    controls,
    message,
    h("div", { class: "live-grid" },
      h("div", {}, img, noFrame, current),
      h("div", {}, stats, made)),
    h("h2", {}, "Actions"),
    h("table", { class: "grid" },
      h("thead", {}, h("tr", {}, ["Step", "Action", "Oracle", "Decoded", "p(error)", "Latency"].map((c) => h("th", { scope: "col" }, c)))),
      rows),
  );
}
