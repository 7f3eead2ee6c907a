"""HM-VAE (Li et al., "Task-generic hierarchical human motion prior using VAEs", 3DV 2021) as benchmark priors.

- ``hmvae`` = :class:`HMVAEPrior`: the len-64 window VAE, free per-frame translation;
- ``hmvae-trajectory`` = :class:`HMVAETrajectoryPrior`: plus the authors' trajectory model.

Modules: :mod:`.skeleton` (edge topology, masks, skeleton conv / pool / unpool), :mod:`.model`
(the VAE, paper len-64 and len-8 configs), :mod:`.trajectory` (trajectory CNN),
:mod:`.checkpoint` (official-format and project loaders), :mod:`.adapter` (the priors),
:mod:`.train` (embedded training). No official weights were published (see :mod:`.checkpoint`).
"""

from priors.hmvae.adapter import HMVAEPrior, HMVAETrajectoryPrior
from priors.hmvae.model import LEN8_CONFIG, PAPER_CONFIG, HMVAE, HMVAEConfig
from priors.hmvae.trajectory import PAPER_TRAJECTORY_CONFIG, TrajectoryConfig, TrajectoryModel

__all__ = [
    "HMVAEPrior",
    "HMVAETrajectoryPrior",
    "HMVAE",
    "HMVAEConfig",
    "PAPER_CONFIG",
    "LEN8_CONFIG",
    "TrajectoryModel",
    "TrajectoryConfig",
    "PAPER_TRAJECTORY_CONFIG",
]
