// The robot's frames of a live session through the api's relay, reconnecting when dropped.

import { framesSocket } from "./api.js";

const RETRY_MS = [500, 1000, 2000, 4000];

/**
 * Show every relayed frame in ``img`` and call ``onFrame(message)`` after it is drawn.
 * ``onStatus(text)`` reports the connection. Reconnects with back-off until ``stop()``.
 */
export function followFrames(sessionId, img, { onFrame = () => {}, onStatus = () => {} } = {}) {
  let stopped = false;
  let socket = null;
  let failures = 0;
  let timer = null;

  function connect() {
    if (stopped) return;
    socket = framesSocket(sessionId);
    socket.addEventListener("open", () => onStatus("connected"));
    socket.addEventListener("message", async (event) => {
      const message = JSON.parse(event.data);
      if (message.type !== "frame" || !message.frame.data) return;
      failures = 0;
      img.src = `data:image/${message.frame.format};base64,${message.frame.data}`;
      try {
        await img.decode();
      } catch {
        return; // replaced by a newer frame before it was decoded
      }
      requestAnimationFrame(() => onFrame(message));
    });
    socket.addEventListener("close", () => {
      if (stopped) return;
      onStatus("reconnecting");
      timer = setTimeout(connect, RETRY_MS[Math.min(failures, RETRY_MS.length - 1)]);
      failures += 1;
    });
  }

  connect();
  return {
    stop() {
      stopped = true;
      clearTimeout(timer);
      if (socket && socket.readyState <= 1) socket.close();
    },
    drop() {
      if (socket) socket.close(); // tests: the view must reconnect and keep its history
    },
  };
}

/** Poll one kind of a session's live events from the last step seen; ``onItems(items)``. */
export function followEvents(get, sessionId, kind, onItems, everyMs = 700) {
  let next = 0;
  let stopped = false;
  let timer = null;
  async function poll() {
    if (stopped) return;
    try {
      for (;;) {
        const page = await get(`/api/v1/sessions/${sessionId}/events`, {
          kind, since_step: next, limit: 500,
        });
        if (page.items.length) {
          next = page.items[page.items.length - 1].step + 1;
          onItems(page.items);
        }
        if (page.items.length < 500) break;
      }
    } catch {
      // not started yet or a transient error: try again
    }
    timer = setTimeout(poll, everyMs);
  }
  poll();
  return () => {
    stopped = true;
    clearTimeout(timer);
  };
}

/**
 * Call ``onStarted()`` once ``session`` has a live run to follow: at once if it has left
 * "scheduled", else when a poll of the session (every ``everyMs``) finds it started here or
 * elsewhere. A cancelled session never starts. Returns a function that stops waiting.
 */
export function whenStarted(get, session, onStarted, everyMs = 2000) {
  let stopped = false;
  let timer = null;
  function check(status) {
    if (stopped || status === "cancelled") return;
    if (status !== "scheduled") {
      onStarted();
      return;
    }
    timer = setTimeout(async () => {
      let next = status;
      try {
        next = (await get(`/api/v1/sessions/${session.id}`)).status;
      } catch {
        // transient: ask again
      }
      check(next);
    }, everyMs);
  }
  check(session.status);
  return () => {
    stopped = true;
    clearTimeout(timer);
  };
}
