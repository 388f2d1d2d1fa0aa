"""Atomic file writes: a crash or Ctrl-C never leaves a half-written output behind."""

import os
from pathlib import Path
from typing import Callable


def atomic_write(path, write: Callable[[str], object]) -> None:
    """Call write(tmp_path) for a temporary file beside `path`, fsync it, rename it over `path`.

    The temporary name keeps the suffix (Open3D and NumPy pick formats by it). A writer
    returning False (Open3D's convention for failure) raises OSError; `path` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        if write(str(tmp)) is False:
            raise OSError(f"could not write {path}")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
