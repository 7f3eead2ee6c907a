"""The frequency-guided motion prior as a :class:`~priors.base.PriorAdapter`."""

from __future__ import annotations

import math

import torch
from torch import nn

from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import (
    Decoded, ExportableDecoder, ExportSpec, FitBatch, MotionEncoder, PaperNetwork, PriorAdapter, Trainable, WindowSpec,
)
from priors.frequency_guided import checkpoint
from priors.frequency_guided.model import FPS, FRAMES, ExportModule, FrequencyGuidedNetwork, PAPER_CONFIG
from priors.frequency_guided.checkpoint import DEFAULT_WEIGHTS, WHERE_TO_GET
from priors.training import embedded_out_dir


def n_windows_for(window_s: float, frames: int = FRAMES, fps: float = FPS) -> int:
    """Windows covering ``window_s`` seconds (the protocol's grid rule)."""
    return max(1, math.ceil(float(window_s) * fps / frames - 1e-9))


# -- the adapter -------------------------------------------------------------------------------
class FrequencyGuidedPrior(MotionEncoder, ExportableDecoder, PaperNetwork, Trainable, PriorAdapter):
    """Xu et al.'s motion prior: one latent per 128-frame window at 30 fps (module docstring).

    Latents ``{"z": (B, n_windows, L)}`` (L = 256 paper, 128 embedded), initialised from N(0, I);
    prior term |z|^2 summed over dims and windows. ``decode`` gives, on the grid of n_windows*128
    frames at 30 fps from t = 0, the heading-normalised root (6D head) and joints 1..21 (VPoser v1);
    the protocol adds a free heading + offset and a free translation per observed frame.
    """

    name = "frequency-guided"
    paper = "Xu et al. 2021 (3DV), Exploring versatile prior for human motion via motion frequency guidance"
    window = WindowSpec(kind="fixed", frames=FRAMES, fps=FPS)
    encodes_translation = False
    encodes_root_orientation = True
    heading_normalised = True
    joints = tuple(range(NUM_JOINTS))
    shape_conditioned = False
    sixd_layout = "interleaved"
    frozen_network = "network"
    default_weights = DEFAULT_WEIGHTS

    def __init__(self, size: str = "embedded", weights=None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=None if weights is None else str(weights), device=device)
        if size == "paper" and weights is None:
            raise ValueError(f"frequency-guided size 'paper' needs the official weights: {WHERE_TO_GET}")
        if size == "embedded":
            weights = self.embedded_weights(weights, f"or use size='paper' with the official weights ({WHERE_TO_GET})")
        self.network, self.checkpoint = checkpoint.load(weights, size)
        self.weights_path = self.checkpoint.weights_path
        self.freeze_network(device)

    @classmethod
    def paper_network(cls) -> nn.Module:
        """The paper-size network (motion prior + VPoser v1.0) with random weights."""
        return FrequencyGuidedNetwork(PAPER_CONFIG)

    @property
    def latent_dim(self) -> int:
        return self.network.motion_prior.latent

    @property
    def frames(self) -> int:
        return self.network.motion_prior.frames

    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"z": (B, n_windows, L)}`` from N(0, I), n_windows = ceil(window_s * 30 / 128)."""
        n = n_windows_for(batch.window_s, self.frames, self.window.fps)
        z = torch.randn((batch.batch_size, n, self.latent_dim), generator=generator, device=generator.device, dtype=torch.float32)
        return {"z": z.to(self.device)}

    def mean_latents(self, batch: FitBatch) -> dict[str, torch.Tensor]:
        """``{"z": zeros (B, n_windows, L)}``: the mean of the N(0, I) prior."""
        n = n_windows_for(batch.window_s, self.frames, self.window.fps)
        return {"z": torch.zeros((batch.batch_size, n, self.latent_dim), device=self.device)}

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) |z|^2 summed over the latent dims and over the windows."""
        return latents["z"].square().sum(dim=(-1, -2))

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """z (B, n, L) on the grid timestamps (B, n*128) -> rotations (B, n*128, 22, 3, 3)."""
        z = latents["z"]
        if z.dim() != 3 or z.shape[-1] != self.latent_dim:
            raise ValueError(f"frequency-guided: latents['z'] must be (B, n_windows, {self.latent_dim}), got {tuple(z.shape)}")
        B, n, L = z.shape
        if tuple(timestamps.shape) != (B, n * self.frames):
            raise ValueError(
                f"frequency-guided is a fixed-window prior: decode on its grid of n_windows*{self.frames} = {n * self.frames} "
                f"frames at {self.window.fps:g} fps from t = 0, shape {(B, n * self.frames)}; got timestamps {tuple(timestamps.shape)}"
            )
        rot = self.network.decoder(z.reshape(B * n, L))
        return Decoded(rotations=rot.reshape(B, n * self.frames, NUM_JOINTS, 3, 3))

    @torch.no_grad()
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor,
                      n_windows: int | None = None) -> dict[str, torch.Tensor]:
        """Posterior means ``{"z": (B, n_windows, L)}`` of motions.

        rotations (B, T, 22, 3, 3) local rotations (root = world orientation, y up), trans (B, T, 3),
        timestamps (B, T) s from the window start. The motion is brought to the 30 fps grid of
        n_windows*128 frames from t = 0 (SLERP / LERP; the final frame is repeated past the end), cut
        into 128-frame windows, each heading-normalised at its first frame with yaw augmentation 0;
        n_windows defaults to the fewest windows whose grid reaches the last timestamp.
        """
        if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"encode_motion: rotations must be (B, T, 22, 3, 3), got {tuple(rotations.shape)}")
        B, T = rotations.shape[:2]
        if tuple(trans.shape) != (B, T, 3) or tuple(timestamps.shape) != (B, T):
            raise ValueError(f"encode_motion: trans must be (B, T, 3) and timestamps (B, T) for rotations {tuple(rotations.shape)}; "
                             f"got {tuple(trans.shape)}, {tuple(timestamps.shape)}")
        dev = self.device
        Fr, fps = self.frames, self.window.fps
        if n_windows is None:
            last = float(timestamps.max())
            n_windows = max(1, math.floor(last * fps / Fr + 1e-6) + 1)
        grid = (torch.arange(n_windows * Fr, dtype=torch.float64, device=dev) / fps).expand(B, -1)
        ts = timestamps.to(dev, torch.float64)
        R = slerp_frames(rotations.to(dev, torch.float32), ts, grid)
        tr = lerp_frames(trans.to(dev, torch.float32), ts, grid)
        W = B * n_windows
        R = R.reshape(W, Fr, NUM_JOINTS, 3, 3)
        tr = tr.reshape(W, Fr, 3)
        net = self.network
        codes = net.vposer_codes(R[:, :, 1:])
        inp = net.inputs(net.features(R, tr), codes, yaw=None)
        q = net.motion_prior.encode(inp["pin"], inp["frequency"], inp["frequency_block"])
        return {"z": q.loc.reshape(B, n_windows, self.latent_dim)}

    def export_decoder(self) -> ExportSpec:
        """z (B, L) -> rotations (B, 128, 22, 3, 3) of one window (heading-normalised root)."""
        module = ExportModule(self.network.decoder).eval()
        g = torch.Generator().manual_seed(0)
        z = torch.randn(2, self.latent_dim, generator=g).to(self.device)
        return ExportSpec(module=module, example_inputs=(z,), input_names=["z"], output_names=["rotations"])

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """``python -m benchmark train frequency-guided``: retrain the embedded weights (train_frequency_guided)."""
        from priors.frequency_guided.train import train_frequency_guided

        out = embedded_out_dir(out_dir, DEFAULT_WEIGHTS, overwrite)
        _, record = train_frequency_guided(out, seed=seed, dataset=dataset, **({"steps": int(steps)} if steps is not None else {}))
        return record
