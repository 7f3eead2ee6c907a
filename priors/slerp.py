"""The SLERP baseline of the in-betweening table (HM-VAE, Li et al. 2021, Table 2; Harvey et al. 2020).

Not a learned prior: the observed frames' local joint rotations are SLERP-interpolated and the root
translation linearly interpolated to the missing frames. It is expressed as an adapter so that it
runs as an ordinary row of ``python -m benchmark run inbetween --prior slerp``:

- latents ``{"pose": (B, n_observed, 21, 6)}``: the local rotations of SMPL joints 1..21 at the
  observed frames, "interleaved" 6D (row-major 3x2), exactly as :class:`priors.no_prior.NoPrior`;
- ``encode_motion`` returns the observed rotations themselves (exact: Gram-Schmidt of the first two
  columns of a rotation matrix gives it back), root orientation and translation are the protocol's
  per-observed-frame variables, set from the observed frames;
- the :class:`~priors.base.InterpolationBaseline` interface tells the motion protocols (benchmark/protocols/inbetween.py)
  to take these latents and rigid parameters as they are, with no optimisation: the per-frame
  machinery of the protocol (``benchmark.protocols.fit_state.body_parameters``) then SLERPs the
  rotations and LERPs the translation between the last context frame and the key frame.

No weights, no network, no training (``train_embedded`` returns a record saying so); sizes
"embedded" and "paper" are the same. The denoise and reconstruction tables mark it n/a (their
``na_reason``): encoding and decoding the observation is the identity there.
"""

from __future__ import annotations

import torch

from benchmark.core.rotations import matrix_to_sixd
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import InterpolationBaseline, Trainable
from priors.no_prior import NoPrior


class SlerpBaseline(InterpolationBaseline, Trainable, NoPrior):
    """SLERP of local rotations, LERP of translation, between observed frames (no optimisation)."""

    name = "slerp"
    paper = "baseline: SLERP of local joint rotations + LERP of translation between observed frames (HM-VAE Table 2)"
    has_encoder = True  # its encode_motion (the observed rotations) is what the in-betweening table starts from

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        if weights is not None:
            raise ValueError(f"slerp has no weights; got weights={weights!r} (drop its --weights option)")
        super().__init__(size=size, weights=None, device=device)

    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """rotations (B, T, 22, 3, 3) -> ``{"pose": (B, T, 21, 6)}`` the rotations of joints 1..21 as they are."""
        if rotations.dim() != 5 or rotations.shape[-3:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"slerp.encode_motion: rotations must be (B, T, {NUM_JOINTS}, 3, 3), got {tuple(rotations.shape)}")
        if tuple(timestamps.shape) != tuple(rotations.shape[:2]):
            raise ValueError(f"slerp.encode_motion: timestamps must be (B, T) = {tuple(rotations.shape[:2])}, "
                             f"got {tuple(timestamps.shape)}")
        return {"pose": matrix_to_sixd(rotations[:, :, 1:].detach().float(), layout="interleaved").to(self._device)}

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """Nothing to train: returns a record that says so and writes nothing."""
        return {"prior": cls.name, "trained": False, "note": "the SLERP baseline has no parameters"}
