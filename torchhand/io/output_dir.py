"""Output folders: created when missing, never overwritten without being asked."""

from __future__ import annotations

import shutil
from pathlib import Path

__all__ = ["prepare_output_dir"]


def prepare_output_dir(path, force: bool = False) -> Path:
    """Create ``path``; refuse a non-empty existing folder unless ``force``.

    With ``force`` the folder's previous content is removed first so that stale
    files from an earlier run cannot be mistaken for results of this one.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"{path} exists and is not a folder")
    if path.is_dir() and any(path.iterdir()):
        if not force:
            raise FileExistsError(f"{path} is not empty; choose a new folder or pass --force to replace its content")
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    return path
