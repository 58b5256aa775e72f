"""Where a command writes: its output folder, or the file a recording is finished into, checked
before anything runs. A file where a folder is named (or the other way round) was met only at the
end: `tryon record --out FOLDER` recorded a whole session into FOLDER.part and then could not
rename it, and `--out FILE` stopped a session with a traceback after its setup."""

from __future__ import annotations

from pathlib import Path


def output_folder(path: str | Path) -> Path:
    """The folder, made with its parents if need be; ValueError naming it when a file is there or
    it cannot be made."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{path}: a file is there, not a folder (the command writes its files into a folder)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{path}: cannot make the output folder ({err.strerror or err})") from None
    return path


def output_file(path: str | Path) -> Path:
    """A file to write (its folder made if need be); ValueError naming it when it is a folder."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; name the file to write in it")
    output_folder(path.parent)
    return path
