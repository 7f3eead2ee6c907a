"""Marsot, Wuhrer, Franco, Durocher: "A structured latent space for human body motion generation"
(3DV 2022; paper 001 of docs/protocol.md), as the registered prior ``structured-latent``.

The official code (gitlab.inria.fr/mmarsot/a-structured-latent-space) is not reachable: the paper is
the specification; everything it leaves open is chosen here, stated below and configurable.

Representation (representation.py; paper §3.1, Supp. §1-2): one motion = 100 anchor frames
uniformly spaced in time, chi in R^{100 x 124}: 20 joints (SMPL-22 minus the feet 10, 11; root
included) as 6D in the "columns" layout minus the identity [1,0,0,0,1,0] (120), root translation
min-max normalised to [-1, 1]^3 (3), timestamp min-max normalised to [0, 1] (1); normalisation
statistics are those of the training windows and travel with the weights. Motions are aligned:
initial heading (about +y) removed, initial ground-plane translation zeroed [paper: "identity
initial root rotation", read as heading only; height, pitch and roll kept].

Network (model.py; §3.2): a CVAE, encoder E(chi) -> (mu, sigma) not conditioned on shape,
decoder D(z, beta) -> chi_hat conditioned on the body's shape vector. Paper: dim(z) = 64 (256 for
the CHUM comparison), beta = 8 SMPL betas, no layer types or widths [inferred: a temporal
convolutional encoder / decoder over the 100 anchors, widths C (channels) and H (hidden); a
monotone timestamp head]. Sizes:

    paper size    latent 64, shape 8, C 128, H 1024: 7,845,628 parameters (PAPER_CONFIG);
                  latent 256 (CHUM comparison): 8,435,836 (PAPER_CHUM_CONFIG)
    embedded      latent 64, shape 6 (Anny phenotypes in [0, 1], fed as 2 beta - 1), C 64, H 256:
                  1,118,204 parameters, ~4.5 MB (EMBEDDED_CONFIG)

Training (train.py; §3.3, Supp. §2): phase 1 on chi with GradNorm weights over (pose, trans, time)
(gradnorm.py, Chen et al. 2018, implemented here; alpha 1.5, weight lr 0.025, gradients taken at
the decoder's last shared activation [inferred]) + 0.01 KL, lr 1e-3, batch 128 [paper 256];
phase 2 on "meshes" with GradNorm over (spatial, time) + 0.01 KL, lr 1e-4, batch 16 [no SMPL mesh
is shipped: the mesh is stood in for by FK joints + 2 markers per joint on the subject's own rest
skeleton]. Adam [inferred]. Data: one-cycle windows (0.3-3 s) of the synthetic train split cut
with the generator's own phases (benchmark/synthetic/cycles.py), plus 2 s and 4 s windows of
arbitrary motion every 2 s [project extension, so that the reconstruction table's 2 s and table1's
4 s windows are in distribution; so the timestamp scale tau_max is 4 s]. The translation's
normalisation range is its mean +- 2 standard deviations (``trans_range_std``; None: the paper's
min-max, 17-19 m wide on the synthetic split, which left the root 0.4-0.7 m off); KL weight 1e-3
in phase 1 and 1e-4 in phase 2 (GradNorm drives the spatial weight to its 1e-3 floor, against
which the paper's 0.01 made the KL dominate). Default 15,000 steps (13,500 + 1,500; train.py's
DEFAULT_STEPS), about 41 min on one shared core (``train_embedded``).

Adapter (adapter.py): window kind "continuous": the decoder's 100 anchors (predicted timestamps
tau_hat) are spread affinely over the window [0, window_s] and SLERP / LERP-ed to any timestamps
(the paper assumes "constant motion between anchor meshes"). Latents {"z": (B, L), "window_s":
(B, 1)}; z ~ N(0, I) at the start [§5 does not say; the project's rule for prior samples];
window_s is read detached (``constant_latents``). Prior term |z|^2. ``decode_anchors`` gives the
anchors and tau_hat (s) for the sls protocol's timestamp term; ``encode_motion`` the posterior
means; ``export_decoder`` (z, shape) -> (anchor rotations, anchor trans, tau_hat).

Checkpoint format (checkpoint.py; project): ``priors/weights/structured_latent.pt`` = torch.save of
{"state_dict": StructuredLatentCVAE state (including the buffers trans_min, trans_max, tau_max),
"config": {"network": {...}, "normalisation": {...}, "format": "structured-latent/1"}}, loaded
strictly; training record ``structured_latent.json`` beside it. Official weights: format unknown;
``size="paper"`` raises and says what is unknown.
"""

from priors.structured_latent.adapter import StructuredLatentPrior
from priors.structured_latent.checkpoint import DEFAULT_WEIGHTS, OFFICIAL_UNKNOWN
from priors.structured_latent.gradnorm import GradNorm
from priors.structured_latent.model import (
    EMBEDDED_CONFIG, PAPER_CHUM_CONFIG, PAPER_CONFIG, StructuredLatentCVAE, kl_divergence,
)
from priors.structured_latent.train import build_anchor_data, train_structured_latent

__all__ = [
    "StructuredLatentPrior", "StructuredLatentCVAE", "GradNorm", "train_structured_latent",
    "build_anchor_data", "kl_divergence", "EMBEDDED_CONFIG", "PAPER_CONFIG", "PAPER_CHUM_CONFIG", "DEFAULT_WEIGHTS",
    "OFFICIAL_UNKNOWN",
]
