"""The no-prior baseline: free per-observed-frame body rotations, interpolated by the protocol.

Latents: ``{"pose": (B, n_observed, 21, 6)}``, the local rotations of SMPL joints 1..21 in the
"interleaved" 6D layout (row-major 3x2, the first two columns of R), initialised at the identity
(the T-pose). Decoding is Gram-Schmidt (``benchmark.core.rotations.sixd_to_matrix``); the root is
identity (the protocol owns root orientation and translation) and the prior term is zero. It is
what VPoser+SLERP would be without VPoser: the protocol's SLERP/LERP fills the other frames.

No network: it is not an :class:`~priors.base.ExportableDecoder` (``export_decoder`` raises:
nothing learned to export; ``export-onnx no-prior`` is a clear error) nor a
:class:`~priors.base.PaperNetwork`. It is a :class:`~priors.base.MotionEncoder`: ``encode_motion``
is the exact, lossless change of representation (6D of joints 1..21), which table1's per-frame
start search uses to set a pose in the latents; ``has_encoder`` is False because it is not a learned
encoder, so the tables that measure or start from an encoder leave it out (the reconstruction
table, encode then decode, would only measure float round-off for this row).
"""

from __future__ import annotations

import torch

from benchmark.core.rotations import matrix_to_sixd, sixd_to_matrix
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import Decoded, FitBatch, MotionEncoder, PriorAdapter, WindowSpec

NUM_BODY_JOINTS = NUM_JOINTS - 1


class NoPrior(MotionEncoder, PriorAdapter):
    """Per-observed-frame poses fitted directly; no learned model, no weights, zero prior term."""

    name = "no-prior"
    paper = "baseline: per-observed-frame pose fitted directly, SLERP/LERP"
    window = WindowSpec(kind="per-frame")
    encodes_translation = False
    encodes_root_orientation = False
    joints = tuple(range(1, NUM_JOINTS))
    sixd_layout = "interleaved"
    has_encoder = False  # a MotionEncoder, but an exact change of representation: the tables leave it out

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if weights is not None:
            raise ValueError(f"no-prior has no weights; got weights={weights!r} (drop its --weights option)")
        if size not in ("embedded", "paper"):
            raise ValueError(f"no-prior: unknown size {size!r}; expected 'embedded' or 'paper' (both are the same)")

    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"pose": (B, n_observed, 21, 6)}`` at the identity (deterministic; ``generator`` unused)."""
        eye6 = matrix_to_sixd(torch.eye(3, device=self._device), layout="interleaved")
        pose = eye6.expand(batch.batch_size, batch.num_observed, NUM_BODY_JOINTS, 6).clone()
        return {"pose": pose}

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """pose (B, n, 21, 6) at its own timestamps (B, n) -> rotations (B, n, 22, 3, 3), root identity."""
        pose = latents["pose"]
        if pose.dim() != 4 or pose.shape[-2:] != (NUM_BODY_JOINTS, 6):
            raise ValueError(f"no-prior: latents['pose'] must be (B, n, {NUM_BODY_JOINTS}, 6), got {tuple(pose.shape)}")
        if tuple(timestamps.shape) != tuple(pose.shape[:2]):
            raise ValueError(
                f"no-prior is a per-frame prior: decode at the latents' own timestamps, shape {tuple(pose.shape[:2])}, "
                f"got timestamps {tuple(timestamps.shape)}; the protocol interpolates to other timestamps"
            )
        body = sixd_to_matrix(pose, layout="interleaved")
        B, n = pose.shape[:2]
        root = torch.eye(3, dtype=body.dtype, device=body.device).expand(B, n, 1, 3, 3)
        return Decoded(rotations=torch.cat([root, body], dim=2))

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) zeros."""
        pose = latents["pose"]
        return pose.new_zeros(pose.shape[0])

    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """rotations (B, T, 22, 3, 3) -> ``{"pose": (B, T, 21, 6)}``: the latents are the rotations.

        The interleaved 6D of joints 1..21 (what ``decode`` expects); decoding them at the same
        timestamps gives back joints 1..21 exactly (to float round-off) and an identity root. The
        root orientation and ``trans`` are not latents of this prior (the protocol owns them);
        ``trans`` and ``timestamps`` are only checked for shape. Not a learned encoder, hence
        ``has_encoder = False`` (see the module docstring).
        """
        self.check_motion(rotations, trans, timestamps)
        pose = matrix_to_sixd(rotations[:, :, 1:].to(self._device), layout="interleaved")
        return {"pose": pose.detach().clone()}

    def export_decoder(self):
        """Always raises: no-prior has no decoder network (its latents are the 6D rotations and
        ``decode`` is a Gram-Schmidt), so there is nothing learned to export to ONNX."""
        raise NotImplementedError(
            "prior 'no-prior' has no decoder network to export: its latents are the body rotations themselves "
            "(6D, decoded by Gram-Schmidt); export a prior with a learned decoder, e.g. vposer-slerp"
        )
