"""Outfit models kept on disk between runs: built once per outfit, fabric, level and settings.

Fitting an outfit and building its coarse, detailed and layer models takes about a second
(0.8-1.0 s per outfit on the 2-core test machine), which every session start and every live
outfit change waited for. What they are built from is fixed data and code, so the result is
stored under a key made of all of it, and read back (a few milliseconds) whenever the same key
comes again:

* the code that builds them: the bytes of every source file of `cloth/` (its fabric presets
  too), `skinning/` and this package's model building (`cloth_job.py`, this module), and the
  Python, numpy, numba and Pinocchio versions and the machine's architecture;
* the inputs: the body (all its arrays), every file of the outfit's folder, the fabrics and
  settings asked for.

Any change to any of them is another key: the models are built afresh, never read stale. A file
that cannot be read back (truncated, from another version of a library) is built again and
replaced, with a warning; a folder that cannot be written to only costs the build. Files are
written whole or not at all (written beside, then renamed). The folder keeps the `KEEP` most
recently used files.

Where: `$TRYON_CACHE` if set (`off`: no cache), else `$XDG_CACHE_HOME/tryon` (default
`~/.cache/tryon`), in `models/`. The files are Python pickles: load only a folder you trust, as
with numba's own cache.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import platform
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger("tryon.cache")

CACHE_ENV = "TRYON_CACHE"
KEEP = 48  # model files kept (about 3-8 MB each)
ROOT = Path(__file__).resolve().parents[1]
# what the models are built by: every file here whose name ends so
CODE = [(ROOT / "cloth", (".py", ".toml")), (ROOT / "skinning", (".py",)),
        (ROOT / "services" / "cloth_job.py", ()), (Path(__file__).resolve(), ())]


def cache_folder(value: str | Path | None = None) -> Path | None:
    """The cache folder: `value`, else $TRYON_CACHE, else $XDG_CACHE_HOME/tryon or ~/.cache/tryon;
    None where it is 'off'."""
    value = value if value is not None else os.environ.get(CACHE_ENV)
    if value is not None and str(value).strip().lower() in ("off", "none", "0", "no"):
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "tryon"


_code_digest: str | None = None


def code_digest() -> str:
    """A digest of the code that builds the models and of the libraries it runs on."""
    global _code_digest
    if _code_digest is None:
        import numba
        import numpy
        import pinocchio

        h = hashlib.sha256()
        for versions in (sys.version, numpy.__version__, numba.__version__, pinocchio.__version__,
                         platform.machine()):
            h.update(str(versions).encode() + b"\0")
        for where, endings in CODE:
            files = sorted(p for p in where.rglob("*") if p.name.endswith(endings)) if where.is_dir() else [where]
            for p in files:
                if "__pycache__" in p.parts:
                    continue
                h.update(p.relative_to(ROOT).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
        _code_digest = h.hexdigest()
    return _code_digest


def folder_digest(folder: Path) -> str:
    """A digest of every file in a folder (names and bytes), e.g. an outfit's; of a file, its
    name and bytes (an outfit of one garment mesh)."""
    h = hashlib.sha256()
    folder = Path(folder)
    files = [folder] if folder.is_file() else sorted(q for q in folder.rglob("*") if q.is_file())
    for p in files:
        name = p.name if p == folder else p.relative_to(folder).as_posix()
        h.update(name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def object_digest(obj: Any) -> str:
    """A digest of an object's pickle (arrays by their bytes, dataclasses by their fields). An
    object that pickles differently from run to run only makes a key that is never found."""
    return hashlib.sha256(pickle.dumps(obj, protocol=5)).hexdigest()


class ModelCache:
    """`get(key_parts, build)`: what `build()` returns, read from the folder when built before
    under the same key parts (each a string, e.g. a digest, or a picklable object)."""

    def __init__(self, folder: Path | None):
        self.folder = None if folder is None else Path(folder) / "models"
        self.hits = 0
        self.builds = 0

    @classmethod
    def from_env(cls, value: str | Path | None = None) -> "ModelCache":
        return cls(cache_folder(value))

    def key(self, *parts: Any) -> str:
        h = hashlib.sha256(code_digest().encode())
        for part in parts:
            h.update(b"\0" + (part.encode() if isinstance(part, str) else pickle.dumps(part, protocol=5)))
        return h.hexdigest()[:40]

    def get(self, parts: tuple, build: Callable[[], Any]) -> Any:
        if self.folder is None:
            self.builds += 1
            return build()
        path = self.folder / f"{self.key(*parts)}.pickle"
        try:
            with open(path, "rb") as f:
                value = pickle.load(f)
            self.hits += 1
            try:
                os.utime(path)  # (recently used: kept)
            except OSError:
                pass
            return value
        except (FileNotFoundError, NotADirectoryError):
            pass  # (not built before; or no folder there: said when writing)
        except Exception as err:  # noqa: BLE001 - any unreadable file is built again and replaced
            log.warning("model cache: %s cannot be read back (%s: %s); building the models again", path,
                        type(err).__name__, err)
        value = build()
        self.builds += 1
        self._write(path, value)
        return value

    def _write(self, path: Path, value: Any) -> None:
        tmp = path.with_name(f"{path.name}.{os.getpid()}.part")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(tmp, "wb") as f:
                pickle.dump(value, f, protocol=5)
            os.replace(tmp, path)
        except OSError as err:
            log.warning("model cache: cannot write %s (%s); the models are built again next time", path, err)
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            return
        self._prune()

    def _prune(self) -> None:
        try:
            files = sorted(self.folder.glob("*.pickle"), key=lambda p: p.stat().st_mtime)
            for p in files[:-KEEP]:
                p.unlink(missing_ok=True)
        except OSError:
            pass  # (another process pruned the same folder)


__all__ = ["CACHE_ENV", "ModelCache", "cache_folder", "code_digest", "folder_digest", "object_digest"]
