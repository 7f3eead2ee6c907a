"""The prior contract in one place: what a prior declares and provides to the protocols.

The protocol (not the adapter) owns the optimiser loop, the data term, the free rigid parameters,
interpolation to output timestamps and the schedule, so every prior is judged by the same rules.
An adapter owns only its model: how latents start, how they decode to body parameters at given
timestamps, and its prior term.

Adding a prior: ``docs/adding-a-prior.md`` walks from an empty folder to
``python -m benchmark check-prior NAME`` passing and a row in
``python -m benchmark run table1 --profile smoke --prior NAME``, with a complete example package in
the layout every learned prior here uses (``priors/vposer/`` is the nearest real one)::

    my-prior/
        pyproject.toml      registers the prior (entry-point group "benchmark.priors")
        my_prior/
            __init__.py     the method in its docstring; exports the adapter
            model.py        the networks at any size, pure torch, no I/O
            checkpoint.py   load(path, size) -> (network, CheckpointReport), read strictly
            adapter.py      the PriorAdapter
            train.py        the training recipe

The contract, in short. An adapter subclasses :class:`PriorAdapter` and *declares* (class
attributes, each with a default here) ``name`` (registry name), ``paper``, ``window`` (a
:class:`WindowSpec`: "per-frame", "fixed" or "continuous"), ``encodes_translation`` and
``encodes_root_orientation`` (False: the protocol fits them, free, on top of ``decode``),
``heading_normalised`` (True: the protocol frees one heading per window), ``joints``,
``shape_conditioned``, ``sixd_layout``, ``constant_latents``, ``default_weights`` (the embedded
checkpoint, see :meth:`PriorAdapter.embedded_weights`) and ``frozen_network``; it is constructed as
``cls(size=, weights=, device=)`` (the base sets ``size``, ``weights_path`` and ``checkpoint``) and
*provides* the three abstract methods ``init_latents`` (a dict of batch-first tensors, random only
through ``generator``), ``decode`` (latents -> :class:`Decoded` at the requested timestamps,
differentiable) and ``prior_term`` ((B,) penalty); ``mean_latents`` is optional (default None).

Everything else a prior can do is an *interface* it opts into by subclassing it next to
:class:`PriorAdapter` (the harness asks ``isinstance``, never ``hasattr``):

- :class:`MotionEncoder`: ``encode_motion`` (the reconstruction table, encoder starts of the motion
  tables and of table1);
- :class:`MotionDenoiser`: ``denoise_motion`` (the prior's own denoiser, the denoise table);
- :class:`AnchorDecoder`: ``decode_anchors`` (decoded anchors and their timestamps, the sls table);
- :class:`Trainable`: the classmethod ``train_embedded`` (``python -m benchmark train NAME``);
- :class:`ExportableDecoder`: ``export_decoder`` (``python -m benchmark export-onnx NAME``);
- :class:`PaperNetwork`: the classmethod ``paper_network`` (``describe NAME --size paper``);
- :class:`InterpolationBaseline`: no method; the motion tables take its latents as they are.

Minimal example: a complete adapter in one module that passes ``check-prior`` (free per-frame
poses pulled towards the T-pose; ``priors/no_prior.py`` is the same with no pull)::

    import torch
    from benchmark.core.rotations import matrix_to_sixd, sixd_to_matrix
    from priors.base import Decoded, FitBatch, PriorAdapter, WindowSpec

    class TPosePull(PriorAdapter):
        name = "tpose-pull"
        paper = "example: per-frame poses with a quadratic pull towards the T-pose"
        window = WindowSpec(kind="per-frame")  # one latent per observed frame; the protocol SLERPs
        encodes_translation = False  # the protocol fits translation ...
        encodes_root_orientation = False  # ... and root orientation
        heading_normalised = False

        def __init__(self, size="embedded", weights=None, device="cpu"):
            super().__init__(size=size, weights=weights, device=device)
            self.register_buffer("eye6", matrix_to_sixd(torch.eye(3), layout="interleaved"))

        def init_latents(self, batch: FitBatch, generator: torch.Generator):
            noise = 0.01 * torch.randn(batch.batch_size, batch.num_observed, 21, 6, generator=generator)
            return {"pose": self.eye6 + noise.to(self.device)}

        def decode(self, latents, timestamps, shape=None):
            body = sixd_to_matrix(latents["pose"], layout="interleaved")  # (B, n, 21, 3, 3)
            root = torch.eye(3, dtype=body.dtype, device=body.device).expand(*body.shape[:2], 1, 3, 3)
            return Decoded(rotations=torch.cat([root, body], dim=2))  # identity root, trans=None

        def prior_term(self, latents):
            return (latents["pose"] - self.eye6).square().sum((-1, -2)).mean(-1)  # (B,)

and in your package's ``pyproject.toml``, then ``pip install -e .``::

    [project.entry-points."benchmark.priors"]
    tpose-pull = "my_package.my_module:TPosePull"
"""

from __future__ import annotations

import abc
import contextlib
import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Literal

import torch

from benchmark.core.skeleton import NUM_JOINTS

if TYPE_CHECKING:
    from priors.checkpoints import CheckpointReport


@dataclass(frozen=True)
class WindowSpec:
    """How a prior covers time.

    kind:
      "per-frame"   one latent per observed frame, decoded at the observed timestamps; the protocol
                    interpolates (SLERP/LERP) to any other timestamp (VPoser+SLERP, no-prior).
      "fixed"       fixed windows of ``frames`` frames at ``fps``, ``duration_s = frames / fps``; a
                    longer sequence is covered by consecutive non-overlapping windows, each with its
                    own latents; decoded on the window's grid, the protocol interpolates between grid
                    frames (HM-VAE, the frequency-guided prior).
      "continuous"  decoded directly at any timestamps (sequential primitives).
    """

    kind: Literal["per-frame", "fixed", "continuous"] = "continuous"
    frames: int | None = None
    fps: float | None = None

    @property
    def duration_s(self) -> float | None:
        return None if self.frames is None or self.fps is None else self.frames / self.fps


@dataclass
class FitBatch:
    """What an adapter may look at when it initialises latents (observations of B sequences)."""

    points: torch.Tensor  # (B, n, N, 3) observed points, padded
    lengths: torch.Tensor  # (B, n) valid points per observed frame
    timestamps: torch.Tensor  # (B, n) observed timestamps (s), relative to the window start
    window_s: float  # duration of the window to reconstruct
    output_timestamps: torch.Tensor  # (B, T_out)

    @property
    def batch_size(self) -> int:
        return self.points.shape[0]

    @property
    def num_observed(self) -> int:
        return self.points.shape[1]


@dataclass
class Decoded:
    """Body parameters decoded by a prior at the requested timestamps.

    rotations: (B, T, 22, 3, 3) local rotations in the SMPL convention; joints outside the prior's
        subset are identity. The root (joint 0) is the prior's root orientation, or identity when the
        prior does not encode it (the protocol then applies its free root orientation on top).
    trans: (B, T, 3) root translation in metres, or None when the prior does not encode it.
    """

    rotations: torch.Tensor
    trans: torch.Tensor | None = None
    extra: dict = field(default_factory=dict)


@dataclass
class ExportSpec:
    """What :meth:`ExportableDecoder.export_decoder` returns.

    module: an ``nn.Module`` in eval mode whose ``forward(*inputs)`` takes latent tensors (batch
        first) and returns a tuple of tensors (batch first), e.g. rotations (B, T, 22, 3, 3) and,
        where the prior encodes it, translation (B, T, 3). No Python control flow on values.
    example_inputs: a tuple of example tensors with batch size >= 2.
    input_names / output_names: ONNX names, one per input / output.
    """

    module: torch.nn.Module
    example_inputs: tuple
    input_names: list
    output_names: list


class PriorAdapter(torch.nn.Module, metaclass=abc.ABCMeta):
    """Base class of every prior adapter (see module docstring).

    Abstract: a subclass that does not provide ``init_latents``, ``decode`` and ``prior_term`` cannot
    be instantiated. The optional capabilities are the interfaces below (:class:`MotionEncoder`,
    :class:`MotionDenoiser`, :class:`AnchorDecoder`, :class:`Trainable`, :class:`ExportableDecoder`,
    :class:`PaperNetwork`, :class:`InterpolationBaseline`), subclassed beside this class.
    """

    # -- declarations (class attributes) ---------------------------------------------------
    name: str = "prior"
    paper: str = ""
    window: WindowSpec = WindowSpec()
    encodes_translation: bool = False
    encodes_root_orientation: bool = False
    heading_normalised: bool = False  # decoder outputs a canonical heading; the protocol frees one per window
    joints: tuple[int, ...] = tuple(range(1, NUM_JOINTS))  # body joints the prior models
    shape_conditioned: bool = False
    sixd_layout: str | None = None  # "interleaved" (VPoser/Xu) or "columns" (HM-VAE), if it uses 6D
    constant_latents: tuple[str, ...] = ()  # latents entries the decoder reads but never optimises (no gradient)
    frozen_network: str | None = None  # the submodule holding the trained network, kept frozen and in eval mode
    default_weights: ClassVar[Path | None] = None  # the embedded checkpoint size "embedded" reads without --weights
    # Bumped when a change to the adapter's code moves its numbers under the same weights (its
    # latents' units, its start): from 2 on it enters the work units' identity, so units stored by
    # an older revision are recomputed, not reused (revision 1 is left out, keeping stored units valid)
    adapter_revision: ClassVar[int] = 1

    # -- set by the constructor ------------------------------------------------------------
    size: str = "embedded"
    weights_path: str | None = None  # the file(s) the weights came from (several joined by commas), or None
    checkpoint: CheckpointReport | None = None  # what the checkpoint loader read (priors.checkpoints)

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__()
        self.size = size
        self.weights_path = weights
        self._device = torch.device(device)

    # -- the three things a prior provides -------------------------------------------------
    @abc.abstractmethod
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Initial latents for a batch: a prior sample or an encoder's output. Each tensor (B, ...)."""

    @abc.abstractmethod
    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """Body parameters at ``timestamps`` (B, T) seconds from the window start.

        per-frame priors are only asked for their latents' own (observed) timestamps; fixed-window
        priors are asked for their window grid; continuous priors for any timestamps.
        """

    @abc.abstractmethod
    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) the prior's penalty on the latents (e.g. mean over latent codes of |z|^2)."""

    # -- optional, with a default ----------------------------------------------------------
    def mean_latents(self, batch: FitBatch) -> dict[str, torch.Tensor] | None:
        """The prior's mean latents for a batch (same keys and shapes as :meth:`init_latents`), for
        priors whose :meth:`init_latents` draws a random sample of the prior; None (the default)
        where the initialisation is already deterministic (an encoder's output, a rest pose).

        table1 protocol v3 (``objective.latent_init: mean``) starts such priors here: a deterministic
        start, as ``no-prior``'s T-pose is, instead of one random draw (the paper's "a random
        sample from the prior"; docs/protocol.md, table1 version 3), whose luck the tables would
        otherwise measure.
        """
        return None

    def batch_rows(self, rows: torch.Tensor) -> contextlib.AbstractContextManager:
        """A context in which :meth:`decode` and :meth:`prior_term` serve the sequences ``rows``
        ((R,) long) of the batch the adapter was last initialised for (:meth:`init_latents`,
        ``encode_motion``), given their rows of the latents only. A plateau descent evaluates the
        sequences still descending this way (``benchmark.protocols.kept_rows``). The default does
        nothing: right for an adapter whose outputs for a sequence depend on that sequence's inputs
        only. An adapter that keeps per-batch tensors (e.g. the initial latents its prior term pulls
        towards) selects their rows here; one that does neither is detected at the start of each fit
        and evaluated whole."""
        return contextlib.nullcontext()

    @property
    def has_encoder(self) -> bool:
        """Whether the tables use this prior's :meth:`MotionEncoder.encode_motion` (the reconstruction
        table, the encoder starts): True for every :class:`MotionEncoder`. A prior whose
        ``encode_motion`` is only an exact change of representation (``no-prior``) declares
        ``has_encoder = False``: table1's per-frame start search still uses it."""
        return isinstance(self, MotionEncoder)

    # -- the device, the weights, the network -----------------------------------------------
    @property
    def device(self) -> torch.device:
        """The device of the adapter's tensors (its first parameter or buffer), else the one it was built for."""
        for t in itertools.chain(self.parameters(), self.buffers()):
            return t.device
        return self._device

    @classmethod
    def embedded_weights(cls, weights: str | Path | None = None, otherwise: str = "") -> Path:
        """The checkpoint size "embedded" loads: ``weights`` when given, else ``default_weights``.
        When it is absent: FileNotFoundError naming the file, the command that trains it and
        ``otherwise`` (e.g. where the official weights are)."""
        path = Path(weights) if weights is not None else cls.default_weights
        if path is None:
            raise ValueError(f"prior {cls.name!r} declares no default_weights: pass the weights file")
        if not path.exists():
            if weights is not None:  # a path the user gave: most likely mistyped
                raise FileNotFoundError(f"{cls.name} weights {path}: no such file; check the path given with --weights "
                                        f"(or leave --weights out for the embedded weights)")
            how = (f"Train them with `python -m benchmark train {cls.name}`" if issubclass(cls, Trainable) else
                   "Put the prior's weights file there, or pass one with --weights")
            raise FileNotFoundError(f"embedded {cls.name} weights not found: {path}. {how}"
                                    + (f", {otherwise}" if otherwise else ""))
        return path

    @property
    def trained_network(self) -> torch.nn.Module | None:
        """The trained network (the submodule named by ``frozen_network``), None for a prior without one.
        A name that is no submodule is a ValueError naming the declaration (not an AttributeError,
        which ``nn.Module`` would report as a missing ``trained_network``)."""
        if self.frozen_network is None:
            return None
        try:
            return self.get_submodule(self.frozen_network)
        except AttributeError as exc:
            raise ValueError(f"prior {self.name!r} declares frozen_network = {self.frozen_network!r}, but has no "
                             f"submodule of that name ({exc}); set it to the attribute that holds the trained "
                             "network (e.g. self.net = ... and frozen_network = 'net'), or to None") from None

    def freeze_network(self, device: str | torch.device | None = None) -> None:
        """Freeze :attr:`trained_network`: no gradients on its parameters, the adapter moved to
        ``device`` (when given), the network in eval mode (no dropout, BatchNorm running
        statistics). The protocols optimise latents only."""
        net = self.trained_network
        for p in net.parameters():
            p.requires_grad_(False)
        if device is not None:
            self.to(device)
        net.eval()

    def train(self, mode: bool = True):
        """``nn.Module.train``; a ``frozen_network`` stays in eval mode whatever ``mode`` is."""
        super().train(mode)
        if self.frozen_network is not None:
            self.trained_network.eval()
        return self

    def describe(self) -> str:
        n = sum(p.numel() for p in self.parameters())
        return f"{self.name} ({self.size}): {n:,} parameters\n{self}"

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())


# -- the optional interfaces ----------------------------------------------------------------
class MotionEncoder(abc.ABC):
    """A prior that encodes whole motions into its latents."""

    @abc.abstractmethod
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Latents of whole motions.

        rotations (B, T, 22, 3, 3) local rotations (root = world orientation, y up), trans (B, T, 3)
        metres, timestamps (B, T) seconds from the window start. Returns latents that ``decode``
        accepts for the same window (the reconstruction table decodes them at 30 fps; the denoise and
        in-between tables start their fits from them). Deterministic: the posterior mean.
        """

    def check_motion(self, rotations: torch.Tensor, trans: torch.Tensor | None, timestamps: torch.Tensor) -> None:
        """Raise a ValueError naming the argument unless rotations are (B, T, 22, 3, 3), timestamps
        (B, T) and trans (B, T, 3) or None: the shape check at the top of ``encode_motion``."""
        where = f"{self.name}.encode_motion"
        if rotations.dim() != 5 or rotations.shape[-3:] != (NUM_JOINTS, 3, 3):
            raise ValueError(
                f"{where}: rotations must be (B, T, {NUM_JOINTS}, 3, 3) local rotations, got {tuple(rotations.shape)}"
            )
        B, T = rotations.shape[:2]
        if tuple(timestamps.shape) != (B, T):
            raise ValueError(f"{where}: timestamps must be (B, T) = {(B, T)}, got {tuple(timestamps.shape)}")
        if trans is not None and tuple(trans.shape) != (B, T, 3):
            raise ValueError(f"{where}: trans must be (B, T, 3) = {(B, T, 3)}, got {tuple(trans.shape)}")


class MotionDenoiser(abc.ABC):
    """A prior with its own denoiser (the denoise table calls it instead of fitting)."""

    @abc.abstractmethod
    def denoise_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor,
                       mode: str = "regression", iterations: int = 0) -> Decoded:
        """Denoised motions: rotations (B, T, 22, 3, 3), trans (B, T, 3), timestamps (B, T) -> a
        :class:`Decoded` (or a (rotations, trans) pair) at the same timestamps, in the world frame.
        ``mode`` "regression" (one forward pass) or "optimisation" (``iterations`` steps of the
        prior's own optimisation); see ``benchmark/protocols/denoise.py``."""


class AnchorDecoder(abc.ABC):
    """A prior that decodes anchor frames with their own timestamps (the sls table's time term)."""

    @abc.abstractmethod
    def decode_anchors(self, latents: dict[str, torch.Tensor], shape: torch.Tensor | None = None) -> tuple[Decoded, torch.Tensor]:
        """(Decoded (B, A, ...) at the A anchors, tau_hat (B, A) seconds): see ``benchmark/protocols/sls.py``."""


class Trainable(abc.ABC):
    """A prior whose embedded weights can be (re)trained: ``python -m benchmark train NAME``."""

    @classmethod
    @abc.abstractmethod
    def train_embedded(cls, out_dir=None, steps: int | None = None, seed: int = 0, overwrite: bool = False,
                       dataset=None) -> dict:
        """Train the embedded weights into ``out_dir`` (default: beside ``default_weights``); refuse to
        overwrite an existing checkpoint unless ``overwrite``. Returns the training record.

        ``dataset``: the training data, handed over by the caller (``python -m benchmark train``
        passes :class:`benchmark.synthetic.train_data.SyntheticTrainingData`; the interface is in
        :mod:`priors.training`, :func:`~priors.training.split_motions`): a prior never builds its
        training data itself."""


class ExportableDecoder(abc.ABC):
    """A prior whose deterministic decode path exports to ONNX (``python -m benchmark export-onnx NAME``)."""

    @abc.abstractmethod
    def export_decoder(self) -> ExportSpec:
        """The deterministic decode path (latents -> body parameters) as a plain module for ONNX.

        ``python -m benchmark export-onnx NAME`` traces ``spec.module(*spec.example_inputs)`` with a
        dynamic batch dimension (dim 0 of every input and output).
        """


class PaperNetwork(abc.ABC):
    """A prior that can build its published-size network without weights (``describe NAME --size paper``)."""

    @classmethod
    @abc.abstractmethod
    def paper_network(cls) -> torch.nn.Module:
        """The paper-size network with random weights, for its architecture and parameter counts."""


class InterpolationBaseline(abc.ABC):
    """Not a learned prior: the motion protocols take its latents and the rigid parameters set from
    the observed frames as they are, with no optimisation (``priors/slerp.py``)."""


def has_motion_encoder(adapter) -> bool:
    """True when the tables may use the adapter's encoder: a :class:`MotionEncoder` with ``has_encoder``."""
    return isinstance(adapter, MotionEncoder) and adapter.has_encoder


INTERFACES = (MotionEncoder, MotionDenoiser, AnchorDecoder, Trainable, ExportableDecoder, PaperNetwork, InterpolationBaseline)


def interfaces_of(prior) -> list[str]:
    """The names of the interfaces an adapter (or its class) implements, in :data:`INTERFACES` order."""
    cls = prior if isinstance(prior, type) else type(prior)
    return [i.__name__ for i in INTERFACES if issubclass(cls, i)]
