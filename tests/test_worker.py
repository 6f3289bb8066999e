"""The spawned worker process (mpa_gym.agents.worker) behind training's held-out evaluations and the
report's robustness sweep, with real processes and real signals: a worker that cannot start, a
killed worker, a killed parent, a Ctrl-C at the terminal, a cancel."""
from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from conftest import alive, children, default_sigint, wait_gone

from mpa_gym.agents.evaluation.evaluate import Background

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# a user's script: its functions are importable by the spawned worker (``__mp_main__``).
# argv: the nap [s]; "wait" waits for the call at once, else the script sleeps
SCRIPT = textwrap.dedent("""
    import os, sys, time
    from mpa_gym.agents.evaluation.evaluate import Background

    def nap_then_pid(s):
        time.sleep(s)
        return os.getpid()

    if __name__ == "__main__":
        call = Background("a nap", nap_then_pid, float(sys.argv[1]))
        print(*call._worker.pids(), flush=True)
        if sys.argv[2:] == ["wait"]:
            call.result()
        try:
            time.sleep(600)
        except KeyboardInterrupt:
            print("interrupted; the worker answered", call.result(), flush=True)
""")


def started_then_pid(path, nap_s):
    """A call that says it has started (``path``), naps, and returns its process's id."""
    open(path, "w").close()
    time.sleep(nap_s)
    return os.getpid()


def _started(path, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not os.path.exists(path):
        assert time.monotonic() < deadline, "the worker's call did not start"
        time.sleep(0.02)


def _reaped(pid):
    return not alive(pid) and pid not in children(os.getpid())


def _script(tmp_path, *args, **kw):
    path = tmp_path / "user_script.py"
    path.write_text(SCRIPT)
    return subprocess.Popen([sys.executable, str(path), *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw)


def _worker_pid(proc, timeout=60.0):
    """The worker's pid, the script's first line."""
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    assert ready, "the script printed nothing"
    return int(proc.stdout.readline())


def test_a_worker_that_cannot_start_fails_over_rather_than_hangs():
    """A script read from stdin: the spawned interpreter cannot import its ``__main__`` and
    dies (``multiprocessing.Pool`` respawns such a worker for ever, and its caller hangs). The
    call runs in the calling process instead, and it is said."""
    code = textwrap.dedent("""
        import os
        from mpa_gym.agents.evaluation.evaluate import Background
        print(Background("the pid", os.getpid).result() == os.getpid())
    """)
    done = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0 and done.stdout.split() == ["True"], done.stderr
    assert "the worker of the pid stopped" in done.stderr
    assert "running the pid in this process" in done.stderr


def test_a_killed_worker_fails_over_and_says_so(tmp_path, capsys):
    flag = tmp_path / "started"
    call = Background("the nap", started_then_pid, str(flag), 0.2)
    _started(flag)  # the call is under way in the worker
    (pid,) = call._worker.pids()
    os.kill(pid, signal.SIGKILL)
    assert call.result() == os.getpid()  # it ran again, here
    assert "the worker of the nap stopped" in capsys.readouterr().err
    assert _reaped(pid)


def test_cancel_stops_a_call_under_way(tmp_path):
    flag = tmp_path / "started"
    call = Background("a nap", started_then_pid, str(flag), 600)
    _started(flag)
    (pid,) = call._worker.pids()
    started = time.monotonic()
    call.cancel()
    assert time.monotonic() - started < 10 and _reaped(pid)


def test_a_killed_parent_takes_its_worker_with_it(tmp_path):
    """SIGKILL of the main process (nothing of it runs to close the worker): the worker and
    multiprocessing's resource tracker exit by themselves."""
    proc = _script(tmp_path, "600")
    worker = _worker_pid(proc)
    kids = children(proc.pid)
    assert worker in kids and all(alive(k) for k in kids)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    left = wait_gone(kids)
    assert not left, [open(f"/proc/{k}/cmdline").read() for k in left]


def test_ctrl_c_at_the_terminal_reaches_the_main_process_alone(tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C: the main process is
    interrupted and the worker, which ignores it, still answers."""
    proc = _script(tmp_path, "3", start_new_session=True, preexec_fn=default_sigint)
    worker = _worker_pid(proc)
    time.sleep(1.0)  # the worker is importing or napping
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.split() == ["interrupted;", "the", "worker", "answered", str(worker)]
    assert not wait_gone([worker])


@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_while_waiting_for_the_worker_stops_both(tmp_path, presses):
    """Ctrl-C (once or twice) while the main process waits for a long call: nobody will use
    its answer, so the worker is stopped and the main process ends at once."""
    proc = _script(tmp_path, "600", "wait", start_new_session=True, preexec_fn=default_sigint)
    worker = _worker_pid(proc)
    time.sleep(1.0)
    for _ in range(presses):
        os.killpg(proc.pid, signal.SIGINT)
        time.sleep(0.3)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0 and "KeyboardInterrupt" in err
    assert not wait_gone([worker])
