"""VPoser V02_05 (Pavlakos et al. 2019, ``nghorbani/human_body_prior``) and the VPoser+SLERP prior.

Three parts (summary: docs/priors.md):

1. :class:`VPoser`: the V02_05 network, layer for layer (so the official keys map one to one).
   Paper size ``hidden=512, latent=32`` has 936,252 parameters.
2. :func:`priors.vposer.checkpoint.load` (``load(path, size) -> (VPoser, CheckpointReport)``): a
   strict loader for the official Lightning checkpoint (``V02_05/snapshots/*.ckpt``, size "paper")
   and for the project's own ``priors/weights/vposer.pt`` (size "embedded").
3. :class:`VPoserSlerp`: the prior adapter of paper 000 section 5.5 ("VPoser+SLERP"): one latent per
   observed frame, decoded at the observed timestamps; the protocol SLERPs the rotations to the
   output timestamps and owns root orientation and translation.

The embedded weights (``size="embedded"``) are a smaller VPoser (``EMBEDDED_CONFIG``: hidden 256,
latent 32, 271,676 parameters, ~1.1 MB) trained by :func:`train_vposer` on the synthetic training
split. Training loss (the official one needs SMPL-X vertices, which this project does not ship):

    0.005 * KL(q(z|x) || N(0, I))   (sum over latent dims, mean over the batch; official weight)
  + 2     * geodesic angle between decoded and input rotations (rad, mean over joints; official weight)
  + 6     * L1 of joint positions by forward kinematics on a fixed rest skeleton (metres, mean)

The official recipe has 4 * L1(vertices) + 2 * L1(joints); with no mesh, the joint term takes both
weights (6). Joint positions are the cheap stand-in for vertices: they weigh errors by the lever
arm of each joint, which the geodesic term alone does not. Adam, lr 1e-3 with a cosine decay to
1e-4, weight decay 1e-5 (official), batch 256, 15,000 steps on every 2nd frame of the train split
(135k poses), one torch thread: about 3.5 min on one CPU core
(``python -m priors.vposer.train --out priors/weights``; record in ``priors/weights/vposer.json``;
its train losses are measured with dropout on, its validation losses in eval mode).

Beyond the fitting API the adapter implements the interfaces (:mod:`priors.base`)
:class:`~priors.base.MotionEncoder` (``encode_motion``: per-frame posterior means, for the
reconstruction table), :class:`~priors.base.ExportableDecoder` (``export_decoder``, ONNX: ``z`` (B,
32) -> ``rotations`` (B, 22, 3, 3), identity root; ``python -m benchmark export-onnx vposer-slerp``),
:class:`~priors.base.PaperNetwork` (``paper_network``: the paper size with random weights, for
``python -m benchmark describe vposer-slerp --size paper``) and :class:`~priors.base.Trainable`.

VPoser v1.0
-----------
VPoser v1.0 (``nghorbani/human_body_prior``, branch ``cvpr19``), the pose code of Xu et al. 2021.

The frequency-guided motion prior (:mod:`priors.frequency_guided`) decodes a motion into one
32-D VPoser **v1.0** code per frame; the body pose is that code through the VPoser v1.0 decoder.
v1.0 differs from V02_05 (above) in layer names, activations and layout, and the
two checkpoints are not interchangeable (docs/priors.md).

Network (``human_body_prior@cvpr19: human_body_prior/train/vposer_smpl.py``; paper size
``hidden=512, latent=32``, 673,596 parameters), layers directly on the module (so the state-dict
keys are the layer names)::

    encoder  x (N, 63) axis-angle of SMPL joints 1..21
             bodyprior_enc_bn1 BatchNorm1d(63) -> bodyprior_enc_fc1 Linear(63, H) -> leaky_relu(0.2)
             -> bodyprior_enc_bn2 BatchNorm1d(H) -> dropout(0.1) -> bodyprior_enc_fc2 Linear(H, H)
             -> leaky_relu(0.2) -> Normal(bodyprior_enc_mu Linear(H, L), softplus(bodyprior_enc_logvar Linear(H, L)))
    decoder  z (N, L) -> bodyprior_dec_fc1 Linear(L, H) -> leaky_relu(0.2) -> dropout(0.1)
             -> bodyprior_dec_fc2 Linear(H, H) -> leaky_relu(0.2) -> bodyprior_dec_out Linear(H, 21*6)
             -> 6D "interleaved" (each 6 numbers a row-major 3x2 matrix; Gram-Schmidt) -> (N, 21, 3, 3)

The "logvar" head is used as a softplus *scale* (as in the official code). Dropout is inactive in
eval mode (the adapters keep the network in eval mode).

Checkpoint: the official ``vposer_v1_0/snapshots/TR00_E096.pt`` is a plain ``state_dict`` (an
``OrderedDict`` of the 16 parameter tensors above plus the BatchNorms' running statistics and, when
written by torch >= 0.4.1, ``num_batches_tracked``); a ``{"state_dict": ...}`` wrapper is accepted
too. :func:`load_vposer_v1_state` maps it strictly: every key present with its shape, no
leftovers (``num_batches_tracked`` is optional: unused in eval mode).
"""

from priors.vposer.adapter import VPoserSlerp
from priors.vposer.model import EMBEDDED_CONFIG, PAPER_CONFIG, VPoser, VPoserV1

__all__ = ["VPoserSlerp", "VPoser", "VPoserV1", "PAPER_CONFIG", "EMBEDDED_CONFIG"]
