"""A spawned worker process on the second core, for work that runs beside the main process:
training's held-out evaluations (``mpa_gym.agents.training.callbacks.EvalWorker``) and the report's
robustness sweep (``mpa_gym.agents.evaluation.evaluate.Background``).

What it guarantees, each tested with real processes and signals:

- it is spawned while SIGINT and SIGTERM are ignored, which a new interpreter inherits: a
  Ctrl-C at the terminal reaches the whole process group, and the main process decides what
  happens (it records what it was waiting for, or cancels the worker);
- it exits when its parent dies, a SIGKILLed one too (the parent's sentinel: the task queue's
  pipe stays open in the worker itself, so it would otherwise wait for ever);
- a worker that dies, or cannot start (a ``__main__`` a spawned interpreter cannot import,
  such as a script read from stdin), fails its calls: ``Worker.result`` raises
  ``WorkerStopped`` and the caller runs the call itself. It is a
  ``concurrent.futures.ProcessPoolExecutor``, where ``multiprocessing.Pool`` would respawn it
  for ever and its caller would hang;
- a Ctrl-C while the main process waits for it stops it: nobody will use its answer.
"""
from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any


def ignore_stop_signals() -> None:
    """SIGINT and SIGTERM ignored in this process."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)


def _start(initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
    ignore_stop_signals()  # already, unless spawned from a thread other than the main one
    parent = multiprocessing.parent_process()
    if parent is not None:
        def watch() -> None:
            multiprocessing.connection.wait([parent.sentinel])
            os._exit(0)

        threading.Thread(target=watch, daemon=True).start()
    if initializer is not None:
        initializer(*initargs)


def _ready() -> None:
    """A first task, so that the worker is spawned when the ``Worker`` is made."""


class WorkerStopped(Exception):
    """The worker exited (it died, or could not start) before it answered a call."""


class Worker:
    """One spawned worker process; ``initializer(*initargs)`` runs in it before its first call."""

    def __init__(self, initializer: Callable[..., None] | None = None,
                 initargs: tuple[Any, ...] = ()) -> None:
        before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        # only the main thread may set handlers, and only one set from Python (not None) can
        # be put back
        ignore = (threading.current_thread() is threading.main_thread()
                  and None not in before.values())
        if ignore:
            ignore_stop_signals()
        try:
            self._pool = ProcessPoolExecutor(1, multiprocessing.get_context("spawn"),
                                             initializer=_start,
                                             initargs=(initializer, initargs))
            self._pool.submit(_ready)
        finally:
            if ignore:
                for s, h in before.items():
                    signal.signal(s, h)

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Future[Any]:
        """Start ``fn(*args, **kwargs)`` in the worker; returns its ``Future`` (for
        :meth:`result`), failed at once if the worker has already stopped."""
        try:
            return self._pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool as e:
            failed: Future[Any] = Future()
            failed.set_exception(e)
            return failed

    def result(self, future: Future[Any]) -> Any:
        """The call's result, or its error. ``WorkerStopped`` if the worker exited before it
        answered; a Ctrl-C while waiting stops the worker (nobody will wait for it) and goes on."""
        try:
            return future.result()
        except BrokenProcessPool as e:
            # with a cause the answer came and could not be read (an error that does not
            # unpickle): the call ran, and running it again is not a fall-back
            if e.__cause__ is not None:
                raise
            raise WorkerStopped(str(e)) from e
        except KeyboardInterrupt:
            self.terminate()
            raise

    def pids(self) -> list[int]:
        """The process id of the worker while it runs."""
        return [p.pid for p in self._processes() if p.exitcode is None]

    def close(self, wait: bool = True) -> None:
        """Let the worker finish what it was given and reap it (``wait``), or :meth:`terminate`
        it."""
        if not wait:
            self.terminate()
            return
        try:
            self._pool.shutdown(wait=True)
        except KeyboardInterrupt:  # a Ctrl-C while waiting: nobody waits for it any more
            self.terminate()
            raise

    def terminate(self) -> None:
        """Stop the worker now, its call under way too, and reap it."""
        for p in self._processes():  # Python 3.14's kill_workers(), before 3.14
            p.kill()  # SIGKILL: it ignores SIGTERM; nothing once it has been reaped
        self._pool.shutdown(wait=True, cancel_futures=True)

    def _processes(self) -> list[Any]:
        return list((self._pool._processes or {}).values())
