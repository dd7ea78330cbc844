"""`interrupts_held`: Ctrl-C and SIGTERM noted, not raised, while a short block runs, then raised.

Two blocks must not be cut in the middle: a library import whose optional imports catch
``BaseException`` (trimesh: an interrupt landing there was swallowed and the run went on), and the
renames that put a set of outputs in place (`neuralrt.io.files.written_together`: cut there, half
the set was new). The signals' Python handlers only note them meanwhile (masking the main thread
was not enough: torch's and numba's threads took the signal, and Python still ran the handler in
the main thread, inside the block); one that came is raised again once the block ends, through
the handler the block found (KeyboardInterrupt, or the CLI's SIGTERM stop).
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["interrupts_held"]


@contextlib.contextmanager
def interrupts_held():
    """Run the block with SIGINT and SIGTERM held (see the module); off the main thread, where no
    signal handler runs, the block just runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    held = {s: signal.signal(s, lambda signum, frame: came.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in held.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        if came:
            signal.raise_signal(came[0])
