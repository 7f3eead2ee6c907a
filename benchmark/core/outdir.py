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

Every command that writes checks its output the same way before any work. Besides:
:func:`check_not_overlapping` refuses an output equal to, inside or containing an input;
:func:`claim_out_dir` is for commands that replace a whole folder with ``--force`` (``data
make-scans``, ``complete``): they write a marker (:data:`MARKER_NAME`, the command and the entries it
wrote) into the folder, and ``--force`` replaces only a folder holding that command's marker and
nothing else, and only after every argument has been checked.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import re
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
    """``--out`` cannot be used (not a folder, not writable, full, locked by another run, the input
    itself, or holding files the command did not write)."""


def _existing_ancestor(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def _why_not_writable(exc: OSError, path: Path) -> str:
    """Why a file cannot be created in the folder ``path`` (which exists), from the error creating
    one, with the fix: a permission fix is offered only where permissions are the cause."""
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        return "the disk is full; free some space or choose another folder"
    if exc.errno == errno.EDQUOT:
        return "your disk quota is used up; free some space or choose another folder"
    if exc.errno == errno.EROFS:
        return "on a read-only filesystem; choose a folder on a writable disk"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"not writable ({reason}); fix its permissions (chmod u+w {path}) or choose another folder"
    return (f"its filesystem does not let files be created there (creating one failed: {reason}, although the folder "
            "exists): a system folder such as /proc or /sys, or a special filesystem, not one for data; choose "
            "another folder")


def check_out_dir(out: str | os.PathLike, min_free_bytes: int = MIN_FREE_BYTES, what: str = "--out") -> Path:
    """Create ``out`` if needed and check that a run can write its results there.

    Raises :class:`OutDirError` naming the path, what is wrong and the fix. Returns the folder."""
    if not str(out).strip():
        raise OutDirError(f"{what} {str(out)!r}: empty; give a folder path (it is created if missing), e.g. --out runs/mytable")
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
        raise OutDirError(f"{what} {path}: cannot create the folder in {anc}: {_why_not_writable(exc, anc)}") from None
    try:
        fd, probe = tempfile.mkstemp(dir=path, prefix=".write-probe.", suffix=".tmp")
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise OutDirError(f"{what} {path}: {_why_not_writable(exc, path)}") from None
    try:
        free = shutil.disk_usage(path).free
    except OSError:
        free = None
    if free is not None and free < min_free_bytes:
        raise OutDirError(f"{what} {path}: only {free / 2**20:.1f} MiB free, a run needs at least "
                          f"{min_free_bytes / 2**20:.0f} MiB for its unit files and tables; free some space or choose "
                          "another folder")
    return path


def check_units_folder(out: str | os.PathLike, what: str = "--out") -> Path:
    """Before any work: a table run stores each unit in ``<out>/units/`` and moves stale ones to
    ``<out>/units/stale/``; either one that exists must be a folder this process can write into,
    else every unit would be computed and then fail to be stored. Creates nothing (a run refused
    before its first unit leaves no folder behind); raises :class:`OutDirError` naming the path and
    the fix."""
    units = Path(out) / "units"
    for folder in (units, units / "stale"):
        if folder.exists() and not folder.is_dir():
            raise OutDirError(f"{what} {out}: {folder} is a file, not the folder the run keeps its work units in; "
                              "move it away or choose another --out")
    if not units.exists():
        parent = units.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise OutDirError(f"{what} {out}: cannot create {units} ({parent} is not a writable folder); fix the "
                              f"permissions of {parent} or choose another --out")
    for folder in (units, units / "stale"):
        if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
            raise OutDirError(f"{what} {out}: {folder} is not writable; the run stores (and moves aside) its work "
                              f"units there: fix its permissions (chmod u+w {folder}) or choose another --out")
    return units


# the temporary files of an atomic write (benchmark.core.json_io, benchmark.data.unit_arrays):
# ".<name>.<mkstemp's 8 random characters>.tmp", renamed to <name> once complete
_TEMP_FILE = re.compile(r"\.[^/]+\.(?:json|npz|md|csv|tex)\.[A-Za-z0-9_]{8}\.tmp")


def remove_partial_files(out: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of atomic writes that a run killed outright (SIGKILL, a lost node,
    the out-of-memory killer) left half-written in ``out`` and ``out/units``: each is a file the run
    had not finished, never a result. Call it only while holding the folder's :class:`OutDirLock`
    (no other run can be writing there). Returns the files removed."""
    removed = []
    for folder in (Path(out), Path(out) / "units"):
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            if not _TEMP_FILE.fullmatch(entry.name) or not entry.is_file(follow_symlinks=False):
                continue
            try:
                os.unlink(entry.path)
            except OSError:
                continue
            removed.append(Path(entry.path))
    if removed:
        log.info("removed %d half-written file(s) left by a run that was killed (%s)", len(removed),
                 ", ".join(p.name for p in removed[:3]) + (" ..." if len(removed) > 3 else ""))
    return removed


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


# a live process with the lock's pid that started this long after the lock was written is not its
# owner (the owner writes the lock after it starts): the pid was reused. The slack absorbs the
# rounding of the kernel's boot time and small clock adjustments.
PID_REUSE_SLACK_S = 10.0


def _process_start_time(pid: int) -> float | None:
    """When process ``pid`` started (seconds since the epoch), from ``/proc`` (Linux); None where
    it cannot be read (another OS, the process gone, an unreadable ``/proc``)."""
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        ticks = float(stat.rsplit(")", 1)[1].split()[19])  # field 22, starttime (comm may hold spaces)
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def _pid_reused(pid: int, started) -> bool:
    """Whether the live process ``pid`` started after the lock naming it was written (``started``),
    so that it cannot be the run that wrote it: the pid of a killed run, reused by another process
    (a container restarted with the same pids, a long uptime)."""
    if not isinstance(started, (int, float)) or isinstance(started, bool):
        return False
    began = _process_start_time(pid)
    return began is not None and began > started + PID_REUSE_SLACK_S


# the lock files this process holds (a lock naming this process's pid that is not among them was
# left by an earlier process that had the same pid, e.g. the run before a container restart)
_HELD: set[str] = set()


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

    def _key(self) -> str:
        return os.path.realpath(self.path)

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
                if same_host and pid == me["pid"] and self._key() in _HELD:
                    raise OutDirError(f"--out {self.folder}: this process already holds {self.path}")
                # gone, or its pid now another process's: this one's (it does not hold the lock), or
                # one started after the lock was written
                dead = same_host and isinstance(pid, int) and not isinstance(pid, bool) and (
                    pid == me["pid"] or not _pid_alive(pid) or _pid_reused(pid, info.get("started")))
                if not info:  # unreadable: stale only when old (a lock being written is empty for an instant)
                    try:
                        dead = time.time() - self.path.stat().st_mtime > 10
                    except FileNotFoundError:
                        continue
                if dead:
                    if not info or not _pid_alive(pid):
                        gone = "no such process"
                    else:
                        gone = "its pid is now " + ("this process's" if pid == me["pid"] else "another process's, started later")
                    log.warning("--out %s: taking over a stale lock (%s: %s)", self.folder, self._describe(info), gone)
                    print(f"taking over a stale lock in {self.folder} ({self._describe(info)}: {gone})", flush=True)
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
                _HELD.add(self._key())
                return self
        raise OutDirError(f"--out {self.folder}: could not take the lock {self.path}; another run keeps replacing it")

    def release(self) -> None:
        if not self.held:
            return
        self.held = False
        _HELD.discard(self._key())
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


# ------------------------------------------------------------------------------------------------
# inputs and outputs apart; what --force may replace

MARKER_NAME = ".benchmark-output.json"


def check_not_overlapping(out: str | os.PathLike, inputs, what: str = "--out", allow_inside: bool = False) -> None:
    """Refuse an output path that is one of ``inputs`` (``(label, path)`` pairs), lies inside one or
    contains one (paths resolved, so ``./x``, ``x/../x`` and symlinks compare equal): writing there
    would change the input. ``allow_inside``: an output folder below the input is fine (``report``'s
    default ``RUN/report``). Raises :class:`OutDirError` naming both paths and the fix."""
    o = Path(out).expanduser().resolve()
    for label, inp in inputs:
        if inp is None:
            continue
        i = Path(inp).expanduser().resolve()
        if o == i:
            how = f"is the {label} itself"
        elif i in o.parents and not allow_inside:
            how = f"lies inside the {label} {inp}"
        elif o in i.parents:
            how = f"contains the {label} {inp}"
        else:
            continue
        raise OutDirError(f"{what} {out}: {how}; writing there would change the input. Choose an output "
                          f"path outside it")


def _marker_path(folder: Path) -> Path:
    return folder / MARKER_NAME


def read_marker(folder: str | os.PathLike) -> dict | None:
    """The marker an output folder's command wrote (``{"command": ..., "entries": [...]}``), or None."""
    path = _marker_path(Path(folder))
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("entries"), list):
        return None
    return data


def claim_out_dir(out: str | os.PathLike, command: str, force: bool, what: str = "--out",
                  min_free_bytes: int = MIN_FREE_BYTES) -> tuple[Path, list[str]]:
    """Before any work, for a command that writes a folder of its own (``data make-scans``,
    ``complete``): :func:`check_out_dir`, then who wrote what is in it.

    An empty or new folder is fine. A non-empty one is refused without ``force``; with ``force`` it
    must hold the marker (:data:`MARKER_NAME`) that ``command`` wrote when it made the folder and
    nothing besides the entries the marker lists (and the marker, a run lock). Nothing is deleted
    here. Returns (the folder, the entries of the earlier output that the command may replace, after
    checking the rest of its arguments, with :func:`remove_entries`)."""
    path = Path(out).expanduser()
    had = sorted(p.name for p in path.iterdir()) if path.is_dir() else []
    check_out_dir(path, min_free_bytes=min_free_bytes, what=what)
    if not had:
        return path, []
    shown = f"`python -m benchmark {command}`"
    if not force:
        raise FileExistsError(f"{what} {path} exists and is not empty; pass --force to replace what an earlier "
                              f"{shown} wrote there, or choose another {what}")
    marker = read_marker(path)
    if marker is None or marker.get("command") != command:
        whose = "no marker" if marker is None else f"its marker says {marker.get('command')!r}"
        raise OutDirError(f"{what} {path}: not a folder {shown} wrote ({whose} {MARKER_NAME}); --force only "
                          f"replaces that command's own output, so nothing was deleted. Choose another {what}, or "
                          "empty the folder yourself")
    owned = {str(e) for e in marker["entries"]}
    foreign = [n for n in had if n not in owned and n not in (MARKER_NAME, LOCK_NAME)]
    recorded = marker.get("files") if isinstance(marker.get("files"), dict) else {}
    for name in had:  # inside a folder of its own, the files it recorded writing and nothing else
        if name in owned and isinstance(recorded.get(name), list) and (path / name).is_dir():
            mine = {str(f) for f in recorded[name]}
            foreign += [f for f in _files_under(path, name) if f not in mine]
    if foreign:
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        raise OutDirError(f"{what} {path}: holds files {shown} did not write ({', '.join(foreign[:3])}{more}); "
                          f"--force does not delete them, so nothing was deleted. Move them away or choose another {what}")
    return path, [n for n in had if n in owned]


def _plain_name(name: str) -> bool:
    return bool(name) and name not in (".", "..") and "/" not in name and "\\" not in name and name != MARKER_NAME


def _files_under(folder: Path, name: str) -> list[str]:
    """The files below ``folder / name``, as paths relative to ``folder`` (posix)."""
    return sorted(p.relative_to(folder).as_posix() for p in (folder / name).rglob("*") if not p.is_dir())


def write_marker(folder: str | os.PathLike, command: str, entries, files: bool = False,
                 extra: dict | None = None) -> Path:
    """Record in ``folder`` that ``command`` wrote it and which top-level ``entries`` are its own
    (written atomically; entries it adds later are recorded by calling this again). ``files``: also
    record the files now inside each entry that is a folder (call it so once the command has
    written them): a later ``--force`` then refuses a folder of its own holding anything else.
    ``extra``: more keys the command reads back (e.g. checksums of the files it wrote)."""
    folder = Path(folder)
    names = sorted({str(e) for e in entries})
    bad = [n for n in names if not _plain_name(n)]
    if bad:
        raise ValueError(f"marker entries must be plain names in the folder, got {bad}")
    data = {"command": command, "entries": names,
            "note": f"written by python -m benchmark {command}; --force replaces only these entries"}
    if files:
        data["files"] = {n: _files_under(folder, n) for n in names if (folder / n).is_dir()}
    data.update(extra or {})
    tmp = folder / f".{MARKER_NAME}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, _marker_path(folder))
    return _marker_path(folder)


def remove_entries(folder: str | os.PathLike, entries) -> None:
    """Delete the top-level ``entries`` of ``folder`` (a command's earlier output, from
    :func:`claim_out_dir`); a name that is not a plain entry of the folder is skipped."""
    folder = Path(folder)
    for name in entries:
        if not _plain_name(str(name)):
            continue
        p = folder / str(name)
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
