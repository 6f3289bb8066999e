"""Atomic writes (mpa_gym.files): a writer that fails or is killed mid-write leaves the old
complete file, and its temporary is recognisable and removable."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mpa_gym.files import atomic_save, atomic_write_text, remove_stale_temporaries


def test_a_writer_that_fails_mid_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "model.bin"
    atomic_save(path, lambda f: f.write(b"old complete"))

    def torn(f):
        f.write(b"new but only half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_save(path, torn)
    assert path.read_bytes() == b"old complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.bin"]  # no temporary left
    assert atomic_write_text(path, "new") == path and path.read_text() == "new"


def test_a_writer_killed_mid_write_keeps_the_old_file(tmp_path):
    """SIGKILL a real process while it is inside the write: the destination is the old file,
    whole; the killed writer's temporary is the only other file and is removed by
    ``remove_stale_temporaries`` (what a resumed run does)."""
    path = tmp_path / "evaluations.json"
    atomic_write_text(path, '{"timesteps": [1, 2]}')
    ready = tmp_path / "ready"
    code = (
        "import sys, time, pathlib\n"
        "from mpa_gym.files import atomic_open\n"
        "with atomic_open(sys.argv[1], 'w') as f:\n"
        "    f.write('{\"timesteps\": [1, 2, 3')\n"
        "    f.flush()\n"
        "    pathlib.Path(sys.argv[2]).touch()\n"
        "    time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(path), str(ready)])
    try:
        deadline = time.monotonic() + 60.0
        while not ready.exists():
            assert proc.poll() is None, "the writer died before it began"
            assert time.monotonic() < deadline, "the writer never began"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
    assert path.read_text() == '{"timesteps": [1, 2]}'
    stale = [p for p in tmp_path.iterdir() if p.name not in ("evaluations.json", "ready")]
    assert len(stale) == 1 and stale[0].name.startswith(".evaluations.json.")
    assert stale[0].read_text() == '{"timesteps": [1, 2, 3'  # the torn write stayed aside
    assert remove_stale_temporaries(tmp_path) == 1
    assert sorted(p.name for p in Path(tmp_path).iterdir()) == ["evaluations.json", "ready"]
