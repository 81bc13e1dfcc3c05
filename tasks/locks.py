"""One writer per output: a lock file beside each output path (issue 19, "two writers").

``btf`` takes :func:`output_locks` on every output of a command (:attr:`flows.cli.Command.outputs`)
before its checks and holds it until the command ends. The lock of ``OUT`` is the file
``OUT.lock`` beside it, created atomically (``O_CREAT | O_EXCL``) and holding the holder's
identity as JSON: host, pid, command and start time. A second command writing the same output
is refused naming the holder. A lock left by a killed process on this host (its pid no longer
runs) is stale and taken over; one held on another host cannot be checked from here, so it is
refused with the advice to delete the file once that process is gone. Where the output's folder
does not exist yet, no lock is taken (nothing is there to tear; the command creates the folder).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["OutputLockedError", "lock_path", "output_locks"]


class OutputLockedError(FileExistsError):
    """Another running command writes the same output; the message names it and what to do."""


def lock_path(out: str | os.PathLike) -> Path:
    """The lock file of the output ``out``: ``OUT.lock`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".lock")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # runs, under another user
        return True
    return True


def _holder(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _acquire(out: Path, command: str) -> Path | None:
    path = lock_path(out)
    if not path.parent.is_dir():
        return None
    me = {"host": socket.gethostname(), "pid": os.getpid(), "command": command,
          "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    data = json.dumps(me).encode()
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = _holder(path)
            if holder is None:                      # being written this instant, or garbage: look again
                time.sleep(0.05)
                holder = _holder(path)
            if holder is not None and holder.get("pid") == me["pid"] and holder.get("host") == me["host"]:
                return None                         # this process holds it already (a command run twice in a test)
            if holder is not None and (holder.get("host") != me["host"] or _alive(int(holder.get("pid", -1)))):
                raise OutputLockedError(
                    f"{out} is being written by another command ({holder.get('command')!r}, pid {holder.get('pid')} "
                    f"on {holder.get('host')}, since {holder.get('started')}); wait for it to finish or choose "
                    f"another output; if that process is gone, delete {path}")
            # stale (its process is gone) or unreadable: take it over atomically, then check we won
            tmp = path.with_name(f"{path.name}.{me['pid']}")
            tmp.write_bytes(data)
            os.replace(tmp, path)
            if _holder(path) == me:
                return path
            continue
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return path
    raise OutputLockedError(f"{out}: could not take its lock {path} (another command took it at the same time); "
                            "run the command again")


@contextlib.contextmanager
def output_locks(outputs: Iterable[str | os.PathLike], command: str) -> Iterator[None]:
    """Hold the lock of every output (:func:`lock_path`) while the block runs; released at its end.

    Raises
    ------
    OutputLockedError
        An output's lock is held by a running process (its identity in the message).
    """
    held: list[Path] = []
    try:
        for out in dict.fromkeys(os.path.abspath(os.fspath(o)) for o in outputs):
            path = _acquire(Path(out), command)
            if path is not None:
                held.append(path)
        yield
    finally:
        for path in held:
            with contextlib.suppress(OSError):
                if (_holder(path) or {}).get("pid") == os.getpid():
                    path.unlink()
