"""Optuna's trial log around a stop the user asked for, shared by ``mpa-gym tune`` and
``mpa-gym tune-baselines``. Light: Optuna's logging only, no training stack."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator


class _SignalledTrials(logging.Filter):
    """Drops Optuna's failed-trial record (a traceback) when a signal stopped the trial (an
    exception with a ``signum``: the CLI's ``Interrupted``, training's ``TrainingStopped``;
    or Ctrl-C's KeyboardInterrupt): that is a stop the user asked for, said in one line, not a
    fault. A NaN guard's stop (``signum`` None) keeps its traceback."""

    signalled = False

    def filter(self, record: logging.LogRecord) -> bool:
        err = record.exc_info[1] if record.exc_info else None
        if isinstance(err, KeyboardInterrupt) or getattr(err, "signum", None) is not None:
            self.signalled = True
            return False
        # and the "failed with value None" line that follows it
        return not (self.signalled and "failed with value" in record.getMessage())


@contextlib.contextmanager
def quiet_signalled_trials() -> Iterator[None]:
    """Within: a trial stopped by a signal (Ctrl-C, SIGTERM) is not logged by Optuna as a
    failure with its traceback; the command says the stop in one line."""
    quiet = _SignalledTrials()
    logger = logging.getLogger("optuna.study._optimize")
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)
