"""A process that dies with its parent, even when the parent is killed with SIGKILL.

Linux's ``PR_SET_PDEATHSIG`` asks the kernel to send a signal to this process when the
thread that created it ends; process groups alone do not survive a SIGKILL of the leader.
Every process ``bgrl up`` starts sets it, and so does every process those start (the
learner's run pool), so nothing is left listening or computing after a crash.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1
_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None
"""The C library, loaded at import: a child between fork and exec should not load it."""


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> bool:
    """Ask for ``sig`` when the parent ``parent_pid`` dies; True where the kernel has it.

    If the parent died before the request was made (this process was already adopted by
    another), ``sig`` is raised at once: the window between fork and the request is closed.
    Safe between fork and exec (the C library is loaded at import). Not Linux: False.
    """
    if _LIBC is None or _LIBC.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        return False
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)
    return True
