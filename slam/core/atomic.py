"""Atomic file output: readers see the old file or the complete new one, never a partial one.

Every writer of the project goes through here: the data is written to a temporary file in the
destination folder, then renamed over the destination (``os.replace`` is atomic on one file
system); on any error the temporary file is removed and the destination is left untouched.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_output(path: str | Path, text: bool = False) -> Iterator[IO[Any]]:
    """A file object for ``path`` that only replaces it once the ``with`` block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o644)  # mkstemp creates 0600; outputs are ordinary, shareable files
        with os.fdopen(fd, "w" if text else "wb") as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Write ``data`` (text is UTF-8 encoded) to ``path`` atomically."""
    with atomic_output(path) as f:
        f.write(data.encode() if isinstance(data, str) else data)
