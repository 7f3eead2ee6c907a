"""The frequency-guided motion prior of Xu et al., "Exploring versatile prior for human motion via
motion frequency guidance" (3DV 2021; code ``JchenXu/human-motion-prior``, MIT), as the prior
``frequency-guided`` (summary: docs/priors.md).

What it models: one 128-frame window at 30 fps (4.27 s) as one latent z. The decoder turns z into
one VPoser **v1.0** code (32-D) per frame plus a root orientation per frame in 6D; the body pose of
a frame is its code through the VPoser v1.0 decoder (:mod:`priors.vposer`). No translation.

Network (``human_motion_prior/train/motion_prior.py``, class ``MotionPrior``; keys = attribute names)
-----------------------------------------------------------------------------------------------------
Paper size (``PAPER_CONFIG``: num_neurons 512, latent 256, latent_t 8, 128 frames, dense frequency
guidance with 5-frame blocks, 20 DCT coefficients, conv channels 64/64/128, DCT branch 512):

- input per frame, 158 channels: body pose axis-angle of SMPL joints 1..21 (63) + VPoser v1 encoder
  mean of that pose (32) + root orientation axis-angle (3) + root translation relative to frame 0 (3)
  + translation velocity (3; frame 0 = 0) + root angular velocity R_t R_{t-1}^T as axis-angle (3;
  frame 0 = R_0) + 17 root-relative joint positions (51).
- ``dct_att`` Linear(128*5*51 = 32640 -> 128): an attention gate from the dense block DCT (for every
  frame, the orthonormal 5-point DCT of the 5-frame neighbourhood of the 17 joints, edges padded by
  repetition); its output multiplies each frame's 158 channels (no squashing).
- stage 0: ``bodyprior_enc_fc0_1`` Conv1d(158->64, k3 s2 p1), swish; residual pair ``fc0_2``, ``fc0_3``
  Conv1d(64->64, k3 s1 p1): x + swish(fc0_3(swish(fc0_2(x)))) -> 64x64 ("local").
  stage 1: ``pool1_1`` Conv1d(64->64, k3 s2 p1), swish; residual ``fc1_1``/``fc1_2`` -> 64x32.
  stage 2: ``pool2_1`` Conv1d(64->128, k3 s2 p1), swish; residual ``fc2_1``/``fc2_2`` -> 128x16.
  Every encoder conv and ``bodyprior_enc_dct`` carries ``torch.nn.utils.weight_norm`` (keys
  ``weight_g``, ``weight_v``, ``bias``); swish(x) = x * sigmoid(x).
- [stage 2, stage 0, stage 1] flattened (8192) + swish(``bodyprior_enc_dct`` Linear(20*51 = 1020 -> 512))
  of the first 20 orthonormal DCT-II coefficients of the 128x51 joint trajectories -> 8704, dropout
  0.1, ``bodyprior_enc_mu_local`` / ``bodyprior_enc_logvar_local`` Linear(8704 -> 256);
  q(z) = Normal(mu, softplus(logvar)).
- decoder: X = swish(``bodyprior_dec_fc0`` Linear(256->512)); X += swish(``dec_fc1``(X)); X += swish(``dec_fc2``(X));
  dropout; ``bodyprior_dec_pose`` Linear(768 -> 128*32) = per-frame VPoser v1 codes;
  ``bodyprior_dec_orient`` Linear(768 -> 128*6) = per-frame root in the interleaved 6D layout.
- defined but unused by the official forward pass, kept so the official file loads strictly:
  ``bodyprior_enc_bn{0_1,0_2,0_3,1_1,1_2,2_1,2_2}`` BatchNorm1d, ``bodyprior_enc_{mu,logvar}_global``
  Linear(8192 -> 8), ``bodyprior_dec_trans`` Linear(520 -> 384).
- parameters: 14,104,080 for the motion prior (its decoder, ``bodyprior_dec_*`` without the unused
  dec_trans: 4,397,312) + 673,596 for VPoser v1.0 = 14,777,676; the decode path z -> rotations
  (motion-prior decoder + VPoser v1 decoder) has 4,741,502 (:meth:`FrequencyGuidedPrior.paper_network`).

Embedded size (``EMBEDDED_CONFIG``, trained by this project): the same structure with num_neurons
256, latent 128, conv channels 32/32/64, DCT branch 256 and no unused layers; 128 frames, 158
channels, dense 5-frame block DCT and the 20-coefficient DCT kept, so ``dct_att`` is still
Linear(32640 -> 128) (4.18 M of the motion prior's 7,653,312 parameters). Embedded VPoser v1: hidden
256, latent 32 (205,884). Total 7,859,196 (decode path 2,143,870); the checkpoint is about 31 MB.
(``dense_freq=False`` selects Xu's non-dense variant, 8-frame non-overlapping blocks and
``dct_att`` Linear(128*51 -> 16); supported, not used by either shipped size.)

Inputs built by this module (where the paper's data are not available)
-----------------------------------------------------------------------
- Joint positions: the official 17 joints come from SMPL vertices through the Human3.6M regressor
  (``J_regressor_h36m.npy``), which this project does not have. They are derived here from our 22
  SMPL joints by forward kinematics on a fixed rest skeleton (:data:`XU17_FROM_SMPL22`):
  hip = pelvis (0); right hip/knee/ankle = 2/5/8; left hip/knee/ankle = 1/4/7; chest = spine3 (9)
  (the H36M "spine" lies between SMPL spine2 and spine3); neck = neck (12); nose = head (15);
  head (top) = an end site 0.116 m (Xu's nose-head bone length) along the head joint's local +y;
  left shoulder/elbow/wrist = 16/18/20; right = 17/19/21 (official order: hip, RHip, RKnee,
  RAnkle, LHip, LKnee, LAnkle, chest, neck, nose, head, LShoulder, LElbow, LWrist, RShoulder,
  RElbow, RWrist). The rest skeleton is stored with the weights: the embedded checkpoint holds the
  one it was trained with (``priors.training.fixed_rest_skeleton``); the paper size uses the
  SMPL-like skeleton ``benchmark.core.skeleton.SMPL_LIKE_REST_JOINTS``.
- Heading normalisation (as Xu): the window's first root rotation is written R_0 = Ry(c) Rx(b) Rz(a)
  (scipy ``'zxy'`` extrinsic Euler), c = atan2(R_0[0, 2], R_0[2, 2]) is the heading of the body's
  +z axis; every frame's root and the translation (relative to frame 0) are pre-multiplied by
  Ry(-c). The decoder's target is this heading-normalised root. Training augments the encoder input
  by a random yaw in [-pi, pi) applied to root, translation and joints (as Xu); :meth:`encode_motion`
  uses yaw 0 (the canonical heading).
- Coordinate frame: Xu rotates AMASS (z up) into SMPL's own frame (y up, body facing +z at identity
  root). This project's world is also y up with the body facing +z, so the mapping is the identity:
  the decoded root of frame 0 faces +z (heading 0; the decoder is trained towards it), and the protocol's free heading about y (plus its
  offset) places the window in the world; that heading absorbs the constant yaw of the observed
  motion. With several 128-frame windows every window restarts at heading 0 while the protocol
  frees one heading per sequence: windows after the first cannot represent a turn of the whole
  body relative to the first (the 4 s completion window is a single window).

Training of the embedded weights (:func:`train_frequency_guided`, ``python -m priors.frequency_guided.train``
or ``python -m benchmark train frequency-guided``)
--------------------------------------------------------------------------------------------------
The official losses use SMPL-H mesh vertices, which this project does not ship. Both stages use
"pseudo-vertices" instead: the 22 FK joint positions on the fixed rest skeleton plus two markers per
joint 0.1 m along the joint's local x and z axes (so leaf rotations and twists, which move mesh
vertices but no joint, are penalised), in millimetres.

1. VPoser v1 (:func:`vposer_v1_loss`) on every 2nd frame of the training split (at most 200k poses):
   (1 - 1e-4) * mean|pv_rec - pv| (mm) + 1e-4 * KL (sum over dims; the official v1 ``kl_coef``);
   Adam lr 1e-3 cosine to 1e-4, weight decay 5e-4 (official ``reg_coef``), batch 256, 3,000 steps
   (about 0.03 s each on one core).
2. Motion prior on 128-frame windows (stride 32) of the training split at 30 fps, the VPoser v1
   frozen (its codes of the input poses and the heading-normalised joints precomputed once,
   :func:`prepare_windows`): the official structure (1 - 1e-2) * mean|pv_rec - pv| (mm, target
   root = heading-normalised root, no translation) + 1e-2 * KL (sum over latent dims, mean over
   batch) + 1e-3 * mean(decoded codes^2); random-yaw augmentation of the encoder input. The
   reconstruction term is evaluated on 32 random frames of the 128 per step (an unbiased estimate of
   the official mean over all frames; forward kinematics and VPoser decoding dominate the step
   otherwise). Adam lr 5e-4 cosine to 5e-5, weight decay 1e-4 (official ``reg_coef``), batch 32,
   8,000 steps (about 0.1-0.25 s of CPU time each on one core, a third of it in Adam over the 4.2 M
   ``dct_att`` weights): 15 min with stage 1 and data preparation for the committed weights (with
   2,500 steps the validation reconstruction was 34.5 mm and still falling; 20.8 mm now). The official
   lr 1e-4 / batch 60 / 250 epochs do not fit a CPU budget. Validation losses are computed in eval
   mode (yaw 0, z = posterior mean, all frames).

Checkpoints
-----------
- Official (size "paper"): ``pretrained_priorD.pth``, a plain state dict of the
  DistributedDataParallel wrapper (every key ``module.<name>``; the prefix is stripped) holding
  exactly the MotionPrior keys above (the official test loads it strictly), and VPoser v1.0
  ``TR00_E096.pt`` (plain state dict of ``bodyprior_*`` keys). ``weights`` is either a folder
  searched (recursively) for ``pretrained_priorD.pth`` and ``TR00_E096.pt`` (else the single
  ``*.pth`` and the single ``*.pt`` in it), or the two files as ``"a.pth,b.pt"`` (either order: each
  file is recognised by its keys), or a (path, path) tuple. CLI:
  ``--weights frequency-guided=/path/folder`` or ``--weights frequency-guided=/p/pretrained_priorD.pth,/p/TR00_E096.pt``.
- Project (size "embedded"): ``priors/weights/frequency_guided.pt`` =
  ``{"state_dict": {motion_prior.*, vposer.*, rest_joints}, "config": {...}}`` with its record
  ``frequency_guided.json`` (data, sizes, steps, wall time, losses).
"""

from priors.frequency_guided.adapter import FrequencyGuidedPrior
from priors.frequency_guided.model import EMBEDDED_CONFIG, PAPER_CONFIG, FrequencyGuidedNetwork, MotionPrior

__all__ = ["FrequencyGuidedPrior", "FrequencyGuidedNetwork", "MotionPrior", "PAPER_CONFIG", "EMBEDDED_CONFIG"]
