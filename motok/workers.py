"""Worker processes that do not outlive their parent.

A process pool's workers wait on a queue whose other end every worker also holds (they are
forked from one parent), so when the parent is killed outright (``kill -9``, the OOM killer) no
worker ever sees the queue close: each stays, holding its memory (about 200 MB for
``preprocess``), until someone finds it. :func:`die_with_parent` is the pool's initializer: on
Linux it asks the kernel to kill the worker when its parent dies (``PR_SET_PDEATHSIG``); where
that is not available, a daemon thread checks every second whether the parent is still there.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _ask_kernel() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent: int) -> None:
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(1)


def die_with_parent(parent: int) -> None:
    """Pool initializer: end this worker when the process ``parent`` ends, and leave Ctrl-C (which
    the terminal sends to the whole process group) to the parent, which stops the pool and says
    so in one line, instead of every worker printing a traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if not _ask_kernel():
        threading.Thread(target=_watch, args=(parent,), daemon=True, name="motok-parent-watch").start()
    # The parent may have died between the fork and the request above: then nobody will signal us.
    if os.getppid() != parent:
        os._exit(1)
