"""Sequential latent primitives as a :class:`~priors.base.PriorAdapter` (and its ONNX decoder wrapper)."""

from __future__ import annotations

import contextlib
import logging

import torch
from torch import nn

from benchmark.core.frames import yaw_matrix
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import (
    Decoded, ExportableDecoder, ExportSpec, FitBatch, MotionEncoder, PaperNetwork, PriorAdapter, Trainable, WindowSpec,
)
from priors.sequential_primitives import checkpoint
from priors.sequential_primitives.model import (
    MODEL_JOINTS,
    PAPER_CONFIG,
    PrimitiveDecoder,
    SequentialPrimitives,
    TRAIN_FPS,
    canonicalise,
    insert_feet,
)
from priors.sequential_primitives.checkpoint import DEFAULT_WEIGHTS, NOT_PUBLIC, OFFICIAL_MAPPING_NEEDS
from priors.training import embedded_out_dir

log = logging.getLogger(__name__)


DEFAULT_WINDOW_S = 4.0  # decode's time scale when no batch set one (table1's window)


# -- export ------------------------------------------------------------------------------------
class DecoderExport(nn.Module):
    """(z (B, m, D), shape (B, S), tau (B, T) normalised time) -> (rotations (B, T, 22, 3, 3), trans (B, T, 3))."""

    def __init__(self, decoder: PrimitiveDecoder):
        super().__init__()
        self.decoder = decoder

    def forward(self, z: torch.Tensor, shape: torch.Tensor, tau: torch.Tensor):
        out = self.decoder(z, shape, tau)
        return out["rotations"], out["trans"]


# -- the adapter --------------------------------------------------------------------------------
class SequentialPrimitivesPrior(MotionEncoder, ExportableDecoder, PaperNetwork, Trainable, PriorAdapter):
    """Sequential latent primitives (Marsot et al. 2022) as a continuous-time prior (module docstring).

    Latents ``{"z": (B, 8, D)}`` from the PointNet initialisation encoder; decode at any timestamps;
    prior term ``sum |z - z_init|^2``. The decoder outputs a canonical heading and zero-mean
    translation: the protocol frees a heading and an offset.
    """

    name = "sequential-primitives"
    paper = "Marsot, Wuhrer, Franco, Olivier 2022, Representing motion as a sequence of latent primitives (hal-03715820)"
    window = WindowSpec(kind="continuous")
    encodes_translation = True
    encodes_root_orientation = True
    heading_normalised = True
    joints = MODEL_JOINTS
    shape_conditioned = True
    sixd_layout = "columns"
    frozen_network = "net"
    default_weights = DEFAULT_WEIGHTS

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper":
            if weights is None:
                raise ValueError(
                    f"sequential-primitives size 'paper' needs weights, but {NOT_PUBLIC}. Use size='embedded' "
                    "(python -m benchmark train sequential-primitives), or pass a paper-size checkpoint in this "
                    f"project's format; an official-weights loader would have to map onto: {OFFICIAL_MAPPING_NEEDS}"
                )
        elif size == "embedded":
            weights = self.embedded_weights(weights, "or `python -m priors.sequential_primitives.train --out priors/weights`")
        self.net, self.checkpoint = checkpoint.load(weights, size)
        self.weights_path = str(self.checkpoint.file)
        self.freeze_network(device)
        self._z_init: torch.Tensor | None = None
        self._window_s: float = DEFAULT_WINDOW_S
        self._warned_shape = False

    # -- plumbing
    @classmethod
    def paper_network(cls) -> nn.Module:
        """The paper-size network (D = 256, m = 8, 8 betas) with random weights."""
        return SequentialPrimitives(**PAPER_CONFIG)

    def _shape(self, shape: torch.Tensor | None, B: int) -> torch.Tensor:
        S = self.net.shape_dim
        mean = self.net.decoder.shape_mean
        if shape is None:
            return mean.expand(B, S)
        shape = shape.to(self.device, mean.dtype)
        if shape.dim() != 2 or shape.shape[0] != B:
            raise ValueError(f"sequential-primitives: shape must be (B, {S}) = ({B}, {S}), got {tuple(shape.shape)}")
        if shape.shape[1] != S:
            if not self._warned_shape:
                log.warning("sequential-primitives: the body's shape vector has %d entries but the prior was trained "
                            "on %d-entry shapes; its decoder is conditioned on the training-mean shape instead "
                            "(the body's own shape still shapes the mesh)", shape.shape[1], S)
                self._warned_shape = True
            return mean.expand(B, S)
        return shape

    # -- the three adapter functions
    @torch.no_grad()
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"z": (B, 8, D)}``: the initialisation encoder on the observed point clouds (deterministic;
        ``generator`` is unused). Stores z_init and the window duration for prior_term / decode."""
        window_s = float(batch.window_s)
        if not window_s > 0:
            raise ValueError(f"sequential-primitives: FitBatch.window_s must be > 0 seconds, got {batch.window_s}")
        dev = self.device
        pts = batch.points.to(dev, torch.float32)
        tau = batch.timestamps.to(dev, torch.float64).div(window_s).to(torch.float32)
        z = self.net.point_encoder(pts, batch.lengths.to(dev), tau)
        self._z_init = z.detach().clone()
        self._window_s = window_s
        return {"z": z}

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """z (B, 8, D) at timestamps (B, T) seconds from the window start -> rotations (B, T, 22, 3, 3)
        (feet identity) and trans (B, T, 3) in the canonical frame; latents "heading" (B, 1) /
        "offset" (B, 3), when present (from encode_motion), are applied on top."""
        z = latents["z"]
        m, D = self.net.primitives, self.net.latent
        if z.dim() != 3 or z.shape[1:] != (m, D):
            raise ValueError(f"sequential-primitives: latents['z'] must be (B, {m}, {D}), got {tuple(z.shape)}")
        if timestamps.dim() != 2 or timestamps.shape[0] != z.shape[0]:
            raise ValueError(f"sequential-primitives: timestamps must be (B, T) with B = {z.shape[0]}, got {tuple(timestamps.shape)}")
        tau = (timestamps.to(z.device, torch.float64) / self._window_s).to(z.dtype)
        out = self.net.decoder(z, self._shape(shape, z.shape[0]), tau)
        rot, trans = out["rotations"], out["trans"]
        if "heading" in latents:
            H = yaw_matrix(latents["heading"][:, 0])[:, None]  # (B, 1, 3, 3)
            rot = torch.cat([(H[:, :, None] @ rot[:, :, :1]), rot[:, :, 1:]], dim=2)
            trans = (H @ trans[..., None])[..., 0]
        if "offset" in latents:
            trans = trans + latents["offset"][:, None]
        return Decoded(rotations=rot, trans=trans)

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) sum over primitives and dims of |z - z_init|^2 (paper Eq. 9's L_prior)."""
        z = latents["z"]
        if self._z_init is None or self._z_init.shape != z.shape:
            have = None if self._z_init is None else tuple(self._z_init.shape)
            raise ValueError(
                f"sequential-primitives: prior_term needs the initial latents of this batch (have {have}, latents "
                f"{tuple(z.shape)}): call init_latents (or encode_motion) for the batch first; one adapter serves "
                "one batch at a time"
            )
        return (z - self._z_init.to(z)).square().sum((1, 2))

    @contextlib.contextmanager
    def batch_rows(self, rows: torch.Tensor):
        """The prior term of the sequences ``rows`` pulls towards their own initial latents."""
        z_init = self._z_init
        if z_init is not None:
            self._z_init = z_init.index_select(0, rows.to(z_init.device))
        try:
            yield
        finally:
            self._z_init = z_init

    @torch.no_grad()
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means of whole motions: ``{"z": (B, 8, D), "heading": (B, 1), "offset": (B, 3)}``.

        rotations (B, T, 22, 3, 3), trans (B, T, 3), timestamps (B, T) s. The window duration is
        t_last + the median frame interval (120 frames at 30 fps -> 4 s) and is stored, with z as
        z_init. heading/offset map the canonical frame back to the input's, so decode reproduces
        the input's world placement.
        """
        if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"encode_motion: rotations must be (B, T, 22, 3, 3), got {tuple(rotations.shape)}")
        B, T = rotations.shape[:2]
        if trans.shape != (B, T, 3) or timestamps.shape != (B, T):
            raise ValueError(f"encode_motion: trans must be {(B, T, 3)} and timestamps {(B, T)}, got "
                             f"{tuple(trans.shape)}, {tuple(timestamps.shape)}")
        dev = self.device
        ts = timestamps.to(dev, torch.float64)
        dt = (ts[:, 1:] - ts[:, :-1]).median() if T > 1 else torch.tensor(1.0 / TRAIN_FPS, dtype=torch.float64)
        window_s = float(ts[:, -1].max() + dt)
        R = insert_feet(rotations.to(dev, torch.float32)[:, :, list(MODEL_JOINTS)])
        Rc, tc, yaw, mean = canonicalise(R, trans.to(dev, torch.float32))
        tau = (ts / window_s).to(torch.float32)
        mu, _ = self.net.encode(Rc, tc, tau)
        self._z_init = mu.clone()
        self._window_s = window_s
        return {"z": mu, "heading": yaw[:, None], "offset": mean}

    def export_decoder(self) -> ExportSpec:
        """(z (B, 8, D), shape (B, S), tau (B, T) = seconds / window_s) -> (rotations, trans) canonical frame."""
        module = DecoderExport(self.net.decoder).eval()
        g = torch.Generator().manual_seed(0)
        B, T = 2, 16
        z = torch.randn(B, self.net.primitives, self.net.latent, generator=g)
        shape = torch.rand(B, self.net.shape_dim, generator=g)
        tau = torch.linspace(0.0, 1.0, T).expand(B, T).contiguous()
        dev = self.device
        return ExportSpec(module=module, example_inputs=(z.to(dev), shape.to(dev), tau.to(dev)),
                          input_names=["z", "shape", "tau"], output_names=["rotations", "trans"])

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """``python -m benchmark train sequential-primitives``: the embedded weights (see
        :func:`train_sequential_primitives`). ``steps`` sets the motion-VAE steps; the initialisation
        encoder gets steps * DEFAULT_POINT_STEPS / DEFAULT_STEPS."""
        from priors.sequential_primitives.train import DEFAULT_POINT_STEPS, DEFAULT_STEPS, train_sequential_primitives

        out = embedded_out_dir(out_dir, DEFAULT_WEIGHTS, overwrite)
        kw = {}
        if steps is not None:
            kw = {"steps": int(steps), "point_steps": max(1, round(int(steps) * DEFAULT_POINT_STEPS / DEFAULT_STEPS))}
        _, record = train_sequential_primitives(out, seed=seed, dataset=dataset, **kw)
        return record
