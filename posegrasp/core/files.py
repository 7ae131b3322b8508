"""Files that hold records: written atomically, and hashed once per process.

Every record (a JSON report, the weights manifest, a gate baseline, a training checkpoint) is
written by `atomic_write`: into a temporary file in the target's folder, flushed and fsynced, then
renamed over the target with `os.replace`. A failure at any point before the rename leaves the
previous file untouched and removes the temporary file.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

#: Bytes read at a time when hashing.
_CHUNK = 1 << 20


def atomic_write(path: Path | str, write: Callable[[IO[bytes]], Any], fsync: bool = True) -> None:
    """Write a file through `write(f)` on a temporary file in the same folder, then rename it.

    Args:
        path: the file to write; missing parent folders are created.
        write: writes the whole content to the binary file object it is given.
        fsync: flush the content to disk before the rename (records); bulk data may skip it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path | str, payload: bytes, fsync: bool = True) -> None:
    """Write bytes atomically (see `atomic_write`)."""
    atomic_write(path, lambda f: f.write(payload), fsync)


def atomic_write_json(path: Path | str, obj: Any) -> None:
    """Write obj as JSON (one-space indent, sorted keys, trailing newline), atomically."""
    atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode())


@functools.lru_cache(maxsize=64)
def _sha256(path: str, size: int, mtime_ns: int, inode: int) -> str:
    del size, mtime_ns, inode  # the cache key: a rewritten file is hashed again
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def sha256_file(path: Path | str) -> str:
    """SHA-256 of a file's bytes (hex); each file is read once per process while unchanged.

    Raises:
        OSError: the file cannot be read.
    """
    p = Path(path).resolve()
    st = p.stat()
    return _sha256(str(p), st.st_size, st.st_mtime_ns, st.st_ino)
