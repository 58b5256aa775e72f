"""Where the data lives: a setting, so users can bring their own body, garments and motion.

Order of precedence: an explicit argument, the TRYON_DATA environment variable,
then `../shared/data` next to the project (the layout CI and the developers use),
then `../shared/data` relative to the working directory.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "TRYON_DATA"
_PROJECT_ROOT = Path(__file__).resolve().parents[1]


def data_dir(override: str | os.PathLike | None = None) -> Path:
    if override:
        path = Path(override).expanduser()
    elif os.environ.get(ENV_VAR):
        path = Path(os.environ[ENV_VAR]).expanduser()
    else:
        path = _PROJECT_ROOT.parent / "shared" / "data"
        if not path.is_dir():
            path = Path.cwd().parent / "shared" / "data"
    if not path.is_dir():
        raise FileNotFoundError(
            f"data folder {path} does not exist: pass --data DIR or set {ENV_VAR}"
        )
    return path
