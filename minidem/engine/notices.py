"""What a user waiting for a slow step of the set-up is told: a law's ``prepare()``, a
kernel's compilation, the neighbour search compiled for the check of overlapping spheres.
One line, printed once the step has taken SLOW_NOTICE_S, so a long wait is never silent
and a short one says nothing."""

from __future__ import annotations

import contextlib

SLOW_NOTICE_S = 2.0


@contextlib.contextmanager
def notice_if_slow(notify, text: str):
    """Call ``notify(text)`` (from a timer thread) if the block runs longer than SLOW_NOTICE_S."""
    if notify is None:
        yield
        return
    import threading

    timer = threading.Timer(SLOW_NOTICE_S, notify, args=(f"{text} ({SLOW_NOTICE_S:g} s so far)",))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        timer.join()  # a notice being printed is finished before the block's caller goes on
