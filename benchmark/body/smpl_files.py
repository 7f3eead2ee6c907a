"""Read SMPL / SMPL-H / SMPL-X model files (``.npz`` or ``.pkl``) into plain numpy arrays.

Keys read (the same as the reference loaders, smplx and human_body_prior):

    v_template    (V, 3)        mean-shape T-pose vertices, metres
    shapedirs     (V, 3, B)     shape blend shapes (SMPL-X: B = 300 shape + 100 expression, or 10 + 10)
    posedirs      (V, 3, P)     pose blend shapes, P = 9 (J - 1), pose feature = (R_j - I) row-major, j = 1..J-1
    J_regressor   (J, V)        rest joints from rest vertices (a scipy sparse matrix in SMPL ``.pkl``)
    weights       (V, J)        skinning weights
    kintree_table (2, J)        row 0 = parent ids (root: 2**32 - 1 or -1), row 1 = joint ids
    f             (F, 3)        triangle faces

The model type follows from the number of joints: 24 SMPL, 52 SMPL-H, 55 SMPL-X.

The original SMPL / SMPL-H ``.pkl`` files are Python-2 pickles that hold chumpy objects and scipy
sparse matrices. They are read here without chumpy: a :class:`pickle.Unpickler` subclass maps every
``chumpy.*`` class to :class:`ChumpyStandIn`, which keeps the pickled state (a ``chumpy.ch.Ch`` keeps
its array under ``'x'``; a ``chumpy.reordering.Select`` is ``a.ravel()[idxs].reshape(preferred_shape)``),
and every ``scipy.sparse`` matrix class to :class:`SparseStandIn`, densified from its
``data / indices / indptr`` state. Nothing else is imported or called: besides those stand-ins the
unpickler knows only numpy arrays and scalars and plain containers (:data:`MODEL_PICKLE_GLOBALS`),
and a file that names anything else (``os.system``, ``builtins.eval``...) is refused with
:class:`benchmark.core.safe_loading.UnsafeFileError` before any of it runs.
"""

from __future__ import annotations

import _compat_pickle
import importlib
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmark.core.safe_loading import npz_read_error, unsafe_file_error

REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
MODEL_TYPES = {24: "smpl", 52: "smplh", 55: "smplx"}  # number of joints -> model type
_ROOT_PARENT_IDS = (-1, 2**32 - 1)
_CLEAN_FIX = (
    "re-export the file without chumpy (e.g. smplx's tools/clean_ch.py) or use the .npz release "
    "of the model"
)


class MissingKeyError(KeyError):
    """A required key is absent from a body-model file (the message names the file and the key)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class ChumpyStandIn:
    """Takes the place of any ``chumpy`` class while unpickling; keeps the pickled state.

    ``chumpy_class`` is ``"module.Name"`` of the class the pickle referred to.
    """

    chumpy_class = "chumpy"
    args: tuple = ()
    state = None  # set by __setstate__; unpickling usually bypasses __init__

    def __init__(self, *args, **kwargs):  # pickles made by __reduce__ may pass arguments
        self.args = args
        self.state = dict(kwargs) if kwargs else None

    def __setstate__(self, state):
        self.state = state


class SparseStandIn:
    """Takes the place of a ``scipy.sparse`` matrix class while unpickling; keeps its state."""

    sparse_class = "scipy.sparse"
    args: tuple = ()
    state = None

    def __init__(self, *args, **kwargs):
        self.args = args

    def __setstate__(self, state):
        self.state = state


_STAND_INS: dict[tuple[str, str], type] = {}


def _stand_in(base: type, module: str, name: str) -> type:
    key = (module, name)
    if key not in _STAND_INS:
        attr = "chumpy_class" if base is ChumpyStandIn else "sparse_class"
        _STAND_INS[key] = type(name, (base,), {attr: f"{module}.{name}"})
    return _STAND_INS[key]


# Everything a body-model pickle may name besides the chumpy and scipy.sparse classes (which become
# stand-ins): numpy arrays, dtypes and scalars, plain containers, and copyreg's reconstructor for
# Python-2 class pickles (it only calls ``__new__`` of classes that passed this same check). Names
# are checked after Python-2 names (``copy_reg``, ``__builtin__``) are mapped to Python 3's and
# ``numpy.core`` to ``numpy._core``.
MODEL_PICKLE_GLOBALS = frozenset({
    "numpy.ndarray", "numpy.dtype", "numpy._core.multiarray._reconstruct", "numpy._core.multiarray.scalar",
    "numpy._core.numeric._frombuffer", "copyreg._reconstructor", "_codecs.encode", "collections.OrderedDict",
    "builtins.object", "builtins.set", "builtins.frozenset", "builtins.list", "builtins.dict", "builtins.tuple",
    "builtins.int", "builtins.float", "builtins.complex", "builtins.bool", "builtins.str", "builtins.bytes",
    "builtins.bytearray",
})
_REFUSED_FIX = (
    "use the model file as published on the SMPL / SMPL-H / MANO website, or its .npz release "
    "(e.g. AMASS's smplh/neutral/model.npz, read without pickle)"
)


class _RefusedGlobal(pickle.UnpicklingError):
    def __init__(self, full_name: str):
        super().__init__(full_name)
        self.full_name = full_name


class _ModelUnpickler(pickle.Unpickler):
    """Unpickler for body-model files: chumpy and scipy.sparse classes become stand-ins, the
    names of :data:`MODEL_PICKLE_GLOBALS` are imported, anything else is refused."""

    def find_class(self, module: str, name: str):
        if (module, name) in _compat_pickle.NAME_MAPPING:  # Python-2 names
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        if module == "chumpy" or module.startswith("chumpy."):
            return _stand_in(ChumpyStandIn, module, name)
        if module == "scipy.sparse" or module.startswith("scipy.sparse."):
            return _stand_in(SparseStandIn, module, name)
        if module == "numpy.core" or module.startswith("numpy.core."):
            # numpy >= 2 moved numpy.core to numpy._core (old pickles name the former).
            module = "numpy._core" + module[len("numpy.core"):]
        if f"{module}.{name}" not in MODEL_PICKLE_GLOBALS:
            raise _RefusedGlobal(f"{module}.{name}")
        try:
            return getattr(importlib.import_module(module), name)
        except ModuleNotFoundError:  # numpy < 2 (the project allows 1.24): numpy._core is still numpy.core
            if not module.startswith("numpy._core"):
                raise
            return getattr(importlib.import_module("numpy.core" + module[len("numpy._core"):]), name)


def load_pickle_without_chumpy(path: str | Path) -> dict:
    """The raw dictionary of a body-model ``.pkl`` (Python 2 or 3), with stand-ins for chumpy/sparse.

    Does not need chumpy installed. Values may be numpy arrays, :class:`ChumpyStandIn` or
    :class:`SparseStandIn`; :func:`to_numpy` converts them.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        try:
            data = _ModelUnpickler(fh, encoding="latin1").load()  # latin1: Python-2 byte strings decode 1:1
        except _RefusedGlobal as exc:
            raise unsafe_file_error(path, [exc.full_name], _REFUSED_FIX) from None
        except Exception as exc:  # noqa: BLE001 - any failure means "not a readable model pickle"
            raise ValueError(f"{path}: could not unpickle the body-model file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a body-model .pkl must hold a dict, found {type(data).__name__}")
    return {(k.decode("latin1") if isinstance(k, bytes) else k): v for k, v in data.items()}


def to_numpy(value, where: str = "value") -> np.ndarray:
    """Convert a value read from a model file (array, chumpy or sparse stand-in) to a numpy array.

    ``where`` names the file and key in error messages.
    """
    if isinstance(value, ChumpyStandIn):
        return _chumpy_to_numpy(value, where)
    if isinstance(value, SparseStandIn):
        return _sparse_to_dense(value, where)
    if hasattr(value, "toarray"):  # a real scipy sparse matrix
        return np.asarray(value.toarray())
    return np.asarray(value)


def _state_dict(obj, where: str) -> dict:
    state = obj.state
    if isinstance(state, tuple) and len(state) == 2 and isinstance(state[0], (dict, type(None))):
        merged = dict(state[0] or {})  # (dict state, slot state) from __reduce_ex__
        merged.update(state[1] or {})
        state = merged
    if not isinstance(state, dict):
        cls = getattr(obj, "chumpy_class", None) or getattr(obj, "sparse_class", "?")
        raise ValueError(
            f"{where}: cannot read the pickled {cls} object: its state is a {type(state).__name__}, not a dict; "
            f"{_CLEAN_FIX}"
        )
    return {(k.decode("latin1") if isinstance(k, bytes) else k): v for k, v in state.items()}


def _chumpy_to_numpy(obj: ChumpyStandIn, where: str) -> np.ndarray:
    state = _state_dict(obj, where)
    cls = obj.chumpy_class
    if cls.rsplit(".", 1)[-1] == "Select" and {"a", "idxs"} <= state.keys():
        # chumpy.reordering.Select: a.r.ravel()[idxs].reshape(preferred_shape)
        source = to_numpy(state["a"], where).ravel()
        out = source[np.asarray(to_numpy(state["idxs"], where), dtype=np.int64)]
        shape = state.get("preferred_shape")
        return out.reshape(tuple(shape)) if shape is not None else out
    if "x" in state:  # chumpy.ch.Ch and other leaf nodes keep their array as 'x'
        return to_numpy(state["x"], where)
    raise ValueError(
        f"{where}: the pickled chumpy object {cls} holds no array under 'x' (state keys: {sorted(state)}); "
        f"it is a chumpy expression this reader does not evaluate; {_CLEAN_FIX}"
    )


def _sparse_to_dense(obj: SparseStandIn, where: str) -> np.ndarray:
    import scipy.sparse

    state = _state_dict(obj, where)
    fmt = obj.sparse_class.rsplit(".", 1)[-1][:3]
    shape = tuple(int(n) for n in state.get("_shape", state.get("shape", ())))
    try:
        if fmt in ("csc", "csr"):
            cls = scipy.sparse.csc_matrix if fmt == "csc" else scipy.sparse.csr_matrix
            matrix = cls((state["data"], state["indices"], state["indptr"]), shape=shape)
        elif fmt == "coo":
            row, col = state["coords"] if "coords" in state else (state["row"], state["col"])
            matrix = scipy.sparse.coo_matrix((state["data"], (row, col)), shape=shape)
        else:
            raise KeyError(f"unsupported sparse format {obj.sparse_class}")
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(
            f"{where}: cannot densify the pickled {obj.sparse_class} (state keys {sorted(state)}): {exc}"
        ) from exc
    return np.asarray(matrix.toarray())


def read_model_keys(path: str | Path, keys=REQUIRED_KEYS) -> tuple[dict, list[str]]:
    """Read ``keys`` (those present) from a model file; returns (key -> raw value, all keys in the file).

    ``.npz`` files are read without pickle, and only the requested keys are loaded (some releases
    hold object arrays, e.g. SMPL-X ``joint2num``, beside the numeric keys).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"body-model file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            archive = np.load(path, allow_pickle=False)
        except Exception as exc:  # not a zip (or truncated): numpy's message names neither the file nor the fix
            raise ValueError(f"{path}: not a readable .npz body-model file ({npz_read_error(path, exc)}); "
                             "download the model again") from None
        if not hasattr(archive, "files"):
            raise ValueError(f"{path}: holds a single array, not an .npz archive of named keys; download the model again")
        with archive:
            found = list(archive.files)
            values = {}
            for key in keys:
                if key in found:
                    try:
                        values[key] = archive[key]
                    except ValueError as exc:
                        raise ValueError(f"{path}: key {key!r} is an object array, not numbers ({exc})") from exc
        return values, found
    if suffix == ".pkl":
        raw = load_pickle_without_chumpy(path)
        return {k: raw[k] for k in keys if k in raw}, list(raw)
    raise ValueError(f"{path}: unsupported body-model file type {suffix!r}; expected .npz or .pkl")


@dataclass(frozen=True)
class BodyModelData:
    """The arrays of one SMPL-family model file, validated, as float64/int64 numpy arrays."""

    path: Path
    model_type: str  # "smpl" | "smplh" | "smplx"
    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, B) all shape components of the file (SMPL-X: without expressions)
    posedirs: np.ndarray  # (V, 3, 9 (J - 1))
    J_regressor: np.ndarray  # (J, V) dense
    weights: np.ndarray  # (V, J)
    parents: np.ndarray  # (J,) int64, parents[0] == -1, parents[j] < j
    faces: np.ndarray  # (F, 3) int64

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_joints(self) -> int:
        return self.parents.shape[0]

    @property
    def num_betas(self) -> int:
        """Shape components available in the file."""
        return self.shapedirs.shape[-1]


def read_body_model_file(path: str | Path) -> BodyModelData:
    """Read and validate an SMPL / SMPL-H / SMPL-X ``.npz`` or ``.pkl`` model file.

    Errors name the file, the key and what was expected.
    """
    path = Path(path)
    raw, found = read_model_keys(path, REQUIRED_KEYS)
    arrays = {}
    for key in REQUIRED_KEYS:
        if key not in raw:
            raise MissingKeyError(
                f"{path}: body-model file has no key {key!r} (found keys: {sorted(found)}); an SMPL / SMPL-H / "
                f"SMPL-X model file needs {', '.join(REQUIRED_KEYS)}"
            )
        arrays[key] = to_numpy(raw[key], where=f"{path}: key {key!r}")

    def fail(key, expected):
        raise ValueError(f"{path}: key {key!r} has shape {arrays[key].shape}, expected {expected}")

    v_template = arrays["v_template"].astype(np.float64)
    if v_template.ndim != 2 or v_template.shape[1] != 3:
        fail("v_template", "(V, 3)")
    V = v_template.shape[0]
    kintree = arrays["kintree_table"]
    if kintree.ndim != 2 or kintree.shape[0] != 2:
        fail("kintree_table", "(2, J)")
    J = kintree.shape[1]
    if J not in MODEL_TYPES:
        raise ValueError(
            f"{path}: kintree_table has {J} joints; supported are {sorted(MODEL_TYPES)} "
            f"({', '.join(f'{n} {t}' for n, t in MODEL_TYPES.items())})"
        )
    model_type = MODEL_TYPES[J]
    parents = _parents_from_kintree(kintree, path)

    shapedirs = arrays["shapedirs"].astype(np.float64)
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (V, 3):
        fail("shapedirs", f"({V}, 3, B)")
    if model_type == "smplx":
        # SMPL-X keeps expression directions after the shape directions: 300 + 100, or 10 + 10 (v1.0).
        shapedirs = shapedirs[:, :, : 300 if shapedirs.shape[-1] >= 400 else min(shapedirs.shape[-1], 10)]
    posedirs = arrays["posedirs"].astype(np.float64)
    if posedirs.ndim != 3 or posedirs.shape != (V, 3, 9 * (J - 1)):
        fail("posedirs", f"({V}, 3, {9 * (J - 1)}) for a {J}-joint {model_type} model")
    regressor = arrays["J_regressor"].astype(np.float64)
    if regressor.shape != (J, V):
        fail("J_regressor", f"({J}, {V})")
    weights = arrays["weights"].astype(np.float64)
    if weights.shape != (V, J):
        fail("weights", f"({V}, {J})")
    faces = arrays["f"].astype(np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        fail("f", "(F, 3)")
    if faces.size and (faces.min() < 0 or faces.max() >= V):
        raise ValueError(f"{path}: key 'f' indexes vertices outside 0..{V - 1}")
    return BodyModelData(
        path=path,
        model_type=model_type,
        v_template=v_template,
        shapedirs=shapedirs,
        posedirs=posedirs,
        J_regressor=regressor,
        weights=weights,
        parents=parents,
        faces=faces,
    )


def _parents_from_kintree(kintree: np.ndarray, path: Path) -> np.ndarray:
    """(2, J) kintree table -> (J,) parents indexed by joint id, root -1; checks a topological order."""
    table = np.asarray(kintree).astype(np.int64)
    J = table.shape[1]
    ids = table[1]
    if sorted(ids.tolist()) != list(range(J)):
        raise ValueError(f"{path}: kintree_table row 1 must list the joint ids 0..{J - 1}, got {ids.tolist()}")
    parents = np.empty(J, dtype=np.int64)
    parents[ids] = table[0]
    roots = np.isin(parents, _ROOT_PARENT_IDS)
    parents[roots] = -1
    if roots.sum() != 1 or parents[0] != -1:
        raise ValueError(f"{path}: kintree_table must have exactly one root, joint 0; parents {parents.tolist()}")
    if np.any(parents[1:] >= np.arange(1, J)) or np.any(parents[1:] < 0):
        raise ValueError(f"{path}: kintree_table parents must precede their children; parents {parents.tolist()}")
    return parents
