"""Failed-login limiter: too many failures for one account from one address are refused."""

from __future__ import annotations

import math
import threading
import time
from collections import deque


class LoginLimiter:
    """Counts failed logins per key (address and account) in a sliding window.

    In memory, per api process: a deployment running several api processes allows
    ``max_failures`` per process.
    """

    def __init__(self, max_failures: int, window_s: float, max_keys: int = 100_000) -> None:
        self.max_failures = max_failures
        self.window_s = window_s
        self.max_keys = max_keys
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, key: str, now: float) -> deque[float]:
        times = self._failures.get(key, deque())
        while times and times[0] <= now - self.window_s:
            times.popleft()
        return times

    def retry_after(self, key: str) -> int:
        """Seconds until ``key`` may try again (0: it may now)."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(key, now)
            if len(times) < self.max_failures:
                return 0
            return max(1, math.ceil(times[0] + self.window_s - now))

    def failed(self, key: str) -> None:
        """Record a failed attempt."""
        now = time.monotonic()
        with self._lock:
            if len(self._failures) >= self.max_keys:
                self._forget_stale(now)
            times = self._recent(key, now)
            times.append(now)
            self._failures[key] = times

    def succeeded(self, key: str) -> None:
        """Forget the failures of ``key`` after a successful login."""
        with self._lock:
            self._failures.pop(key, None)

    def _forget_stale(self, now: float) -> None:
        for key in list(self._failures):
            if not self._recent(key, now):
                del self._failures[key]
        while len(self._failures) >= self.max_keys:
            self._failures.pop(next(iter(self._failures)))
