"""Output folders: created when missing, never overwritten without being asked, and
completed by a rename (a folder under its final name is always complete)."""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path

__all__ = ["prepare_output_dir", "partial_dir", "commit_dir", "remove_partials", "PARTIAL"]

#: The infix of the hidden folders an output is written into before the rename that
#: completes it (``.<name>.partial-<id>``).
PARTIAL = ".partial-"


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


def partial_dir(final: Path) -> Path:
    """A new hidden folder beside ``final`` to write its content into (``.<name>.partial-<id>``)."""
    final.parent.mkdir(parents=True, exist_ok=True)
    path = final.parent / f".{final.name}{PARTIAL}{uuid.uuid4().hex[:12]}"
    path.mkdir()
    return path


def commit_dir(partial: Path, final: Path, force: bool) -> None:
    """Rename a complete partial folder to ``final``; an existing ``final`` is replaced
    only with ``force`` (moved aside first, removed after the rename)."""
    old = None
    if final.exists():
        if any(final.iterdir()) and not force:
            shutil.rmtree(partial, ignore_errors=True)
            raise FileExistsError(f"{final} is not empty; choose another --out or pass --force")
        old = final.with_name(f".{final.name}.old-{partial.name.rsplit('-', 1)[-1]}")
        final.rename(old)
    partial.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def remove_partials(folder: Path, names=None) -> list:
    """Remove the partial folders (of crashed or killed writers) in ``folder``: all, or
    those of the outputs ``names``. Returns the paths removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    gone = []
    for p in folder.iterdir():
        if p.is_dir() and p.name.startswith(".") and PARTIAL in p.name:
            if names is None or p.name[1:].split(PARTIAL, 1)[0] in names:
                shutil.rmtree(p, ignore_errors=True)
                gone.append(p)
    return gone
