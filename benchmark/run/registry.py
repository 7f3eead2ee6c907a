"""The prior registry: entry points in the group ``benchmark.priors``, loaded lazily.

Registering imports nothing heavy: an entry point is a ``"module:Class"`` placeholder that is
imported on first use. A plug-in that fails to import is reported by name (``list`` shows the
error) and skipped; it never takes the CLI down, nor does a name two packages register (only
using that name fails; ``list`` shows the clash). The project's own priors register through the
same group (``pyproject.toml``), exactly like a third-party package would.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import zipfile
from pathlib import Path

from benchmark.core.plugins import PluginEntry, PluginRegistry

GROUP = "benchmark.priors"


class PriorEntry(PluginEntry):
    """A registered prior: ``target`` is ``"module:Class"``, ``origin`` the distribution that
    registered it or "runtime"."""

    kind = "prior"


PRIORS = PluginRegistry(PriorEntry, GROUP, warn_if_empty=True)
# the registry's API: registry() (name -> PriorEntry), register(name, target, origin="runtime") at run
# time (tests, notebooks; target is a class or "module:Class"), unregister(name),
# get_prior_class(name) (a KeyError naming close names, an ImportError for a broken plug-in)
registry = PRIORS.all
register = PRIORS.register
unregister = PRIORS.unregister
get_prior_class = PRIORS.load
prior_names = PRIORS.names


class WeightsFileError(ValueError):
    """A weights file that torch cannot read (empty, truncated, not a checkpoint)."""


# what torch.load raises on a file that is not a readable checkpoint
_LOAD_ERRORS = (EOFError, pickle.UnpicklingError, zipfile.BadZipFile, RuntimeError, OSError, KeyError, ValueError,
                UnicodeDecodeError, AttributeError, IndexError, TypeError)


def _torch_load_file(exc: BaseException) -> str | None:
    """The file a failing ``torch.load`` was reading, when ``exc`` was raised inside it."""
    tb = exc.__traceback__
    found = None
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_name == "load" and frame.f_code.co_filename.replace("\\", "/").endswith("torch/serialization.py"):
            f = frame.f_locals.get("f")
            found = str(f) if isinstance(f, (str, os.PathLike)) else getattr(f, "name", None) or "(a file object)"
        tb = tb.tb_next
    return found


def weights_files(adapter) -> list[Path]:
    """The weights files an adapter read (``adapter.weights_path``: one path or several joined by
    commas), those that exist."""
    raw = adapter.weights_path
    if not raw:
        return []
    parts = raw if isinstance(raw, (list, tuple)) else str(raw).split(",")
    return [Path(p) for p in parts if str(p).strip() and Path(str(p).strip()).is_file()]


def weights_content_sha256(adapter) -> str | None:
    """sha256 over the contents of :func:`weights_files` (None when the adapter reads none). A
    folder given as weights is hashed file by file (sorted)."""
    files = weights_files(adapter)
    raw = adapter.weights_path
    if not files and raw and not isinstance(raw, (list, tuple)) and Path(str(raw)).is_dir():
        files = sorted(p for p in Path(str(raw)).rglob("*") if p.is_file())
    if not files:
        return None
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def check_weights_option(weights: dict, priors, verb: str = "being run") -> None:
    """``--weights`` ({prior: path}) against the priors a command builds: a prior not among them, or
    a path that does not exist (a comma-separated list: its first file), is an error naming the
    option and the fix, raised before any work."""
    unknown = sorted(set(weights) - set(priors))
    if unknown:
        raise ValueError(f"--weights given for prior(s) {unknown} that are not {verb} ({', '.join(priors)}); "
                         "add them with --prior NAME or drop those --weights")
    for name, path in weights.items():
        if not Path(str(path).split(",")[0]).expanduser().exists():
            raise FileNotFoundError(f"--weights {name}={path}: no such file or folder")


def _where(name: str) -> str:
    entry = registry().get(name)
    return f"{entry.target}, from {entry.origin}" if entry is not None else "registered at run time"


def _check_prior_class(name: str, cls) -> None:
    """ValueError naming the entry point unless ``cls`` is a concrete PriorAdapter subclass."""
    import inspect

    from priors.base import PriorAdapter

    if not (isinstance(cls, type) and issubclass(cls, PriorAdapter)):
        raise ValueError(f"prior {name!r} ({_where(name)}) names {cls!r}, not a subclass of priors.base.PriorAdapter; "
                        "point the entry point at the adapter class (docs/adding-a-prior.md)")
    if inspect.isabstract(cls):
        missing = sorted(getattr(cls, "__abstractmethods__", ()))
        raise ValueError(f"prior {name!r} ({_where(name)}): {cls.__name__} does not implement {', '.join(missing)} "
                        "(abstract in priors.base.PriorAdapter or an interface it declares); implement them "
                        "(docs/adding-a-prior.md)")


def make_adapter(name: str, size: str = "embedded", weights: str | None = None, device: str = "cpu"):
    """Construct the registered prior ``name`` (``size``: "embedded" or "paper"; ``weights``: a
    checkpoint path or None for the embedded weights), moved to ``device`` and in eval mode.

    A weights file that ``torch.load`` cannot read (empty, truncated, a text file...) raises
    :class:`WeightsFileError` naming the file and the fix, instead of torch's bare EOFError /
    UnpicklingError / RuntimeError."""
    cls = get_prior_class(name)
    _check_prior_class(name, cls)
    try:
        adapter = cls(size=size, weights=weights, device=device)
    except _LOAD_ERRORS as exc:
        if isinstance(exc, TypeError) and "__init__()" in str(exc) and "argument" in str(exc):
            raise ValueError(f"prior {name!r} ({_where(name)}): {cls.__name__}(size=..., weights=..., device=...) "
                             f"failed ({exc}); a prior's constructor takes those three keyword arguments and passes "
                             "them to PriorAdapter.__init__ (docs/adding-a-prior.md)") from exc
        file, cause = None, exc
        while cause is not None and file is None:  # raw, or re-raised by the adapter ``from`` torch's error
            file = _torch_load_file(cause)
            if file is None:
                cause = cause.__cause__
        if file is None:
            raise
        exc = cause
        embedded = weights is None and size == "embedded"
        fix = (f"restore it (git checkout -- {file}) or retrain it (python -m benchmark train {name})" if embedded else
               "check the file: download it again, or pass the right file with --weights")
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else "no message"
        if len(detail) > 200:  # cut at the last sentence or clause that fits, never mid-word
            cut = max(detail.rfind(". ", 0, 200), detail.rfind("; ", 0, 200), detail.rfind(": ", 0, 200))
            detail = detail[:cut if cut > 40 else detail.rfind(" ", 0, 200)].rstrip(" .;:,(") + " ..."
        raise WeightsFileError(f"prior {name!r}: weights file {file} is not a readable torch checkpoint "
                               f"(empty, truncated or another format: {type(exc).__name__}: {detail}); fix: {fix}") from exc
    return adapter.to(device).eval()
