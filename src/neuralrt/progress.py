"""Progress bars on standard error: tqdm's (a widget in a notebook), redrawn less often where
standard error is no terminal (a batch job's log, ``2> log.txt``), where each redraw is another
line's worth of bytes: a 70-second training wrote ~700 of them, joined by carriage returns."""

from __future__ import annotations

import os
import sys
import time

__all__ = ["progress_bar", "redraw_due", "LOG_REDRAW_SECONDS"]

LOG_REDRAW_SECONDS = 30.0  # between redraws into a log (tqdm's own TQDM_MININTERVAL, where set, wins)


def progress_bar(**kwargs):
    """``tqdm.auto.tqdm(**kwargs)``, drawn every `LOG_REDRAW_SECONDS` where its stream is no terminal."""
    from tqdm.auto import tqdm
    from tqdm.autonotebook import tqdm as chosen
    from tqdm.std import tqdm as text_bar

    stream = kwargs.get("file") or sys.stderr
    if chosen is text_bar and "TQDM_MININTERVAL" not in os.environ and not _is_terminal(stream):
        kwargs.setdefault("mininterval", LOG_REDRAW_SECONDS)
        kwargs.setdefault("maxinterval", LOG_REDRAW_SECONDS)  # (tqdm's monitor thread forced one every 10 s)
    return tqdm(**kwargs)


def redraw_due(bar) -> bool:
    """Whether a new postfix should redraw ``bar`` now (``set_postfix(refresh=...)``): on a terminal,
    yes; into a log, once its interval has passed (tqdm redraws on `update` alone)."""
    return time.time() - bar.last_print_t >= bar.mininterval


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError, OSError):  # (closed, or a stand-in without isatty)
        return False
