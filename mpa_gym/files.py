"""Files that survive a kill and errors that name them: atomic writes and checked reads.

An artefact is written to a temporary file beside its destination, flushed to disk and renamed
over it (``os.replace``, atomic on POSIX and Windows), so a reader (or a resumed run) sees the old
complete file or the new complete one, never a torn one. A file that cannot be read is reported by
path and by what is wrong with it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import yaml


class DamagedFileError(ValueError):
    """A file exists but cannot be read (truncated, corrupt, not what its name says)."""


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on a clean exit flush, fsync and rename it to
    ``path``; on an exception remove it (``path`` keeps its old content)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    with atomic_open(path, "w") as f:
        f.write(text)
    return Path(path)


def atomic_save(path: str | os.PathLike[str], save: Callable[[Any], Any]) -> Path:
    """``save(file)`` writes into an open binary file that becomes ``path`` atomically (for
    writers that take a file object: ``model.save``, ``np.savez``, ``pickle.dump``)."""
    with atomic_open(path, "wb") as f:
        save(f)
    return Path(path)


def remove_stale_temporaries(folder: str | os.PathLike[str]) -> int:
    """Delete the temporary files a killed writer left in ``folder``; returns how many."""
    n = 0
    for p in Path(folder).glob(".*.tmp"):
        with contextlib.suppress(OSError):
            p.unlink()
            n += 1
    return n


def read_yaml(path: str | os.PathLike[str], what: str, error: type[ValueError] = ValueError,
              loader: type[yaml.SafeLoader] = yaml.SafeLoader) -> Any:
    """The YAML document in ``path``; ``error`` names the file and the problem (missing, a
    folder, not UTF-8 text, not YAML). ``loader``: a ``yaml.SafeLoader`` subclass that also
    reads a tag of its own."""
    p = Path(path)
    if p.is_dir():
        raise error(f"{what} {str(p)!r} is a folder, not a YAML file")
    if not p.is_file():
        raise error(f"{what} {str(p)!r} does not exist")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{what} {str(p)!r} is not UTF-8 text (byte 0x{e.object[e.start]:02x} at "
                    f"offset {e.start}): is it a YAML file?") from None
    except OSError as e:
        raise error(f"{what} {str(p)!r} cannot be read: {e.strerror}") from None
    try:
        return yaml.load(text, Loader=loader)  # a SafeLoader (subclass): no object is built
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise error(f"{what} {str(p)!r} is not valid YAML: {problem}{where}") from None


def check_out_dir(flag: str, path: str) -> Path:
    """An output folder, checked before any work: not a file, creatable, writable."""
    if not str(path).strip():
        raise ValueError(f"{flag} is empty; give a folder")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{flag} {path!r} is a file; give a folder (it is created if missing)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path!r} cannot be created: {e.strerror}") from None
    if not os.access(p, os.W_OK):
        raise ValueError(f"{flag} {path!r} is not writable")
    return p


def check_out_file(flag: str, path: str) -> Path:
    """An output file, checked before any work: not a folder, its folder creatable and
    writable (:func:`check_out_dir`)."""
    if not str(path).strip():
        raise ValueError(f"{flag} is empty; give a file")
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{flag} {path!r} is a folder; give a file")
    parent = p.parent if str(p.parent) else Path(".")
    if parent.exists() and not parent.is_dir():
        raise ValueError(f"{flag} {path!r}: {str(parent)!r} is a file, not a folder")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path!r}: its folder cannot be created: {e.strerror}"
                         ) from None
    if not os.access(parent, os.W_OK):
        raise ValueError(f"{flag} {path!r}: its folder is not writable")
    return p
