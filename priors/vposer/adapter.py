"""The VPoser+SLERP prior adapter (paper 000 section 5.5) and its ONNX decoder wrapper."""

from __future__ import annotations


import roma
import torch
from torch import nn

from benchmark.core.skeleton import NUM_JOINTS
from priors.base import (
    Decoded, ExportableDecoder, ExportSpec, FitBatch, MotionEncoder, PaperNetwork, PriorAdapter, Trainable, WindowSpec,
)
from priors.vposer import checkpoint
from priors.vposer.model import NUM_BODY_JOINTS, PAPER_CONFIG, VPoser
from priors.vposer.checkpoint import DEFAULT_WEIGHTS, WHERE_TO_GET
from priors.training import embedded_out_dir


# -- the adapter -----------------------------------------------------------------------------
class VPoserSlerp(MotionEncoder, ExportableDecoder, PaperNetwork, Trainable, PriorAdapter):
    """VPoser+SLERP: one VPoser latent per observed frame; the protocol SLERPs between them.

    Latents: ``{"z": (B, n_observed, L)}``, initialised by a random sample of N(0, I) (paper 000
    section 5.5). ``decode`` gives joints 1..21 from the VPoser decoder and an identity root (the
    protocol owns root orientation and translation). Prior term: mean over the sequence's codes of
    ``|z|^2``. The network is frozen and always in eval mode.
    """

    name = "vposer-slerp"
    paper = "Pavlakos et al. 2019 (VPoser V02_05) + SLERP, as in Marsot et al. 2022 §5.5"
    window = WindowSpec(kind="per-frame")
    encodes_translation = False
    encodes_root_orientation = False
    joints = tuple(range(1, NUM_JOINTS))
    sixd_layout = "interleaved"
    frozen_network = "vposer"
    default_weights = DEFAULT_WEIGHTS

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper" and weights is None:
            raise ValueError(f"vposer-slerp size 'paper' needs the official weights. {WHERE_TO_GET}")
        if size == "embedded":
            weights = self.embedded_weights(weights, "or use size='paper' with the official V02_05.")
        self.vposer, self.checkpoint = checkpoint.load(weights, size)
        self.weights_path = str(self.checkpoint.file)
        self.freeze_network(device)

    @property
    def latent_dim(self) -> int:
        return self.vposer.latent

    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"z": (B, n_observed, L)}`` drawn from N(0, I) with ``generator`` (on its device)."""
        shape = (batch.batch_size, batch.num_observed, self.latent_dim)
        z = torch.randn(shape, generator=generator, device=generator.device, dtype=torch.float32)
        return {"z": z.to(self.device)}

    def mean_latents(self, batch: FitBatch) -> dict[str, torch.Tensor]:
        """``{"z": zeros (B, n_observed, L)}``: the mean of the N(0, I) prior (the mean pose)."""
        return {"z": torch.zeros((batch.batch_size, batch.num_observed, self.latent_dim), device=self.device)}

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """z (B, n, L) at their own timestamps (B, n) -> rotations (B, n, 22, 3, 3), root identity."""
        z = latents["z"]
        if z.dim() != 3 or z.shape[-1] != self.latent_dim:
            raise ValueError(f"vposer-slerp: latents['z'] must be (B, n, {self.latent_dim}), got {tuple(z.shape)}")
        if tuple(timestamps.shape) != tuple(z.shape[:2]):
            raise ValueError(
                f"vposer-slerp is a per-frame prior: decode at the latents' own timestamps, shape {tuple(z.shape[:2])}, "
                f"got timestamps {tuple(timestamps.shape)}; the protocol interpolates to other timestamps"
            )
        B, n, L = z.shape
        body = self.vposer.decode(z.reshape(B * n, L)).reshape(B, n, NUM_BODY_JOINTS, 3, 3)
        root = torch.eye(3, dtype=body.dtype, device=body.device).expand(B, n, 1, 3, 3)
        return Decoded(rotations=torch.cat([root, body], dim=2))

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """``python -m benchmark train vposer-slerp``: retrain the embedded weights (see train_vposer)."""
        from priors.vposer.train import train_vposer

        out = embedded_out_dir(out_dir, DEFAULT_WEIGHTS, overwrite)
        _, record = train_vposer(out, seed=seed, dataset=dataset, **({"steps": int(steps)} if steps is not None else {}))
        return record

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) mean over the sequence's latent codes of |z|^2 (sum over the L dims)."""
        return latents["z"].square().sum(-1).mean(-1)

    @classmethod
    def paper_network(cls) -> VPoser:
        """The paper-size VPoser V02_05 (hidden 512, latent 32: 936,252 parameters) with random
        weights, in eval mode: ``python -m benchmark describe vposer-slerp --size paper`` prints its
        architecture and parameter counts without the (gated) official checkpoint."""
        return VPoser(**PAPER_CONFIG).eval()

    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means of every frame: rotations (B, T, 22, 3, 3) -> ``{"z": (B, T, L)}``.

        VPoser encodes one pose at a time, so the latents are per frame and ``decode(latents,
        timestamps)`` at the same timestamps gives the per-frame reconstruction (joints 1..21; the
        root comes back as identity). Only joints 1..21 are encoded: the root orientation (joint
        0) and ``trans`` are not part of this prior (``encodes_root_orientation`` and
        ``encodes_translation`` are False), so the protocol supplies them. ``trans`` and
        ``timestamps`` are only checked for shape. Deterministic (the encoder mean, eval mode), no
        gradient.
        """
        self.check_motion(rotations, trans, timestamps)
        return {"z": self.encode_poses(rotations[:, :, 1:])}

    def export_decoder(self) -> ExportSpec:
        """ONNX export of the decoder: input ``z`` (B, L) -> output ``rotations`` (B, 22, 3, 3).

        One latent per pose (the prior is per-frame; a (B, T, L) sequence is flattened to B*T
        poses). The output has all 22 SMPL joints, in the same convention as ``decode``: joint 0 is
        the identity (the protocol owns the root orientation), joints 1..21 are the VPoser decoder's
        local rotations. Example batch: 2 latents drawn from N(0, I) with seed 0.
        """
        module = _VPoserDecoderExport(self.vposer).eval()
        g = torch.Generator().manual_seed(0)
        z = torch.randn(2, self.latent_dim, generator=g).to(self.device)
        return ExportSpec(module=module, example_inputs=(z,), input_names=["z"], output_names=["rotations"])

    @torch.no_grad()
    def encode_poses(self, rotmats: torch.Tensor) -> torch.Tensor:
        """(..., 21, 3, 3) local rotations of joints 1..21 -> (..., L) the encoder's mean."""
        if rotmats.shape[-3:] != (NUM_BODY_JOINTS, 3, 3):
            raise ValueError(f"encode_poses expects (..., 21, 3, 3) rotations of joints 1..21, got {tuple(rotmats.shape)}")
        lead = rotmats.shape[:-3]
        aa = roma.rotmat_to_rotvec(rotmats.reshape(-1, NUM_BODY_JOINTS, 3, 3).to(self.device, torch.float32))
        return self.vposer.encode(aa).mean.reshape(*lead, self.latent_dim)


class _VPoserDecoderExport(nn.Module):
    """The traceable decode path of :meth:`VPoserSlerp.export_decoder`: z (B, L) -> (B, 22, 3, 3)
    with an identity root.

    Same numbers as ``VPoserSlerp.decode``, written so that the batch dimension stays symbolic in a
    trace: the 6D -> matrix step is the Gram-Schmidt of ``roma.special_gramschmidt`` (interleaved
    layout, epsilon 0) restated with ``reshape(-1, ...)``, because roma's own batch flattening
    records the example's batch size as a constant (an export at batch 2 then fails at batch 5).
    """

    def __init__(self, vposer: VPoser):
        super().__init__()
        self.mlp = vposer.decoder_net[:-1]  # every layer but ContinousRotReprDecoder (shared weights)
        self.register_buffer("eye", torch.eye(3), persistent=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        m = self.mlp(z).reshape(-1, NUM_BODY_JOINTS, 3, 2)  # interleaved: row-major 3x2, columns a1, a2
        a1, a2 = m[..., 0], m[..., 1]
        b1 = a1 / torch.linalg.vector_norm(a1, dim=-1, keepdim=True)
        a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
        b2 = a2 / torch.linalg.vector_norm(a2, dim=-1, keepdim=True)
        b3 = torch.cross(b1, b2, dim=-1)
        body = torch.stack((b1, b2, b3), dim=-1)  # (B, 21, 3, 3), columns b1 b2 b3
        root = torch.zeros_like(body[:, :1]) + self.eye.to(body.dtype)
        return torch.cat([root, body], dim=1)
