"""The numba settings of every compiled kernel of the package (``JIT``), and where their
on-disk cache lives.

numba invalidates a cached function when its own source file changes, not when a compiled
function it calls from another file does ("Cache limitations" in numba's notes on caching):
the sim engine (``envs/sim.py``) calls ``model/fast.py``, the compiled rig path
(``agents/learned/inference.py``) calls the controller front-end (``agents/learned/
frontend.py``). After an update of a checkout or of an installed version, a kernel would run
its callee's old code from the cache: a rollout acting through a front-end its policy was not
trained with. So importing this module, which every module with a kernel does before it
compiles one, points numba's cache at a directory named by a digest of the package's sources
(``cache_dir``): any change to them starts a fresh cache. numba's setting is the process's, so
another package's kernels compiled later cache there too. A ``NUMBA_CACHE_DIR`` the user set
is kept; where the cache home is not writable, numba keeps its default.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path

import numba

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}  # every kernel's numba.njit


def sources_digest(roots: list[Path]) -> str:
    """A digest of every Python file under ``roots``: its path relative to its root and its
    bytes."""
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def package_roots() -> list[Path]:
    """The folders the package's modules live in: the library's, and the app's where it is
    apart (a checkout's ``agents/``, which an editable install maps to ``mpa_gym.agents``; in a
    wheel it is inside the library's)."""
    root = Path(__file__).resolve().parents[1]
    roots = [root]
    app = importlib.util.find_spec("mpa_gym.agents")
    if app is not None and app.origin is not None:
        where = Path(app.origin).resolve().parent
        if root not in where.parents:
            roots.append(where)
    return roots


def cache_dir() -> Path:
    """[dir] the kernels' cache for these sources: under the user's cache home
    (``XDG_CACHE_HOME`` or ``~/.cache``), ``mpa-gym/numba/<digest>``."""
    home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return home / "mpa-gym" / "numba" / sources_digest(package_roots())[:16]


def _use_cache_dir() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    where = cache_dir()
    try:
        where.mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    numba.config.CACHE_DIR = str(where)


_use_cache_dir()
