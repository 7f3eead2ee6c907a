"""The report's folder: ``index.html`` and ``img/``, and the marker (:data:`~benchmark.core.outdir.MARKER_NAME`)
that records what the report wrote there (the files under ``img/``, a checksum of ``index.html``).

A later report into the same folder replaces that earlier output, and only that: a folder with no
marker, files the marker does not list, or an ``index.html`` changed since the report wrote it is
refused before anything is written or deleted. What a page says (a user's notes may well mention
``python -m benchmark report``) never makes it the report's own.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from benchmark.core.outdir import LOCK_NAME, MARKER_NAME, OutDirError, read_marker, remove_entries, write_marker

COMMAND = "report"
REPORT_ENTRIES = ("index.html", "img")  # what the report writes into its folder, besides the marker
LEGACY_MARKER = Path("img") / ".benchmark-report"  # what reports before the marker wrote: recognised, not trusted
NOTE = "written by python -m benchmark report; the next report into this folder replaces only these entries"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _files(folder: Path, name: str) -> list[str]:
    root = folder / name
    if not root.is_dir():
        return []
    return sorted(p.relative_to(folder).as_posix() for p in root.rglob("*") if not p.is_dir())


def check_report_folder(folder: str | Path, what: str = "--out") -> None:
    """Refuse (:class:`OutDirError`, nothing written or deleted) a folder that holds anything but an
    earlier report, as its marker records it. A new or empty folder is fine."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    entries = sorted(p.name for p in folder.iterdir() if p.name not in (MARKER_NAME, LOCK_NAME))
    if not entries:
        return
    marker = read_marker(folder)
    keep = "the report replaces its folder's index.html and img/, so nothing was written or deleted"
    if marker is None or marker.get("command") != COMMAND:
        if marker is None and (folder / LEGACY_MARKER).is_file():
            raise OutDirError(f"{what} {folder}: holds a report from an older harness, which recorded no list of its "
                              f"files (no {MARKER_NAME}); {keep}. If you changed nothing there, delete the folder "
                              f"yourself; or choose an empty or new {what}")
        whose = f"no marker {MARKER_NAME}" if marker is None else f"its marker {MARKER_NAME} names {marker.get('command')!r}"
        raise OutDirError(f"{what} {folder}: holds files the report did not write ({', '.join(entries[:3])}{_more(entries)}; "
                          f"{whose}); {keep}: choose an empty or new {what}")
    foreign = [n for n in entries if n not in REPORT_ENTRIES]
    recorded = marker.get("files") if isinstance(marker.get("files"), dict) else None
    if recorded is not None:  # None: a report stopped before it finished, whose files are all its own
        mine = {str(f) for f in recorded.get("img", []) if isinstance(recorded.get("img"), list)}
        foreign += [f for f in _files(folder, "img") if f not in mine]
    index = folder / "index.html"
    if index.exists() and not (index.is_file() and marker.get("index_sha256") == _sha256(index)):
        foreign.append("index.html (changed since the report wrote it)")
    if foreign:
        raise OutDirError(f"{what} {folder}: holds files the report did not write ({', '.join(foreign[:3])}{_more(foreign)}); "
                          f"{keep}: move them away or choose an empty or new {what}")


def _more(names) -> str:
    return f" and {len(names) - 3} more" if len(names) > 3 else ""


def start_report_folder(folder: Path) -> Path:
    """After :func:`check_report_folder`: the earlier report removed, the marker of a report in
    progress written, ``img/`` made. Returns ``img/``."""
    remove_entries(folder, REPORT_ENTRIES)
    folder.mkdir(parents=True, exist_ok=True)
    write_marker(folder, COMMAND, REPORT_ENTRIES, extra={"note": NOTE})
    img = folder / "img"
    img.mkdir()
    return img


def finish_report_folder(folder: Path) -> None:
    """Record what the report wrote: the files under ``img/`` and the checksum of ``index.html``."""
    write_marker(folder, COMMAND, REPORT_ENTRIES, files=True, extra={"note": NOTE, "index_sha256": _sha256(folder / "index.html")})
