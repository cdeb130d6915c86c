// Live job progress: the API's job events websocket, with polling if it drops.

import { get, jobEventsSocket } from "./api.js";

export const FINAL = new Set(["succeeded", "failed", "cancelled"]);
const POLL_MS = 2000;

/**
 * Call ``onUpdate(job)`` whenever the job changes until it is final. The websocket sends the
 * job (as GET /api/v1/jobs/{id}) on every change; if it closes early, poll instead.
 * Returns a function that stops watching.
 */
export function watchJob(jobId, onUpdate) {
  let stopped = false;
  let socket = null;
  let timer = null;

  async function poll() {
    if (stopped) return;
    try {
      const job = await get(`/api/v1/jobs/${encodeURIComponent(jobId)}`);
      onUpdate(job);
      if (FINAL.has(job.status)) return;
    } catch {
      // transient: try again
    }
    timer = setTimeout(poll, POLL_MS);
  }

  let last = null;
  socket = jobEventsSocket(jobId);
  socket.addEventListener("message", (event) => {
    last = JSON.parse(event.data);
    onUpdate(last);
  });
  socket.addEventListener("close", () => {
    if (!stopped && !(last && FINAL.has(last.status))) timer = setTimeout(poll, POLL_MS);
  });

  return () => {
    stopped = true;
    clearTimeout(timer);
    if (socket && socket.readyState <= 1) socket.close();
  };
}

/** A <progress> bar with its percentage beside it; ``set(job)`` updates both. */
export function progressBar(job) {
  const bar = document.createElement("progress");
  bar.max = 1;
  const text = document.createElement("span");
  text.className = "pct";
  const wrapper = document.createElement("span");
  wrapper.className = "progress";
  wrapper.append(bar, text);
  wrapper.set = (j) => {
    bar.value = j.progress;
    const pct = `${Math.round(j.progress * 100)}%`;
    bar.setAttribute("aria-label", `Job ${j.id.slice(0, 8)} progress ${pct}`);
    bar.dataset.status = j.status;
    text.textContent = pct;
  };
  wrapper.set(job);
  return wrapper;
}
