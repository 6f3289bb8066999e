"""The spawned worker process (agents.worker) behind training's held-out evaluations and the
report's robustness sweep, with real processes and real signals: a worker that cannot start, a
killed worker, a killed parent, a Ctrl-C at the terminal, a cancel."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

from conftest import alive, children, default_sigint

from agents.evaluate import Background

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# a user's script: its functions are importable by the spawned worker (``__mp_main__``)
SCRIPT = textwrap.dedent("""
    import os, sys, time
    from agents.evaluate import Background

    def nap_then_pid(s):
        time.sleep(s)
        return os.getpid()

    if __name__ == "__main__":
        call = Background("a nap", nap_then_pid, float(sys.argv[1]))
        print(*call._worker.pids(), flush=True)
        try:
            time.sleep(600)
        except KeyboardInterrupt:
            print("interrupted; the worker answered", call.result(), flush=True)
""")


def _script(tmp_path):
    path = tmp_path / "user_script.py"
    path.write_text(SCRIPT)
    return path


def _wait_gone(pids, timeout=30.0):
    deadline = time.monotonic() + timeout
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return [p for p in pids if alive(p)]


def test_a_worker_that_cannot_start_fails_over_rather_than_hangs():
    """A script read from stdin: the spawned interpreter cannot import its ``__main__`` and
    dies (``multiprocessing.Pool`` respawns such a worker for ever, and its caller hangs). The
    call runs in the calling process instead, and it is said."""
    code = textwrap.dedent("""
        import os
        from agents.evaluate import Background
        print(Background("the pid", os.getpid).result() == os.getpid())
    """)
    done = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0 and done.stdout.split() == ["True"], done.stderr
    assert "the worker of the pid stopped" in done.stderr
    assert "running the pid in this process" in done.stderr


def test_a_killed_worker_fails_over_and_says_so(capsys):
    call = Background("the pid", os.getpid)
    (pid,) = call._worker.pids()
    os.kill(pid, signal.SIGKILL)  # during its start-up: the call has not run there
    assert call.result() == os.getpid()
    assert "the worker of the pid stopped" in capsys.readouterr().err
    assert not alive(pid)


def test_cancel_stops_a_call_under_way():
    call = Background("a nap", time.sleep, 600)
    (pid,) = call._worker.pids()
    started = time.monotonic()
    call.cancel()
    assert time.monotonic() - started < 10 and not alive(pid)


def test_a_killed_parent_takes_its_worker_with_it(tmp_path):
    """SIGKILL of the main process (nothing of it runs to close the worker): the worker and
    multiprocessing's resource tracker exit by themselves."""
    proc = subprocess.Popen([sys.executable, str(_script(tmp_path)), "600"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    worker = int(proc.stdout.readline())
    kids = children(proc.pid)
    assert worker in kids and all(alive(k) for k in kids)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    left = _wait_gone(kids)
    assert not left, [open(f"/proc/{k}/cmdline").read() for k in left]


def test_ctrl_c_at_the_terminal_reaches_the_main_process_alone(tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C: the main process is
    interrupted and the worker, which ignores it, still answers."""
    proc = subprocess.Popen([sys.executable, str(_script(tmp_path)), "3"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=default_sigint)
    worker = int(proc.stdout.readline())
    time.sleep(1.0)  # the worker is importing or napping
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.split() == ["interrupted;", "the", "worker", "answered", str(worker)]
    assert not _wait_gone([worker])
