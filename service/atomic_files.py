"""Files that are either wholly written or not there at all.

A write goes to a fsynced temporary file in the same folder and is renamed over the target,
so a crash or a full disk never leaves a half-written spool entry, result or state file; a
killed writer's temporaries are removed at the next start (:func:`remove_partial`).
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

__all__ = ["TEMP_PREFIX", "write_atomic", "write_json_atomic", "remove_partial"]

TEMP_PREFIX = ".tmp-"


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes, replace: bool = True) -> bool:
    """Write ``data`` to ``path`` via a fsynced temporary file in the same folder.

    With ``replace=False`` an existing ``path`` is kept and False is returned.
    """
    path = Path(path)
    tmp = path.parent / f"{TEMP_PREFIX}{uuid.uuid4().hex}"
    try:  # a failed write (disk full) leaves nothing behind
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                return False
            finally:
                os.unlink(tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return True


def remove_partial(folder: Path) -> int:
    """Delete the temporary files a killed writer left in ``folder``; how many there were.

    Only safe while nothing writes into ``folder`` (at start-up, before the port opens).
    """
    leftovers = list(Path(folder).glob(f"{TEMP_PREFIX}*"))
    for path in leftovers:
        path.unlink(missing_ok=True)
    if leftovers:
        _fsync_dir(Path(folder))
    return len(leftovers)


def write_json_atomic(path: Path, doc: dict) -> None:
    write_atomic(path, (json.dumps(doc, indent=2, default=str) + "\n").encode())


