"""What a control loop on a general-purpose OS does to hold its rate (``mpa-gym rollout``,
``mpa-gym emulate``; ``--realtime`` adds the real-time priority).

- **Scheduling.** A loop that sleeps until its deadline is woken when the scheduler gets round to
  it; on a loaded machine that is milliseconds late, and the period overruns. ``SCHED_FIFO``
  (POSIX real-time priority) runs it as soon as it is runnable. It needs the privilege
  (root, ``CAP_SYS_NICE`` or an ``rtprio`` limit in ``/etc/security/limits.conf``); without it the
  loop runs at normal priority and the returned report says so.
- **Garbage collection.** CPython's cyclic collector pauses the interpreter for a time that
  grows with the heap: with torch imported and a rollout's records accumulating, a full
  collection can pause the loop for longer than the device's 40 ms watchdog, which then
  vents the rig. It is frozen (``gc.freeze``) and disabled for the loop,
  always (``sched_fifo`` or not), and re-enabled after. The loop allocates no reference
  cycles, so nothing accumulates meanwhile.

Memory locking (``mlockall``) is left out: with torch loaded it would pin hundreds of MB.
"""

from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def realtime(priority: int = 20, sched_fifo: bool = True) -> Iterator[dict[str, Any]]:
    """The collector off and, with ``sched_fifo``, real-time scheduling (``SCHED_FIFO`` at
    ``priority``, 1…99, as far as permitted) for the ``with`` block; yields a report
    ``{"sched_fifo": bool, "gc_disabled": True, "notes": [...]}`` and restores the previous
    state on exit."""
    if not 1 <= priority <= 99:
        raise ValueError(f"priority={priority} is outside the allowed range [1, 99]")
    report: dict[str, Any] = {"sched_fifo": False, "gc_disabled": True, "notes": []}
    old_policy = old_param = None
    if sched_fifo and hasattr(os, "sched_setscheduler"):
        try:
            old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            report["sched_fifo"] = True
        except OSError as e:
            report["notes"].append(f"SCHED_FIFO not permitted ({e.strerror}): normal priority; "
                                   "grant CAP_SYS_NICE or an rtprio limit")
    elif sched_fifo:
        report["notes"].append("no SCHED_FIFO on this OS: normal priority")
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield report
    finally:
        if was_enabled:
            gc.enable()
        gc.unfreeze()
        if report["sched_fifo"] and old_policy is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, old_policy, old_param)
