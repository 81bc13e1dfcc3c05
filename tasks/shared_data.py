"""Where the real files of ``../shared/data`` are (their list: data/MANIFEST.md there).

They are never copied into the repository: every reader finds them through
:func:`shared_data_dir`, which honours ``$BTF_SHARED_DATA``.
"""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    """The shared data folder, or ``None`` when this checkout has none.

    ``$BTF_SHARED_DATA`` when set (and nothing else), otherwise
    ``../shared/data`` beside the repository root or the current directory.
    A folder counts only when it holds ``MANIFEST.md``.
    """
    if os.environ.get("BTF_SHARED_DATA"):  # an explicit choice is never second-guessed
        candidates = [Path(os.environ["BTF_SHARED_DATA"])]
    else:
        candidates = [_REPO_ROOT.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"]
    for path in candidates:
        if (path / "MANIFEST.md").is_file():
            return path.resolve()
    return None


def shared_file(relative: str) -> Path | None:
    """A file under the shared data folder, or ``None`` when it is absent."""
    root = shared_data_dir()
    if root is None:
        return None
    path = root / relative
    return path if path.is_file() else None
