// Live session (operator): frames, current action, per-action decoded feedback beside the
// oracle label, running accuracy, labels vs budget, latency per action, start and stop.

import { get, post } from "../api.js";
import { field, fmtNumber, h, messageBox, statusBadge } from "../dom.js";
import { followEvents, followFrames } from "../frames.js";

const ACTIONS = ["forward", "turn left", "turn right"];
const label = (correct) => (correct === null || correct === undefined ? "–" : correct ? "correct" : "error");

function startForm(session, message, onStarted) {
  const classifier = h("input", { type: "number", min: 1, name: "classifier_id" });
  const actions = h("input", { type: "number", min: 1, name: "n_actions", value: 60 });
  const budget = h("input", { type: "number", min: 1, name: "label_budget", value: 1000 });
  const accelerated = h("input", { type: "checkbox", name: "accelerated", checked: true });
  const form = h(
    "form",
    { class: "inline-form", "aria-label": "Start the session" },
    session.kind === "calibration" ? null : field("Classifier id", classifier),
    field("Actions", actions),
    session.kind === "online" ? field("Label budget", budget) : null,
    h("label", { class: "check" }, accelerated, " Accelerated (virtual subject)"),
    h("button", { type: "submit", class: "btn primary" }, "Start"),
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    message.clear();
    const body = { accelerated: accelerated.checked, n_actions: Number(actions.value) };
    if (session.kind !== "calibration") body.classifier_id = Number(classifier.value);
    if (session.kind === "online") body.label_budget = Number(budget.value);
    try {
      await post(`/api/v1/sessions/${session.id}/start`, body);
      onStarted();
    } catch (err) {
      message.error(err);
    }
  });
  return form;
}

export async function livePage(root, { canEdit }, sessionId) {
  const session = await get(`/api/v1/sessions/${sessionId}`);
  document.title = `Session ${session.id} live · Brain-guided RL platform`;
  const message = messageBox();
  const img = h("img", { class: "live-frame", alt: "The robot's view", id: "live-frame" });
  const connection = h("span", { class: "muted", id: "live-connection" }, "connecting…");
  const current = h("p", { class: "current-action", id: "current-action", "aria-live": "polite" }, "No action yet.");
  const stats = h("dl", { class: "stats", id: "live-stats" });
  const rows = h("tbody", { id: "live-actions" });
  const steps = new Map(); // step -> {marker, decision}: the view's history, kept on reconnect

  function statRow(name, value) {
    return [h("dt", {}, name), h("dd", {}, value)];
  }
  function renderRow(step) {
    const { marker, decision } = steps.get(step);
    const latency = decision && decision.epoch_end_ts !== null && decision.epoch_end_ts !== undefined
      ? `${fmtNumber((decision.decided_ts - decision.epoch_end_ts) * 1000, 1)} ms` : "–";
    const decoded = !decision ? "pending" : decision.status === "ok" ? decision.feedback : `rejected`;
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

  let stopButton = null;
  let form = null;
  function showControls(active) {
    if (stopButton) stopButton.hidden = !active;
    if (form) form.hidden = active || session.status !== "scheduled";
  }
  async function refresh() {
    let live;
    try {
      live = await get(`/api/v1/sessions/${sessionId}/live`);
    } catch {
      stats.replaceChildren(...statRow("Status", "not started"));
      showControls(false);
      return;
    }
    const latency = live.latency.epoch_end_to_decision || {};
    stats.replaceChildren(
      ...statRow("Status", statusBadge(live.run.status)),
      ...statRow("Actions", String(live.markers)),
      ...statRow("Running accuracy", live.running_accuracy === null ? "–" : `${fmtNumber(live.running_accuracy * 100, 1)} %`),
      ...statRow("Labels", live.label_budget ? `${live.labels} / ${live.label_budget}` : String(live.labels)),
      ...statRow("Decision latency p50 / p99", latency.n ? `${latency.p50_ms} / ${latency.p99_ms} ms` : "–"),
    );
    showControls(["queued", "running"].includes(live.run.status));
  }
  const timer = setInterval(refresh, 1000);

  const frames = followFrames(sessionId, img, {
    onStatus: (text) => { connection.textContent = text; },
    onFrame: (frame) => {
      const marker = frame.state.last_marker;
      if (marker) {
        current.textContent = `Now: ${ACTIONS[marker.action]} (oracle: ${label(marker.correct)}), sim step ${marker.step}`;
      }
    },
  });
  window.bgrlLiveView = { frames, steps }; // for the browser tests: drop the connection

  const controls = h("div", { class: "live-controls" });
  if (canEdit) {
    stopButton = h("button", { type: "button", class: "btn" }, "Stop");
    stopButton.addEventListener("click", async () => {
      message.clear();
      try {
        await post(`/api/v1/sessions/${sessionId}/stop`);
        message.show("Stop requested: the session ends after the current action.");
      } catch (err) {
        message.error(err);
      }
    });
    form = startForm(session, message, () => message.show("Session started."));
    controls.append(stopButton, form);
  }
  await refresh();
  addEventListener("pagehide", () => {
    frames.stop(); stopMarkers(); stopDecisions(); clearInterval(timer);
  });
  root.append(
    h("h1", {}, `Session ${session.id} live (${session.kind})`),
    h("p", {}, h("a", { href: `/sessions/${session.id}/display`, target: "_blank" }, "Open the subject display"), " · frames: ", connection),
    controls,
    message,
    h("div", { class: "live-grid" },
      h("div", {}, img, current),
      h("div", {}, stats)),
    h("h2", {}, "Actions"),
    h("table", { class: "grid" },
      h("thead", {}, h("tr", {}, ["Step", "Action", "Oracle", "Decoded", "p(error)", "Latency"].map((c) => h("th", { scope: "col" }, c)))),
      rows),
  );
}
