// Subject display: the robot's frames full screen, nothing else. Reports when the frame of
// each action is actually on screen (POST /api/v1/sessions/{id}/frames-shown).

import { get, post } from "../api.js";
import { h } from "../dom.js";
import { followEvents, followFrames, whenStarted } from "../frames.js";

export async function displayPage(root, _context, sessionId) {
  document.body.classList.add("subject-display");
  document.title = `Session ${sessionId} · display`;
  const img = h("img", { class: "display-frame", alt: "", id: "display-frame" });
  root.replaceChildren(img);
  const runStep = new Map(); // "<sim session>:<sim step>" -> the run's step
  const shown = new Map(); // same key -> when its frame was first on screen (ISO)
  const reported = new Set();

  async function report() {
    for (const [key, shownAt] of shown) {
      const step = runStep.get(key);
      if (step === undefined || reported.has(key)) continue;
      reported.add(key);
      try {
        await post(`/api/v1/sessions/${sessionId}/frames-shown`, { step, shown_at: shownAt });
      } catch {
        // already reported (409) or the run ended: nothing to retry
      }
    }
  }
  // opened before the session starts (the usual order), it waits for the run to exist
  const session = await get(`/api/v1/sessions/${sessionId}`);
  whenStarted(get, session, () => {
    followEvents(get, sessionId, "markers", (items) => {
      for (const m of items) runStep.set(`${m.sim_session_id}:${m.sim_step}`, m.step);
      report();
    }, 500);
    followFrames(sessionId, img, {
      onFrame: (frame) => {
        const marker = frame.state.last_marker;
        if (!marker) return;
        const key = `${marker.session_id}:${marker.step}`;
        if (!shown.has(key)) {
          shown.set(key, new Date().toISOString());
          report();
        }
      },
    });
  });
}
