"""One checkpoint API for every prior.

Each prior's ``checkpoint`` module offers ``load(path, size) -> (network, CheckpointReport)``: it
recognises the file's format (the official release, or the project's ``{"state_dict", "config"}``
written by its training recipe), builds the network at the size the file describes and copies the
tensors in with :func:`load_state_strict`, the one strict state-dict loader every format goes
through: every tensor of the network present with its shape, nothing left over that the format
does not allow, and an error naming the file and the keys otherwise (never a silent partial load).
Files are read by :mod:`benchmark.core.safe_loading` (``torch.load(..., weights_only=True)``) before
anything is built.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping

import torch
from torch import nn

SHOWN = 20  # keys listed in an error before "and N more"


class CheckpointMismatchError(KeyError, ValueError):
    """A checkpoint whose tensors do not fit the network: missing, unexpected or wrongly shaped
    keys, or a fixed tensor that differs. A KeyError and a ValueError both, with a plain message."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


@dataclass
class CheckpointReport:
    """What a prior's ``checkpoint.load`` read.

    file: the (first) file read; files: every file read (a pair for the official frequency-guided
    release and for hmvae-trajectory); format: "project", or the official format's name;
    chosen_because: why this file (a folder was given: which snapshot); config: the network's
    configuration; loaded: the keys copied into the network; ignored: entries of the file that were
    not (official bookkeeping, duplicates); parts: the report of each sub-network read from its own
    file, by name.
    """

    file: Path
    format: str
    config: dict = field(default_factory=dict)
    loaded: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)
    chosen_because: str = "file given"
    files: list[Path] = field(default_factory=list)
    parts: dict[str, "CheckpointReport"] = field(default_factory=dict)

    def __post_init__(self):
        self.file = Path(self.file)
        self.files = [Path(f) for f in self.files] or [self.file]

    @property
    def weights_path(self) -> str:
        """The files read, joined by commas (what an adapter's ``weights_path`` holds)."""
        return ",".join(str(f) for f in self.files)


def _listed(keys: list[str]) -> str:
    more = f" and {len(keys) - SHOWN} more" if len(keys) > SHOWN else ""
    return f"{keys[:SHOWN]}{more}"


def _shape_of(t) -> object:
    return tuple(t.shape) if torch.is_tensor(t) else type(t).__name__


def load_state_strict(
    model: nn.Module,
    state: Mapping[str, object],
    file: str | Path,
    what: str,
    *,
    prefix: str = "",
    optional: Callable[[str], bool] | Iterable[str] = (),
    ignore_unexpected: bool = False,
    fixed: Iterable[str] = (),
    fixed_note: str = "",
    note: str = "",
    hint: Callable[[list[str], list[str]], str] | None = None,
) -> tuple[list[str], list[str]]:
    """Copy ``state`` into ``model`` strictly; returns (loaded keys as the model names them, ignored
    keys as the file names them), both sorted.

    The file's key for the model's ``k`` is ``prefix + k``. Every model key must be present, but
    those ``optional`` says (a predicate or a collection: BatchNorm counters older files lack, fixed
    tensors a project file leaves out); with ``ignore_unexpected`` the file's other keys are
    ignored (and returned), else they are an error. Every tensor must have the model's shape, and
    the ``fixed`` ones (masks, pooling matrices rebuilt from the model's config) the model's values
    (``fixed_note`` says why they differ). Errors (:class:`CheckpointMismatchError`) name ``file``,
    ``what``, the keys as the file names them with the expected shapes, then ``note`` (e.g. the
    network's configuration) and ``hint(missing, unexpected)`` (what the file looks like instead).
    """
    if not isinstance(state, Mapping) or not all(isinstance(k, str) for k in state):
        raise ValueError(f"{file}: not a state dict of the {what} (expected a dict of named tensors), "
                         f"found {type(state).__name__}")
    is_optional = optional if callable(optional) else set(optional).__contains__
    expected = model.state_dict()
    raw = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    missing = [k for k in expected if k not in raw and not is_optional(k)]
    unexpected = sorted(k for k in state if not (k.startswith(prefix) and k[len(prefix):] in expected))
    extra = "" if not note else f"; {note}"
    if missing or (unexpected and not ignore_unexpected):
        parts = []
        if missing:
            shapes = {prefix + k: tuple(expected[k].shape) for k in missing}
            parts.append(f"missing keys {_listed(list(shapes))} (expected shapes {_listed(list(shapes.values()))})")
        if unexpected and not ignore_unexpected:
            parts.append(f"unexpected keys {_listed(unexpected)}")
        more = hint(missing, unexpected) if hint is not None else ""
        raise CheckpointMismatchError(f"{file}: the {what} checkpoint does not match the network: "
                                      f"{', '.join(parts)}{more}{extra}")
    bad = [f"{prefix + k}: file {_shape_of(raw[k])}, expected {tuple(ref.shape)}"
           for k, ref in expected.items() if k in raw and (not torch.is_tensor(raw[k]) or raw[k].shape != ref.shape)]
    if bad:
        raise CheckpointMismatchError(f"{file}: {len(bad)} tensor(s) of the {what} checkpoint have the wrong shape: "
                                      f"{_listed(bad)}; expected the shapes of the network{extra}")
    for k in sorted(set(fixed) & set(raw)):
        if not torch.equal(raw[k].to(expected[k].dtype), expected[k]):
            raise CheckpointMismatchError(f"{file}: fixed tensor {prefix + k!r} of the {what} differs from the "
                                          f"network's own{f' ({fixed_note})' if fixed_note else ''}")
    mapped = {k: raw[k] for k in expected if k in raw}
    params = {name for name, _ in model.named_parameters()}
    nonfinite = [prefix + k for k, t in sorted(mapped.items()) if t.is_floating_point() and bool(
        (~torch.isfinite(t) if k in params else torch.isnan(t)).any())]  # a buffer may hold an inf mask
    if nonfinite:
        raise CheckpointMismatchError(f"{file}: {len(nonfinite)} tensor(s) of the {what} checkpoint hold NaN or inf "
                                      f"values: {_listed(nonfinite)} (a diverged training?); retrain, or give the "
                                      "checkpoint of a finished training")
    model.load_state_dict(mapped, strict=False)  # every required key checked above
    return sorted(mapped), (unexpected if ignore_unexpected else [])


def check_size(prior: str, size: str) -> None:
    """A ValueError unless ``size`` is "embedded" or "paper"."""
    if size not in ("embedded", "paper"):
        raise ValueError(f"{prior}: unknown size {size!r}; expected 'embedded' or 'paper'")


__all__ = ["CheckpointMismatchError", "CheckpointReport", "check_size", "load_state_strict"]
