"""The output folder of a table run: checked before any work, and locked while a run writes to it.

:func:`check_out_dir` runs before the body, the data or any prior is loaded: the folder must be
creatable (or exist as a folder), writable (a probe file is created and removed), and hold enough
free space for the unit files and tables (:data:`MIN_FREE_BYTES`). A wrong ``--out`` therefore
fails in a second, not after hours of fitting.

:class:`OutDirLock` is ``<out>/.lock``, created with ``O_CREAT | O_EXCL`` and holding the pid, the
host and the start time of the run that owns the folder. A second run into the same folder is
refused with a message naming that process. A lock left by a process that no longer exists on this
host (a run killed with SIGKILL, a crashed node) is stale: it is taken over, with a warning. A lock
from another host cannot be checked and is refused; the message says how to remove it.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

log = logging.getLogger(__name__)

LOCK_NAME = ".lock"
# free space asked for before a run starts: unit files are a few kB each, tables well under 1 MB
MIN_FREE_BYTES = 16 * 1024 * 1024


class OutDirError(ValueError):
    """``--out`` cannot be used (not a folder, not writable, full, locked by another run)."""


def _existing_ancestor(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def check_out_dir(out: str | os.PathLike, min_free_bytes: int = MIN_FREE_BYTES, what: str = "--out") -> Path:
    """Create ``out`` if needed and check that a run can write its results there.

    Raises :class:`OutDirError` naming the path, what is wrong and the fix. Returns the folder."""
    path = Path(out).expanduser()
    if path.exists() and not path.is_dir():
        raise OutDirError(f"{what} {path}: is a file, not a folder; give a folder path (it is created if missing), "
                          "e.g. --out runs/mytable")
    anc = _existing_ancestor(path.absolute())
    if anc != path.absolute() and not anc.is_dir():
        raise OutDirError(f"{what} {path}: cannot be created because {anc} is a file, not a folder; choose another path")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutDirError(f"{what} {path}: cannot create the folder ({exc.strerror or exc}); choose a writable "
                          "location or fix the permissions of its parent") from None
    try:
        fd, probe = tempfile.mkstemp(dir=path, prefix=".write-probe.", suffix=".tmp")
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            raise OutDirError(f"{what} {path}: the disk is full; free some space or choose another folder") from None
        raise OutDirError(f"{what} {path}: not writable ({exc.strerror or exc}); fix its permissions "
                          f"(chmod u+w {path}) or choose another folder") from None
    try:
        free = shutil.disk_usage(path).free
    except OSError:
        free = None
    if free is not None and free < min_free_bytes:
        raise OutDirError(f"{what} {path}: only {free / 2**20:.1f} MiB free, a run needs at least "
                          f"{min_free_bytes / 2**20:.0f} MiB for its unit files and tables; free some space or choose "
                          "another folder")
    return path


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def read_lock(path: Path) -> dict | None:
    """The lock's contents, or None when missing; an unreadable lock reads as ``{}``."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


class OutDirLock:
    """``with OutDirLock(out): ...`` -- holds ``<out>/.lock`` for the duration of a run."""

    def __init__(self, out: str | os.PathLike, command: str = ""):
        self.folder = Path(out)
        self.path = self.folder / LOCK_NAME
        self.command = command
        self.held = False
        self.took_over: dict | None = None

    def _describe(self, info: dict) -> str:
        if not info:
            return "an unreadable lock"
        started = info.get("started")
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)) if isinstance(started, (int, float)) else "?"
        return f"pid {info.get('pid')} on host {info.get('host')!r}, started {when}" + (
            f" ({info['command']})" if info.get("command") else "")

    def acquire(self) -> "OutDirLock":
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time(), "command": self.command}
        text = json.dumps(me) + "\n"
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            except FileExistsError:
                info = read_lock(self.path)
                if info is None:  # released meanwhile
                    continue
                same_host = info.get("host") == me["host"]
                pid = info.get("pid")
                if same_host and pid == me["pid"]:
                    raise OutDirError(f"--out {self.folder}: this process already holds {self.path}")
                dead = same_host and isinstance(pid, int) and not _pid_alive(pid)
                if not info:  # unreadable: stale only when old (a lock being written is empty for an instant)
                    try:
                        dead = time.time() - self.path.stat().st_mtime > 10
                    except FileNotFoundError:
                        continue
                if dead:
                    log.warning("--out %s: taking over a stale lock (%s: the process is gone)", self.folder,
                                self._describe(info))
                    print(f"taking over a stale lock in {self.folder} ({self._describe(info)}: no such process)", flush=True)
                    self.took_over = info
                    try:
                        os.unlink(self.path)
                    except FileNotFoundError:
                        pass
                    continue
                hint = ("wait for it to finish, or stop it" if same_host else
                        f"if that run is no longer alive on {info.get('host')!r}, delete {self.path}")
                raise OutDirError(f"--out {self.folder}: another run is writing there ({self._describe(info)}); "
                                  f"{hint}, or choose another --out") from None
            else:
                with os.fdopen(fd, "w", encoding="utf-8") as fh:
                    fh.write(text)
                self.held = True
                return self
        raise OutDirError(f"--out {self.folder}: could not take the lock {self.path}; another run keeps replacing it")

    def release(self) -> None:
        if not self.held:
            return
        self.held = False
        info = read_lock(self.path)
        if info and info.get("pid") == os.getpid() and info.get("host") == socket.gethostname():
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    def __enter__(self) -> "OutDirLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
