"""Motion-DVAE (Fiche et al., "Motion-DVAE: Unsupervised learning for fast human motion denoising",
ACM MIG 2023, arXiv 2306.05846; paper 003 of docs/protocol.md; summary: docs/priors.md).

The formulas of our copy of the paper were lost in conversion; everything below that the text does
not state is marked **[inferred]** and is this project's reconstruction.

State (paper section 3.1)
-------------------------
One 138-D state per frame **[inferred dimension]**::

    x_t = [ trans (3) | root orientation axis-angle (3) | 21 body joints axis-angle (63)
            | their velocities (finite differences x 30 fps, 69) ]

Velocities: ``(p_t - p_{t-1}) * fps``; frame 0 copies frame 1's **[inferred]**. Axis-angle sequences
are unwrapped in time (a rotation vector is replaced by its equivalent ``v - 2 pi v/|v|`` when that
is closer to the previous frame's) so that finite differences stay small **[inferred]**. The network
sees the state standardised with per-dimension training mean/std (buffers ``state_mean`` /
``state_std``) **[inferred]**. Every window is canonicalised like HuMoR (A.4): at its first frame
the translation is zeroed in the ground plane (x, z; the height y is kept) and the heading (yaw of
the root about the world y axis; the body faces +z) is removed; the same rigid transform is
applied to every frame.

Network (paper section 3.2, Appendix A.1-A.2)
---------------------------------------------
Generative model, x_0 given (a parameter)::

    p(x_{1:T}, z_{1:T} | x_0) = prod_t p(x_t | x_0, z_{1:t}) p(z_t | x_0, z_{1:t-1})

- One LSTM (``gen_rnn``, paper hidden 1024) shared by the prior and the decoder. It consumes
  ``u_t = [z_t, x^_0]`` (x^_0 = standardised x_0, repeated at every step) with ``z_0 = 0``, from a
  zero state: ``h_0`` summarises x_0 and ``h_t`` summarises (x_0, z_{1:t}) **[inferred]**.
- Prior head on the previous state: ``p(z_t | x_0, z_{1:t-1}) = N(prior_mean(h_{t-1}),
  exp(prior_logvar(h_{t-1})))`` (two MLPs).
- Decoder head on the current state and the latent: ``d_t = decoder([h_t, z_t])`` is the increment
  of the standardised state, ``mean(x^_t) = x^_0 + sum_{s<=t} d_s`` (a deterministic function of
  x_0 and z_{1:t}, so the factorisation above holds) **[inferred]**; the decoder's last layer starts
  at zero (the untrained model holds x_0). ``p(x_t | x_0, z_{1:t})`` is Gaussian with a learned
  per-dimension variance ``exp(dec_logvar)`` in standardised units **[inferred]** (a fixed unit
  variance let the KL term switch the latents off in our trials). x_t does not depend on past x
  given z: no scheduled sampling, and for given latents the whole generative pass is one LSTM call
  over the sequence (plus a running sum), which is what ``decode`` and the ONNX export run.
- MLPs follow HuMoR's pattern (``davrempe/humor: humor/models/humor_model.py`` class MLP): Linear,
  then [GroupNorm(16) -> ReLU -> Linear] x 2 (2 hidden layers). Hidden width 1024 in the paper size
  (HuMoR's width; the paper does not give it **[inferred]**).
- Inference ``q(z_t | x_0, z_{1:t-1}, x_{t:T})`` (D-separation): an anti-causal LSTM over the
  standardised states ``b_t = LSTM_bwd(x^_t, b_{t+1})`` (``encoder.bwd_rnn``) and a forward
  recurrence over z ``f_t = LSTMCell([z_t, x^_0], f_{t-1})``, ``f_0`` from ``[0, x^_0]``
  (``encoder.fwd_cell``), heads ``post_mean([f_{t-1}, b_t])`` and ``post_logvar([f_{t-1}, b_t])``
  **[inferred wiring]**; the encoder LSTMs have the generative LSTM's width.
- Feedback wiring (``feedback=True`` in the config; the embedded weights use it, a paper-size
  network defaults to the plain wiring above): the forward recurrence reads the decoded standardised
  state instead of x^_0, ``f_t = LSTMCell([z_t, x^dec_t], f_{t-1})``, with ``x^dec_t`` the decoder's
  output for ``x_0, z_{1:t}``. It conditions on the same variables (x^dec_t is a function of x_0 and
  z_{1:t}), so the factorisation is the paper's; it lets the encoder see the decoder's accumulated
  increments and correct them. The plain wiring's embedded encoder was 41 mm off by frame 5 and
  57 mm over 2 s windows (:meth:`MotionDVAE.infer`). Same parameters, so a plain checkpoint loads
  into either wiring.
- Residual input of the clean encoder (``encoder_residual=True`` in the config, feedback wiring
  only; the embedded weights use it): the posterior heads also read ``clip(x^_t - x^dec_{t-1})``,
  the target pose (trans, root, body: 69 standardised dims) minus the decoded pose, each dimension
  clipped to +-``RESIDUAL_CLIP`` std, through two bias-free Linear maps that start at zero **[inferred]**.
  Same conditioning set (x^dec_{t-1} is a function of x_0 and z_{1:t-1}; x_t is in x_{t:T}); it hands
  the encoder the gap it must close instead of leaving it to compute the gap from two LSTM summaries.
  The denoising encoder does not have it.
- Latent z_t in R^48.

Loss (A.3), per frame, mean over the batch: ``1/2 sum_d [(x^_t,d - mean_d)^2 / var_d + log var_d]``
(standardised state) ``+ beta * KL(q(z_t) || p(z_t))`` (48 dims) ``+ POINT_WEIGHT * sum over body
points of the squared error`` (metres^2). Body points: the 22 forward-kinematics joints on a fixed
rest skeleton (``priors.training.fixed_rest_skeleton``) and 2 virtual markers per joint
(``MARKER_OFFSET`` m along the joint frame's x and z axes). We do not ship SMPL meshes: the markers
stand in for the paper's mesh term, the joints for its joint term. beta (KL annealing) rises
linearly from 0 to 1 over the first ``KL_ANNEAL_FRACTION`` of the steps (paper: the first 50 of 200
epochs).

Denoising (section 4, Appendix E)
---------------------------------
Prior and decoder frozen; trained (unsupervised, on noisy copies of the training windows: Gaussian
noise sigma ~ U[0.05, 0.25] rad on every joint's axis-angle, root included, translation clean;
see :func:`noisy_poses` for the one approximation):

- ``denoise_encoder``: a copy of the DVAE encoder, fine-tuned (the clean ``encoder`` stays, for
  ``encode_motion``);
- ``init_state``: initial-state predictor ``q(x_0 | y) = N(mu, sigma)``: an anti-causal LSTM over
  the noisy states + two MLP heads; ``mu`` is a residual on the noisy first positions/orientations
  while its velocities start from the data mean (noisy finite differences are far off the data)
  **[inferred]**;
- ``noise``: per-frame variance ``q(v_t | y) = InvGamma(alpha_t, beta_t)`` from an MLP on the
  denoising encoder's anti-causal features (the paper's noise predictor re-uses the encoder's LSTM
  and adds its own MLP; one variance per frame instead of per joint and axis: a simplification).

Objective (per window, per frame): ``sum_t [ 1/2 E[1/v_t] |y_t - y^_t|^2 + (P/2) E[log v_t] ] +
beta * sum_t KL_z + sum_t KL(InvGamma(alpha_t, beta_t) || InvGamma(a0, b0))``, y the body points of
the noisy input (joints + markers as above, P = 198 coordinates), y^ those of the decoded motion
(frame 0 from the sampled x_0), ``E[1/v] = alpha/beta``, ``E[log v] = log beta - digamma(alpha)``:
marginally a Student-t likelihood. Noise prior: shape ``a0 = NOISE_PRIOR_SHAPE`` (large: nearly
Gaussian, as the paper does for AMASS), mean precision ``1/NOISE_PRIOR_SCALE_M^2``. The entropy of
q(x_0) is dropped as in the paper (C.2.2). The paper's observations are SMPL-H joints and mesh
markers; ours are the fixed-skeleton joints and the virtual markers. Regression mode = one forward
pass with posterior means; optimisation mode = a copy of the three denoising networks fine-tuned
for ``iterations`` Adam steps on the given batch with the same objective, then that forward pass
(:meth:`MotionDVAEPrior.denoise_motion`).

Sizes (``MotionDVAE(**cfg).parameter_counts()``)
------------------------------------------------
Paper (``PAPER_CONFIG``): z 48, LSTM hidden 1024 (generative, both encoder LSTMs, initial-state
LSTM), MLP hidden 1024: 27,697,620 parameters for the DVAE (generative 11,563,380 + encoder
16,134,240), 55,194,442 with the denoising networks. Embedded (``EMBEDDED_CONFIG``): z 48, LSTM
hidden 256, MLP hidden 256, residual clean encoder: DVAE 2,241,492 (generative 925,044 + encoder
1,316,448), 4,397,386 in all (17.6 MB float32).

Embedded training (:func:`train_motion_dvae`, ``python -m benchmark train motion-dvae``)
---------------------------------------------------------------------------------------
30-frame windows every 10 frames of the synthetic train split at 30 fps (paper: 1 s windows),
batch 64, the shared loop ``priors.training.train_loop`` (Adam, cosine decay to 0.1 lr, one torch
thread): 1,800 DVAE steps at lr 1e-3, then 720 denoising steps at lr 1e-3. The paper uses Adamax
lr 1e-4 with HuMoR's decays for 200 epochs (far beyond an embedded CPU budget); a higher Adam lr
was chosen for the short run. Measured per step on this project's shared 2-core machine (other jobs
running; a VPoser step took 4-10x its documented idle time): 1.35 s (DVAE) and 1.64 s (denoising);
scaled by the VPoser reference, about 0.29 s and 0.35 s on an idle core, i.e. about 13 min for the
default steps (an estimate, +-50%). The record ``priors/weights/motion_dvae.json`` holds both
phases' losses, wall times and seconds per step.

The committed weights are the end of a warm-started chain (``training_chain`` in the record). Its
last two stages switched to the feedback wiring and kept the generative model fixed (so the
completion decoder and prior are the earlier ones). The clean encoder was trained alone
(``--encoder-only``) with the squared point errors weighted 400 instead of 100
(``--encoder-point-weight``): 2 x 2,400 steps; the 4 s validation point RMSE went from 0.154 m to
0.106 m. Before it, Adam fitting z directly on 4 test windows (300 steps, no prior term) reached
20 mm MPJPE with the same decoder where the encoder gave 55 mm: an amortisation gap, not a decoder
limit. The denoising networks were continued
under the feedback wiring (2 x 1,500 steps). The last stage gave the clean encoder its residual input
(1,000 steps), then 2,000 steps with two extra markers 1.5 m along the root's x and z axes in its point
loss (``--encoder-root-marker``; ``dvae_loss(root_marker_m=...)``): the reconstruction table aligns a
decoded motion by its mean root heading, so a heading error of 2-3 degrees moved a 3 m running path by
50-75 mm while the training loss barely saw it. Selected on the validation split's reconstruction
MPJPE (24 sequences): 54.8 mm before the stage, 38.7 after. Commands in the record.

Completion adapter (``MotionDVAEPrior``, registered as ``motion-dvae``)
-----------------------------------------------------------------------
Recurrent at a fixed 30 fps. ``window = WindowSpec("fixed", frames=30, fps=30)``: the protocol asks
``decode`` for ``ceil(window_s * 30 / 30) * 30`` grid frames from t = 0 (a 4 s window = 120 frames)
and the adapter runs ONE recurrence over the whole grid (30 frames is only the training length;
the model is recurrent, so grids longer than the training windows are extrapolation). Latents:
``x0n`` (B, 138), the state of frame 0 in the canonical frame, standardised (``state_mean``,
``state_std``: the units the network reads), and ``z`` (B, T - 1, 48), one latent per frame after
the first (frame 0 is x0 itself). Adapter revision 2 (``adapter_revision``): revision 1 optimised the
raw state, where a step of the fit's learning rate (0.03) moves a hinge joint's off axis, whose
deviation in the training data is the 1e-3 floor, by 30 deviations: table1's fits crept and jumped
without settling. Initialisation: x0n = the mean canonical first-frame state of the training windows
(buffer ``x0_mean``), z = an ancestral sample of the learned prior. ``encode_motion`` holds the
encoded first state within ``X0_HOLD`` (3) deviations, translation excepted, and encodes z from the
held state. Prior term (``prior_term_kind``): ``"learned"`` (default)
``= -1/(T-1) sum_t log N(z_t; mu_p(h_{t-1}), sigma_p(h_{t-1}))`` (nats per frame, summed over the 48
dims; gradients reach z and x0n), or ``"l2"`` = mean over frames of ``|z_t|^2``. Translation and root
orientation come from the decoded state (its positions and orientations, not integrated
velocities) in the canonical frame: ``heading_normalised = True``, the protocol frees a heading and
an offset per sequence. ``encode_motion`` and ``denoise_motion`` accept any timestamps (resampled
to 30 fps when they are not a 30 fps grid).

Checkpoints
-----------
Project file ``priors/weights/motion_dvae.pt``: ``{"state_dict": {...}, "config": {"z_dim",
"hidden", "mlp_hidden", "fps", "feedback", "encoder_residual"}}`` (``feedback`` absent: the plain
wiring; ``encoder_residual`` absent: no residual input) with this module's key names (``gen_rnn.*``, ``prior_mean.net.*``,
``prior_logvar.net.*``, ``decoder.net.*``, ``dec_logvar``, ``encoder.*``, ``denoise_encoder.*``,
``init_state.*``, ``noise.*`` and the buffers ``state_mean``, ``state_std``, ``x0_mean``,
``rest_joints``), loaded strictly. The official release (presumably github.com/g-fiche/Motion-DVAE)
could not be reached, so its format is unknown: :func:`priors.motion_dvae.checkpoint.load` (size
"paper", through :func:`~priors.motion_dvae.checkpoint.load_official`) loads a file whose keys match
these names (or are mapped by a ``key_map``) and otherwise raises a NotImplementedError that says
what is expected.
"""

from priors.motion_dvae.adapter import MotionDVAEPrior
from priors.motion_dvae.model import EMBEDDED_CONFIG, PAPER_CONFIG, MotionDVAE

__all__ = ["MotionDVAEPrior", "MotionDVAE", "PAPER_CONFIG", "EMBEDDED_CONFIG"]
