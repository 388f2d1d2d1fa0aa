"""Atomic file writes (a crash or Ctrl-C never leaves a half-written output behind), checked JSON reads,
and the library's cache folder."""

import json
import os
from pathlib import Path
from typing import Callable, Mapping

Writer = Callable[[str], object]
"""Writes one file at the path it is given; returning False (Open3D's convention) is a failure."""


def atomic_write(path, write: Writer) -> None:
    """Call write(tmp_path) for a temporary file beside `path`, fsync it, rename it over `path`.

    The temporary name keeps the suffix (Open3D and NumPy pick formats by it). On any
    failure (an exception, Ctrl-C, or a writer returning False: OSError) `path` is untouched
    and the temporary file is removed.
    """
    atomic_write_all({path: write})


def atomic_write_all(writes: Mapping[object, Writer]) -> None:
    """Write several files so that a failure in any writer leaves every target untouched.

    Every writer first writes (and fsyncs) a temporary file beside its target; only when all
    have succeeded are the temporaries renamed over the targets. Temporaries never outlive
    the call.
    """
    temps: dict[Path, Path] = {}
    try:
        for path, write in writes.items():
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = temps[path] = path.with_name(f".tmp-{os.getpid()}-{path.name}")
            if write(str(tmp)) is False:
                raise OSError(f"could not write {path}")
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        for path, tmp in temps.items():
            os.replace(tmp, path)
    finally:
        for tmp in temps.values():
            tmp.unlink(missing_ok=True)


def read_json_object(path, error: type[Exception]) -> dict:
    """The JSON object in file `path`; raises `error` naming the file if it is not valid JSON or
    not an object."""
    try:
        meta = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: corrupt JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise error(f"{path}: expected a JSON object, got {type(meta).__name__}")
    return meta


def cache_dir() -> Path:
    """The library's cache folder, ``$XDG_CACHE_HOME/open3d_pnerf`` (``~/.cache/open3d_pnerf`` by default):
    built kernels, frames extracted from recordings."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "open3d_pnerf"
