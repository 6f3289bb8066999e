"""Where the compiled kernels' cache lives (``mpa_gym.model.jit``): named by every source file,
since numba does not see a change in a callee's file (its notes on caching, "Cache
limitations")."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from mpa_gym.model.jit import cache_dir, package_roots, sources_digest

SHOW = ("import numba, numpy as np; from mpa_gym.model import fast; "
        "from mpa_gym.model.params import DEFAULT_PARAMS; "
        "c = fast.pack(DEFAULT_PARAMS); fast.force_and_stiffness(0.8, 0.0, 3e5, 5e4, c); "
        "print(numba.config.CACHE_DIR)")


def _show(env: dict[str, str]) -> str:
    """numba's cache folder in a fresh interpreter that compiled (or loaded) a kernel."""
    clean = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run([sys.executable, "-c", SHOW], env={**clean, **env}, check=True,
                         capture_output=True, text=True, timeout=300)
    return out.stdout.rstrip("\n").rsplit("\n", 1)[-1]


def test_the_digest_changes_with_any_python_file_and_only_with_them(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "fast.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    (tmp_path / "notes.txt").write_text("n\n")
    first = sources_digest([tmp_path])
    (tmp_path / "notes.txt").write_text("changed\n")  # not a source
    assert sources_digest([tmp_path]) == first
    (tmp_path / "a" / "fast.py").write_text("x = 2\n")  # a callee's file
    changed = sources_digest([tmp_path])
    assert changed != first
    (tmp_path / "a" / "fast.py").rename(tmp_path / "a" / "slow.py")  # same bytes, moved
    assert sources_digest([tmp_path]) not in (first, changed)


def test_the_package_roots_hold_the_library_and_the_app():
    # a checkout's editable install maps agents/ beside the library; a wheel holds it inside
    modules = {p.relative_to(r).as_posix() for r in package_roots() for p in r.rglob("*.py")}
    assert any(m.endswith("model/fast.py") for m in modules)
    assert any(m.endswith("learned/frontend.py") for m in modules)


def test_kernels_cache_under_the_digest_unless_the_user_chose(tmp_path):
    home = tmp_path / "cache"
    want = cache_dir().relative_to(Path(os.environ.get("XDG_CACHE_HOME")
                                        or Path.home() / ".cache"))
    assert _show({"XDG_CACHE_HOME": str(home)}) == str(home / want)
    assert any((home / want).rglob("*.nbi"))  # the kernel's index was written there
    # the user's NUMBA_CACHE_DIR stays
    assert _show({"XDG_CACHE_HOME": str(home), "NUMBA_CACHE_DIR": str(tmp_path / "mine")}) \
        == str(tmp_path / "mine")
    # a cache home that cannot be created leaves numba's default (no folder: next to the
    # sources), and the kernel still runs
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert _show({"XDG_CACHE_HOME": str(blocked)}) == ""
