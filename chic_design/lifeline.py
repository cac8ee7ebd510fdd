"""Worker processes that end with the process that started them, even when it is SIGKILLed.

Kept tiny on purpose: a spawned worker imports this module before anything
else (it holds the pool's initializer), so the protection starts within
Python's start-up time, not after the CAD or plotting imports.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time


def die_with_parent(parent_pid: int) -> None:
    """Worker initializer: end this worker when the build process ends, even by SIGKILL.

    On Linux the kernel sends SIGKILL on the parent's death (``PR_SET_PDEATHSIG``);
    elsewhere, and as a second line, a daemon thread polls the parent pid. A
    worker left behind would keep the caller's stderr pipe open (and a caller
    waiting for it would hang).
    """
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass

    def watch():
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(0.5)

    if os.getppid() != parent_pid:  # the parent died before the prctl took effect
        os._exit(1)
    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
