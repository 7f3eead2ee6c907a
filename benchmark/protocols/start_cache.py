"""The prior-free start on disk: :func:`~benchmark.protocols.start_search.prior_free_start`'s
result, shared by the worker processes of a run and by its resumptions.

Every prior of a table cell starts from the same prior-free search on the same observation (the
facing, then the limb start search), which takes minutes per cell on a CPU (20 to 30 on the sls
quick cells). In memory it is kept per process; a new worker, or a run resumed after a stop, would
search again. A table run on the local backend therefore keeps each search's result in
``<out>/cache/starts/`` (:func:`use_start_cache`, set by ``TableExecutor``), one file per
observation, and serves it back bit for bit: a unit computed from a stored start equals the unit
computed from a fresh search.

A file's name is the sha256 of its key (what the search depends on: the observation's fingerprint,
its facing rule, the objective and the search's sizes) and of the run's namespace: the table, its
protocol version and rules (less those only the descent reads, :data:`DESCENT_ONLY_KEYS`), torch's
version and the body (:func:`start_namespace`). Another protocol version, rule, torch or body
therefore searches again, never serves an old start; like
the stored work units, the stored starts outlive a change of code that moves no number (one that
does bumps the protocol version, docs/protocol.md). A file that cannot be read, or
whose stored key differs, is searched again with a warning. The Ray backend does not use it (its
workers may not share the driver's disk).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import torch

from benchmark.core.json_io import current_umask
from benchmark.protocols.fit_state import FitState

log = logging.getLogger(__name__)

START_CACHE_FOLDER = ("cache", "starts")  # under a run's --out
TENSOR_FIELDS = ("shape_param", "obs_t", "root", "trans", "heading", "offset")

_ACTIVE: list = []  # (folder, namespace) of the unit executing in this process


# The objective's keys that only the descent after the start reads (its step rule, its stopping
# test, several starts of the encoded rows): the prior-free search gets its rules as arguments (lr,
# lambda_prior, facing, start_fit; in its key), never these, so a run that differs from another in
# them alone (fit-check's longer probe, a raised step cap) finds the other's stored starts.
DESCENT_ONLY_KEYS = ("plateau", "step_rule", "schedule", "convergence", "multi_start")


def search_rules(rules: dict) -> dict:
    """A table's rules (:func:`benchmark.core.work_units.table_rules`) without the objective's
    :data:`DESCENT_ONLY_KEYS`: what a stored start's namespace names."""
    objective = rules.get("objective")
    if not isinstance(objective, dict):
        return dict(rules)
    return {**rules, "objective": {k: v for k, v in objective.items() if k not in DESCENT_ONLY_KEYS}}


def start_namespace(identity: dict) -> str:
    """What every stored start of a run depends on besides its key: ``identity`` (JSON-able: the
    table, its protocol version and rules (:func:`search_rules`), the body) and torch's version."""
    return hashlib.sha256(json.dumps({**identity, "torch": torch.__version__}, sort_keys=True, default=str).encode()).hexdigest()


def stored_starts(folder) -> list[Path]:
    """The starts stored in ``folder`` (the files this module writes there, nothing else), sorted;
    [] where it is no folder."""
    path = Path(folder)
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.is_file() and re.fullmatch(r"[0-9a-f]{64}\.pt", p.name))


def forget_starts(folder) -> int:
    """Remove the starts stored in ``folder`` (:func:`stored_starts`), so that a run asked to compute
    everything again (``run --resume never``) searches again too. Returns how many were removed."""
    ours = stored_starts(folder)
    for p in ours:
        p.unlink()
    return len(ours)


def share_starts(source_out, dest_out) -> int:
    """Copy the starts stored under the run folder ``source_out`` (``cache/starts``) into
    ``dest_out``'s, keeping any file already there; a run in ``dest_out`` reads those of the same
    namespace and key (fit-check's longer probe: the base run's observation and search, another step
    rule) and ignores the rest. Returns how many were copied."""
    dest = Path(dest_out).joinpath(*START_CACHE_FOLDER)
    copied = 0
    for p in stored_starts(Path(source_out).joinpath(*START_CACHE_FOLDER)):
        if not (dest / p.name).exists():
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, dest / p.name)
            copied += 1
    return copied


@contextmanager
def use_start_cache(folder, namespace: str):
    """Within the block, :func:`load` and :func:`store` use ``folder`` (None: no disk cache)."""
    if folder is None:
        yield
        return
    _ACTIVE.append((Path(folder), str(namespace)))
    try:
        yield
    finally:
        _ACTIVE.pop()


def _where(key: tuple) -> tuple[Path, str] | None:
    if not _ACTIVE:
        return None
    folder, namespace = _ACTIVE[-1]
    text = f"{namespace};{key!r}"
    return folder / f"{hashlib.sha256(text.encode()).hexdigest()}.pt", text


def read(key: tuple, device) -> dict | None:
    """The blob stored for ``key`` (its tensors on ``device``), or None: no disk cache in use, nothing
    stored, or a file that cannot be read or holds another key (a warning)."""
    where = _where(key)
    if where is None or not where[0].is_file():
        return None
    path, text = where
    try:
        blob = torch.load(path, map_location=device, weights_only=True)
        if not isinstance(blob, dict) or blob.get("key") != text:
            raise ValueError("its stored key differs from the one asked for")
        blob["log"] = json.loads(blob["log"])
    except Exception as exc:  # a damaged or foreign file: search again, never fail the unit
        log.warning("stored prior-free search %s cannot be read (%s: %s); searching again", path, type(exc).__name__, exc)
        return None
    log.info("prior-free search read from %s", path)
    return blob


def write(key: tuple, search_log: dict, **tensors) -> Path | None:
    """Store ``tensors`` (tensors, dicts of tensors, floats, bools) and ``search_log`` for ``key``,
    atomically (a stopped run leaves no partial file). Nothing is written without a disk cache in
    use, or for a log that JSON would not give back unchanged. A folder that cannot be written costs
    a warning, never the unit."""
    where = _where(key)
    if where is None:
        return None
    path, text = where
    log_text = json.dumps(search_log, sort_keys=True)
    if json.loads(log_text) != search_log:
        log.debug("prior-free search not stored: its log does not survive JSON unchanged")
        return None
    blob = {"key": text, "log": log_text, **tensors}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".start-", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                torch.save(blob, fh)
            os.chmod(tmp, 0o666 & ~current_umask())  # as the run's other files (mkstemp makes it 0600)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        log.warning("prior-free search not stored in %s (%s); a later worker will search again", path.parent, exc)
        return None
    return path


def load_state(key: tuple, adapter, device) -> tuple[FitState, dict] | None:
    """The start stored for ``key`` by :func:`store_state` (on ``device``, with ``adapter``) and the
    search's log, or None (:func:`read`). Its tensors are plain: the caller hands out leaf copies
    (``start_search._leaf_copy``), as it does of a start kept in memory."""
    blob = read(key, device)
    if blob is None:
        return None
    try:
        tensors = blob["tensors"]
        state = FitState(adapter=adapter, latents=dict(blob["latents"]), window_s=float(blob["window_s"]),
                         bounded_shape=bool(blob["bounded_shape"]), **{name: tensors.get(name) for name in TENSOR_FIELDS})
    except (KeyError, TypeError, AttributeError) as exc:
        log.warning("stored prior-free start for this observation lacks %s; searching again", exc)
        return None
    return state, blob["log"]


def store_state(key: tuple, state: FitState, search_log: dict) -> Path | None:
    """Store a prior-free start (every tensor of ``state``, on the CPU) and its search's log (:func:`write`)."""
    return write(key, search_log, window_s=float(state.window_s), bounded_shape=bool(state.bounded_shape),
                 latents={k: v.detach().cpu() for k, v in state.latents.items()},
                 tensors={name: getattr(state, name).detach().cpu() for name in TENSOR_FIELDS
                          if getattr(state, name) is not None})
