"""Canonical JSON and its sha256 (the spec hashes, unit checksums and seeds are computed over it),
and atomic files: a reader sees the old file or the new one, never a half-written one."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any


def canonical_json(obj: Any) -> str:
    """Deterministic JSON text: sorted keys, no whitespace, no NaN/inf. Raises TypeError for
    values JSON cannot represent (numpy scalars, tensors): convert them to int/float/str first."""

    def _reject(o):
        raise TypeError(f"{type(o).__name__} value {o!r} is not JSON-serialisable; convert it to int/float/str/list/dict")

    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False, default=_reject)


def sha256_json(obj: Any) -> str:
    """sha256 hex digest of :func:`canonical_json` of ``obj``."""
    return hashlib.sha256(canonical_json(obj).encode("utf-8")).hexdigest()


def current_umask() -> int:
    """The process umask (read by setting and restoring it; there is no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically: a temp file in the same folder, fsync, ``os.replace``.
    A reader sees the old file or the new one, never a half-written one; on error the old file is
    untouched and the temp file is removed. The file gets the mode a plain ``open()`` would give
    (0666 minus the umask: 0644 by default), not mkstemp's private 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        try:
            os.fchmod(fd, 0o666 & ~current_umask())
        except (AttributeError, OSError):  # no fchmod (Windows): keep mkstemp's mode
            pass
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            # a full disk or a quota says nothing about which file: name it
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_texts(files: "dict[str | os.PathLike, str]") -> list[Path]:
    """Write several files (path -> text) as one set: every temp file is written and synced first,
    and only then are they renamed into place. A full disk or an error on any of them leaves every
    old file as it was (never the new JSON beside the old Markdown of another run); the renames
    themselves need no space."""
    staged: list[tuple[str, Path]] = []
    try:
        for path, text in files.items():
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            staged.append((tmp, path))
            try:
                os.fchmod(fd, 0o666 & ~current_umask())
            except (AttributeError, OSError):
                pass
            try:
                with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                if exc.filename is None and exc.errno is not None:
                    raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
                raise
        while staged:
            tmp, path = staged[0]
            os.replace(tmp, path)
            staged.pop(0)
            _fsync_dir(path.parent)
    finally:
        for tmp, _ in staged:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
    return [Path(p) for p in files]


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """:func:`atomic_write_text` of ``obj`` as indented JSON (sorted keys; NaN/inf rejected)."""
    return atomic_write_text(path, json_text(obj))


def json_text(obj: Any) -> str:
    """The text of a JSON file the harness writes: indented, sorted keys, NaN/inf rejected."""
    return json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False, allow_nan=False) + "\n"


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # not supported (Windows): the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
