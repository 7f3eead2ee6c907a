"""The prior adapter of the structured latent space (see the package docstring for the model)."""

from __future__ import annotations

import logging

import torch
from torch import nn

from benchmark.core.interpolate import lerp_frames, slerp_frames
from priors.base import (
    AnchorDecoder, Decoded, ExportableDecoder, ExportSpec, FitBatch, MotionEncoder, PaperNetwork, PriorAdapter, Trainable,
    WindowSpec,
)
from priors.structured_latent import checkpoint
from priors.structured_latent.model import PAPER_CONFIG, StructuredLatentCVAE
from priors.structured_latent.representation import (
    ANCHORS, JOINTS, SIXD_LAYOUT, canonical_frame, canonicalise, motion_to_chi, resample_anchors,
)
from priors.structured_latent.checkpoint import DEFAULT_WEIGHTS
from priors.training import embedded_out_dir

log = logging.getLogger(__name__)


class _AnchorDecoder(nn.Module):
    """(z (B, L), shape (B, S)) -> (anchor rotations (B, 100, 22, 3, 3), anchor trans (B, 100, 3) m,
    tau_hat (B, 100) s): the deterministic decode path, for ONNX."""

    def __init__(self, net: StructuredLatentCVAE):
        super().__init__()
        self.net = net

    def forward(self, z: torch.Tensor, shape: torch.Tensor):
        return self.net.decode_motion(z, shape)


# -- the adapter ------------------------------------------------------------------------------
class StructuredLatentPrior(MotionEncoder, AnchorDecoder, ExportableDecoder, PaperNetwork, Trainable, PriorAdapter):
    """Structured latent space (Marsot et al. 3DV 2022) as a continuous-time prior.

    Latents: ``{"z": (B, L), "window_s": (B, 1)}``; z starts as a sample of N(0, I) (the paper's
    §5 does not say how z is initialised; this is the project's rule for prior samples), window_s
    is the duration the 100 decoded anchors are spread over (``FitBatch.window_s``; read detached,
    never optimised: see :attr:`constant_latents`). decode: the decoder gives 100 anchors with
    predicted timestamps tau_hat; they are mapped affinely onto [0, window_s] (first anchor at 0,
    last at window_s) and SLERP / LERP-ed to the requested timestamps. :meth:`decode_anchors`
    gives the anchors and the raw tau_hat (seconds) for the sls protocol's timestamp term.
    Prior term |z|^2. Output in the canonical frame (initial heading removed, initial ground-plane
    position zero): the protocol's free heading and offset place it.
    """

    name = "structured-latent"
    paper = "Marsot et al., A structured latent space for human body motion generation (3DV 2022)"
    window = WindowSpec(kind="continuous")
    encodes_translation = True
    encodes_root_orientation = True
    heading_normalised = True
    joints = JOINTS
    shape_conditioned = True
    sixd_layout = SIXD_LAYOUT
    frozen_network = "net"
    default_weights = DEFAULT_WEIGHTS
    anchors = ANCHORS
    constant_latents = ("window_s",)  # latents decode reads but never differentiates (zero gradient)
    init = "sample"  # "sample": z ~ N(0, I); "zero": z = 0 (the prior mean)

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "embedded":
            weights = self.embedded_weights(weights)
        self.net, self.checkpoint = checkpoint.load(weights, size)
        self.weights_path = str(self.checkpoint.file)
        self.freeze_network(device)

    @classmethod
    def from_network(cls, net: StructuredLatentCVAE) -> "StructuredLatentPrior":
        """An adapter around an in-memory network (tests, freshly trained models); frozen."""
        self = cls.__new__(cls)
        PriorAdapter.__init__(self, size="embedded", weights=None)
        self.net = net
        self.freeze_network()
        return self

    # -- properties ---------------------------------------------------------------------------
    @property
    def latent_dim(self) -> int:
        return self.net.latent

    @property
    def shape_dim(self) -> int:
        return self.net.shape_dim

    # -- latents ------------------------------------------------------------------------------
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        B = batch.batch_size
        if self.init == "zero":
            z = torch.zeros(B, self.latent_dim)
        else:
            z = torch.randn((B, self.latent_dim), generator=generator, device=generator.device, dtype=torch.float32)
        window = torch.full((B, 1), float(batch.window_s), dtype=torch.float32)
        return {"z": z.to(self.device), "window_s": window.to(self.device)}

    def mean_latents(self, batch: FitBatch) -> dict[str, torch.Tensor]:
        """z = 0 (the mean of the N(0, I) prior) and the window duration, as ``init = "zero"``."""
        B = batch.batch_size
        window = torch.full((B, 1), float(batch.window_s), dtype=torch.float32)
        return {"z": torch.zeros(B, self.latent_dim, device=self.device), "window_s": window.to(self.device)}

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) |z|^2."""
        return latents["z"].square().sum(-1)

    def _shape(self, shape: torch.Tensor | None, B: int, like: torch.Tensor) -> torch.Tensor:
        if shape is None:
            return like.new_full((B, self.shape_dim), self.net.shape_center)
        if shape.dim() != 2 or shape.shape != (B, self.shape_dim):
            raise ValueError(
                f"structured-latent: shape must be (B, {self.shape_dim}) = {(B, self.shape_dim)} (the decoder is conditioned "
                f"on {self.shape_dim} shape numbers: the body's shape vector), got {tuple(shape.shape)}; use a body whose "
                f"shape_dim is {self.shape_dim} (the embedded Anny body has 6) or retrain with config shape_dim"
            )
        return shape.to(like)

    def _z(self, latents: dict) -> torch.Tensor:
        z = latents.get("z")
        if z is None or z.dim() != 2 or z.shape[1] != self.latent_dim:
            raise ValueError(f"structured-latent: latents['z'] must be (B, {self.latent_dim}), got "
                             f"{None if z is None else tuple(z.shape)}")
        return z

    # -- decoding -----------------------------------------------------------------------------
    def decode_anchors(self, latents: dict[str, torch.Tensor], shape: torch.Tensor | None = None) -> tuple[Decoded, torch.Tensor]:
        """The 100 decoded anchors: (Decoded(rotations (B, 100, 22, 3, 3), trans (B, 100, 3) m),
        tau_hat (B, 100) seconds since the first anchor, non-decreasing), canonical frame."""
        z = self._z(latents)
        rot, trans, tau = self.net.decode_motion(z, self._shape(shape, z.shape[0], z))
        tau = torch.cummax(tau, dim=1).values  # a no-op for the monotone time head
        return Decoded(rotations=rot, trans=trans), tau

    def anchor_times(self, latents: dict[str, torch.Tensor], tau: torch.Tensor) -> torch.Tensor:
        """tau_hat (B, 100) -> the anchors' times in the window: affinely onto [0, window_s]
        (``latents["window_s"]``, detached); without "window_s", tau_hat itself."""
        window = latents.get("window_s")
        rel = tau - tau[:, :1]
        if window is None:
            return rel
        window = window.detach().to(tau).reshape(-1, 1)
        return rel / rel[:, -1:].clamp_min(1e-6) * window

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """Body parameters at ``timestamps`` (B, T) s from the window start (class docstring)."""
        anchors, tau = self.decode_anchors(latents, shape)
        B = tau.shape[0]
        if timestamps.dim() != 2 or timestamps.shape[0] != B:
            raise ValueError(f"structured-latent: timestamps must be (B, T) with B = {B}, got {tuple(timestamps.shape)}")
        t_anchor = self.anchor_times(latents, tau)
        ts = timestamps.to(t_anchor.device)
        rot = slerp_frames(anchors.rotations, t_anchor, ts)
        trans = lerp_frames(anchors.trans, t_anchor, ts)
        return Decoded(rotations=rot, trans=trans, extra={"anchor_times": t_anchor, "tau_hat": tau})

    # -- encoding -----------------------------------------------------------------------------
    @torch.no_grad()
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means of whole motions: rotations (B, T, 22, 3, 3), trans (B, T, 3), timestamps
        (B, T) s -> {"z": (B, L), "window_s": (B, 1) = t_last - t_first}. The motion is resampled to
        100 anchors over [t_first, t_last] and aligned; decode reproduces it at ``timestamps -
        timestamps[:, :1]`` in the canonical frame (:meth:`canonical_frame` gives the way back)."""
        dev = self.device
        rot, tr, tau = resample_anchors(rotations.to(dev, torch.float32), trans.to(dev, torch.float32), timestamps.to(dev))
        rot, tr, _, _ = canonicalise(rot, tr)
        chi = motion_to_chi(rot, tr, tau, self.net.trans_min, self.net.trans_max, self.net.tau_max)
        mu, _ = self.net.encode(chi)
        span = (timestamps[:, -1] - timestamps[:, 0]).to(dev, torch.float32)[:, None]
        return {"z": mu, "window_s": span}

    @staticmethod
    def canonical_frame(rotations: torch.Tensor, trans: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(yaw0 (B,), offset (B, 3)) of motions: world = R_y(yaw0) @ canonical + offset."""
        return canonical_frame(rotations, trans)

    # -- export / sizes / training ---------------------------------------------------------------
    def export_decoder(self) -> ExportSpec:
        """(z (B, L), shape (B, S)) -> (anchor_rotations (B, 100, 22, 3, 3), anchor_trans (B, 100, 3),
        tau_hat (B, 100)): the decoder and the de-normalisation of chi, no interpolation."""
        g = torch.Generator().manual_seed(0)
        z = torch.randn(2, self.latent_dim, generator=g)
        shape = torch.full((2, self.shape_dim), self.net.shape_center)
        return ExportSpec(module=_AnchorDecoder(self.net).eval(), example_inputs=(z, shape), input_names=["z", "shape"],
                          output_names=["anchor_rotations", "anchor_trans", "tau_hat"])

    @classmethod
    def paper_network(cls, latent: int = PAPER_CONFIG["latent"]) -> nn.Module:
        """The paper-size network with random weights (latent 64; ``latent=256`` for the CHUM variant,
        :data:`PAPER_CHUM_CONFIG`); layer widths are this project's inference (package docstring)."""
        return StructuredLatentCVAE(**{**PAPER_CONFIG, "latent": int(latent)})

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """``python -m benchmark train structured-latent``: retrain the embedded weights."""
        from priors.structured_latent.train import train_structured_latent

        out = embedded_out_dir(out_dir, DEFAULT_WEIGHTS, overwrite)
        _, record = train_structured_latent(out, steps=steps, seed=seed, dataset=dataset)
        return record


__all__ = ["StructuredLatentPrior"]
