"""Opening a user's file never runs code from it.

A pickle (a torch checkpoint is one, and so is an SMPL ``.pkl``) may name any Python callable and
have the reader call it: ``os.system``, ``builtins.eval``... The harness therefore reads

- every torch file with ``torch.load(..., weights_only=True)`` (tensors, numbers, strings, lists,
  tuples, dicts, ``OrderedDict``, optimiser state): :func:`torch_load_weights`;
- an official format that pickles more than that through an allow-list of the names it may hold
  (exact names, and a few modules such as ``omegaconf``), each read as an :class:`InertStandIn`
  that only records what it was given: the real class or function is never imported or called
  (:func:`torch_load_with_stand_ins`; the bookkeeping of a PyTorch-Lightning checkpoint,
  :func:`is_lightning_bookkeeping`);
- the SMPL ``.pkl`` files with a restricted unpickler of their own
  (:mod:`benchmark.body.smpl_files`).

A file that names anything else is refused, before it is unpickled when the names can be listed
up front: :class:`UnsafeFileError` (a ``ValueError``, printed by the CLI as one ``error:`` line)
names the file, the refused globals and the fix.
"""

from __future__ import annotations

import _compat_pickle
import io
import pickle
import pickletools
import re
import zipfile
from pathlib import Path
from typing import Callable, Iterable

import torch

STATE_DICT_FIX = (
    "if you trust the file, re-save only its tensors from Python: "
    "torch.save(model.state_dict(), 'weights.pt') (or torch.save({'state_dict': model.state_dict()}, 'weights.pt'))"
)


class UnsafeFileError(ValueError):
    """A file that holds objects the harness will not unpickle (reading them could run code)."""


def unsafe_file_error(file: str | Path, names: Iterable[str], fix: str = STATE_DICT_FIX) -> UnsafeFileError:
    """The error for ``file``, which refers to the globals ``names`` (e.g. ``posix.system``)."""
    names = sorted(set(names))
    shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
    return UnsafeFileError(
        f"{file}: holds objects the harness will not unpickle ({shown or 'unknown globals'}): opening it could run "
        f"code from the file, so it was not read; fix: {fix}"
    )


class InertStandIn:
    """Takes the place of an allow-listed class or function while unpickling.

    Creating, calling or filling it only records the arguments (``args``) and the pickled state
    (``state``); it has no other behaviour. ``pickled_name`` is the ``module.name`` it replaces.
    """

    pickled_name = "?"

    def __new__(cls, *args, **kwargs):
        obj = object.__new__(cls)
        obj.args, obj.state = args, None
        return obj

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self.state = state

    def __repr__(self) -> str:
        return f"<inert stand-in for {self.pickled_name}>"


_STAND_INS: dict[str, type] = {}


def stand_in(full_name: str) -> type:
    """The :class:`InertStandIn` subclass for the global ``module.name`` (one per name)."""
    if full_name not in _STAND_INS:
        module, _, name = full_name.rpartition(".")
        _STAND_INS[full_name] = type(name, (InertStandIn,), {"pickled_name": full_name, "__module__": module or "?",
                                                            "__qualname__": name})
    return _STAND_INS[full_name]


# The bookkeeping a PyTorch-Lightning checkpoint may pickle besides its tensors: callback classes used
# as dict keys (Lightning 1.x), hyper-parameters as OmegaConf / DotMap / argparse objects and the
# type objects their metadata refers to. Only the harness's stand-ins are ever created for them.
_LIGHTNING_MODULES = ("pytorch_lightning.", "lightning.", "lightning_fabric.", "omegaconf.", "dotmap.")
_LIGHTNING_NAMES = frozenset({
    "argparse.Namespace", "typing.Any", "pathlib.Path", "pathlib.PosixPath", "pathlib.WindowsPath",
    "builtins.object", "builtins.dict", "builtins.list", "builtins.tuple", "builtins.str", "builtins.int",
    "builtins.float", "builtins.bool", "numpy.dtype", "numpy.core.multiarray.scalar", "numpy._core.multiarray.scalar",
})


def is_lightning_bookkeeping(full_name: str) -> bool:
    """Whether ``module.name`` is Lightning bookkeeping that may be read as an inert stand-in."""
    return full_name in _LIGHTNING_NAMES or full_name.startswith(_LIGHTNING_MODULES)


_GLOBAL_IN_MESSAGE = re.compile(r"GLOBAL ([A-Za-z_][\w.]*)")


def _unsafe_globals(file: Path) -> list[str] | None:
    """The globals of a zip-format torch file that ``weights_only=True`` does not allow by default
    (read statically, nothing is unpickled); None when they cannot be listed (legacy format,
    unreadable file: ``torch.load`` then reports the first one, or why the file is unreadable)."""
    try:
        return sorted(torch.serialization.get_unsafe_globals_in_checkpoint(file))
    except Exception:  # noqa: BLE001 - not a zip checkpoint, truncated, an opcode the scanner does not know
        return None


def pickle_globals(file: str | Path, max_pickles: int = 5) -> set[str]:
    """``module.name`` of every global the pickles at the start of ``file`` refer to, read
    statically with :mod:`pickletools` (nothing is unpickled). A legacy torch file is a sequence of
    pickles (magic number, version, system info, the content, storage keys) followed by raw data;
    scanning stops at the first byte that does not parse. ``STACK_GLOBAL`` names are read from the
    strings pushed just before it (memo lookups included), which is how pickle writes them."""
    found: set[str] = set()
    if zipfile.is_zipfile(file):  # torch's format since 1.6: the content is the archive's data.pkl
        with zipfile.ZipFile(file) as archive:
            names = [n for n in archive.namelist() if n == "data.pkl" or n.endswith("/data.pkl")]
            data = archive.read(min(names, key=len)) if names else b""
        stream, max_pickles = io.BytesIO(data), 1
    else:
        stream = open(file, "rb")
    with stream as fh:
        for _ in range(max_pickles):
            strings: list[str] = []  # the strings pushed so far, in order
            memo: dict = {}  # memo index -> string (other memoized values are not needed)
            top = None  # the last value pushed, when it is a string
            try:
                for op, arg, _pos in pickletools.genops(fh):
                    name, pushed = op.name, None
                    if name in ("GLOBAL", "INST"):
                        found.add(str(arg).replace(" ", "."))
                    elif name == "STACK_GLOBAL" and len(strings) >= 2:
                        found.add(f"{strings[-2]}.{strings[-1]}")
                    elif isinstance(arg, str) and ("UNICODE" in name or "STRING" in name):
                        pushed = arg
                    elif name in ("GET", "BINGET", "LONG_BINGET"):
                        pushed = memo.get(arg)
                    if name in ("MEMOIZE", "PUT", "BINPUT", "LONG_BINPUT"):
                        index = len(memo) if name == "MEMOIZE" else arg
                        memo[index] = top  # memoizing leaves the stack as it was
                        continue
                    if pushed is not None:
                        strings.append(pushed)
                    top = pushed
            except Exception:  # noqa: BLE001 - end of the pickles (raw storage bytes) or not a pickle
                break
    return {py3_name(n) for n in found}


def py3_name(full_name: str) -> str:
    """``module.name`` with Python 2's names (``__builtin__``, ``copy_reg``...) mapped to Python 3's,
    as the unpickler maps them."""
    module, _, name = full_name.rpartition(".")
    module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
    return f"{_compat_pickle.IMPORT_MAPPING.get(module, module)}.{name}"


def _other_refused_globals(file: Path) -> list[str]:
    """For the message only: the globals of ``file`` that ``weights_only`` does not allow by
    default, besides the first one torch reports (empty when they cannot be listed)."""
    try:
        from torch._weights_only_unpickler import _get_allowed_globals  # private: a better message, if present

        allowed = set(_get_allowed_globals())
        return sorted(n for n in pickle_globals(file) if n not in allowed)
    except Exception:  # noqa: BLE001
        return []


def torch_load_with_stand_ins(file: str | Path, allow: Callable[[str], bool] | None = None,
                              fix: str = STATE_DICT_FIX) -> tuple[object, list[str]]:
    """``torch.load(file, map_location="cpu", weights_only=True)``; the globals for which ``allow``
    is true are read as :class:`InertStandIn` objects. Returns (content, names read as stand-ins).

    Raises :class:`UnsafeFileError` (naming ``file``, the globals and ``fix``) when the file refers
    to anything else; torch's own errors for unreadable files (empty, truncated) pass through.
    """
    file = Path(file)
    unsafe = _unsafe_globals(file) or []
    refused = [n for n in unsafe if allow is None or not allow(n)]
    if refused:
        raise unsafe_file_error(file, refused, fix)
    extra = [(stand_in(n), n) for n in unsafe]
    try:
        with torch.serialization.safe_globals(extra):
            content = torch.load(file, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # legacy format, a plain pickle, or an opcode torch's static scan does not know (pickle
        # protocol 4): torch stopped at its first unknown global or opcode
        # torch's message drops the "builtins." of builtins ("GLOBAL exec"): put it back
        named = [n if "." in n else f"builtins.{n}" for n in _GLOBAL_IN_MESSAGE.findall(str(exc))]
        named += [n for n in _other_refused_globals(file) if allow is None or not allow(n)]
        if named:
            raise unsafe_file_error(file, named, fix) from None
        raise
    return content, [n for _, n in extra]


def torch_load_weights(file: str | Path, fix: str = STATE_DICT_FIX) -> object:
    """``torch.load(file, map_location="cpu", weights_only=True)`` with :class:`UnsafeFileError`
    for a file that refers to anything ``weights_only`` does not allow."""
    return torch_load_with_stand_ins(file, None, fix)[0]


def npz_read_error(file: str | Path, exc: BaseException) -> str:
    """Why ``np.load(file, allow_pickle=False)`` failed, in words that fit the file.

    numpy reads any file that is not a zip archive as a single array, and one whose bytes are not
    an ``.npy`` header either as a pickle, which ``allow_pickle=False`` refuses: so a truncated
    download, or a text or ``.ply`` file renamed ``.npz``, is reported as "contains pickled (object)
    data", which sends a user looking for a pickle that is not there."""
    path = Path(file)
    try:
        size = path.stat().st_size
        is_zip = zipfile.is_zipfile(path)
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if size == 0:
        return "is empty (0 bytes)"
    if not is_zip:
        return (f"its {size} bytes are not a zip archive, and a .npz is a zip of .npy arrays: the file is cut short "
                "or is another format named .npz")
    return f"{type(exc).__name__}: {exc}"
