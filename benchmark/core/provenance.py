"""Where a result came from: code revision, library versions, machine, time, command line.

Stored in every table JSON (``provenance``) so that two tables can be told apart by what ran
them, not only by their numbers. Collecting it never fails: a piece that cannot be found is
``None`` (with a note where useful), never an exception.
"""

from __future__ import annotations

import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

# Distribution names whose versions a result records (python is added separately).
LIBRARIES = ("torch", "numpy", "scipy", "roma", "anny", "trimesh", "tqdm", "pyyaml", "motion-prior-benchmark")

REPO_ROOT = Path(__file__).resolve().parents[2]


def git_info(repo_dir: str | Path | None = None) -> dict:
    """``{"revision": sha | None, "dirty": bool | None, "note": str | None}`` of the checkout holding
    the harness. ``dirty`` is True when tracked files differ from the revision (untracked files,
    such as fresh results, are not counted)."""
    repo = Path(repo_dir) if repo_dir is not None else REPO_ROOT

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()

    try:
        revision = git("rev-parse", "HEAD")
    except (OSError, subprocess.SubprocessError) as exc:
        note = "not a git checkout" if isinstance(exc, subprocess.CalledProcessError) else f"git unavailable: {exc}"
        return {"revision": None, "dirty": None, "note": note}
    try:
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError) as exc:
        return {"revision": revision, "dirty": None, "note": f"git status failed: {exc}"}
    return {"revision": revision, "dirty": dirty, "note": None}


def library_versions() -> dict:
    """Installed versions of :data:`LIBRARIES` (``None`` when not installed) and ``python``."""
    versions = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    if versions.get("motion-prior-benchmark") is None:  # running from a checkout, not installed
        from benchmark import __version__

        versions["motion-prior-benchmark"] = f"{__version__} (not installed)"
    return versions


def cpu_name() -> str | None:
    """The CPU model (``/proc/cpuinfo`` on Linux, else ``platform.processor()``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or None


def gpu_info(device: str | None) -> dict | None:
    """Name and CUDA version of the accelerator ``device`` names (``cuda``, ``cuda:1``, ``mps``);
    ``None`` for a CPU run."""
    if not device or not (device.startswith("cuda") or device.startswith("mps")):
        return None
    try:
        import torch

        if device.startswith("mps"):
            return {"name": "Apple MPS", "cuda": None}
        if not torch.cuda.is_available():
            return {"name": None, "cuda": None, "note": "CUDA not available"}
        return {"name": torch.cuda.get_device_name(torch.device(device)), "cuda": torch.version.cuda,
                "cudnn": torch.backends.cudnn.version()}
    except Exception as exc:  # provenance must never take a finished run down
        return {"name": None, "cuda": None, "note": f"{type(exc).__name__}: {exc}"}


def collect_provenance(device: str | None = None, argv: list[str] | None = None, repo_dir: str | Path | None = None) -> dict:
    """Everything a table records about how it was made (timings are added by the derivation):
    ``git``, ``versions``, ``platform``, ``cpu``, ``gpu``, ``device``, ``timestamp`` (UTC, ISO 8601),
    ``command`` (the command line, shell-quoted)."""
    return {
        "git": git_info(repo_dir),
        "versions": library_versions(),
        "platform": platform.platform(),
        "cpu": cpu_name(),
        "gpu": gpu_info(device),
        "device": device,
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": shlex.join(sys.argv if argv is None else argv),
    }
