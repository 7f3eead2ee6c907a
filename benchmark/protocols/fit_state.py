"""The state of a completion fit and the pieces every fit and search shares (split from
:mod:`benchmark.protocols.completion`): the optimised variables
(:class:`FitState`), body parameters at any time, the initial state, and the data term on subsets
used by the coarse searches (facing, limb start). The optimisers and step rules are in
:mod:`benchmark.protocols.step_rules`."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import roma
import torch

from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.metrics.static_chamfer import StaticChamfer
from priors.base import Decoded, FitBatch, PriorAdapter

log = logging.getLogger(__name__)

@dataclass
class FitState:
    """Everything optimised for one batch, and how to turn it into body parameters at any time."""

    adapter: PriorAdapter
    latents: dict
    shape_param: torch.Tensor  # (B, S)
    obs_t: torch.Tensor  # (B, n) observed timestamps
    window_s: float
    root: torch.Tensor | None = None  # (B, n, 6) free root orientation per observed frame
    trans: torch.Tensor | None = None  # (B, n, 3) free translation per observed frame
    heading: torch.Tensor | None = None  # (B, 1) free heading angle
    offset: torch.Tensor | None = None  # (B, 3) free offset
    bounded_shape: bool = True

    def shape(self) -> torch.Tensor:
        return torch.sigmoid(self.shape_param) if self.bounded_shape else self.shape_param

    def parameters(self) -> list[torch.Tensor]:
        params = [*(v for v in self.latents.values() if v.requires_grad), self.shape_param]
        params += [p for p in (self.root, self.trans, self.heading, self.offset) if p is not None]
        return params


def as_latent(adapter: PriorAdapter, key: str, leaf: torch.Tensor) -> torch.Tensor:
    """``leaf`` (a fresh leaf copy of the latent ``key``) requiring grad where the protocol optimises
    it: a floating latent not among the adapter's ``constant_latents`` (those, like integer ones, are
    read by the decoder and never optimised)."""
    return leaf.requires_grad_(leaf.is_floating_point() and key not in adapter.constant_latents)


def decode_grid(adapter: PriorAdapter, window_s: float, B: int, device) -> torch.Tensor:
    """The decoder's own frame grid for fixed-window priors, covering the window."""
    w = adapter.window
    per_window = w.frames
    n_windows = max(1, math.ceil(window_s * w.fps / per_window - 1e-9))
    t = torch.arange(n_windows * per_window, dtype=torch.float64, device=device) / w.fps
    return t.expand(B, -1)


def body_parameters(state: FitState, timestamps: torch.Tensor, observed: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations (B, T, 22, 3, 3) and translation (B, T, 3) at ``timestamps`` (B, T).

    ``observed`` says the timestamps are the observed ones (no interpolation of per-frame variables).
    """
    a = state.adapter
    kind = a.window.kind
    shape = state.shape() if a.shape_conditioned else None
    if kind == "per-frame":
        dec = _decode_output(a, a.decode(state.latents, state.obs_t, shape), state.shape_param)
        rot = dec.rotations if observed else slerp_frames(dec.rotations, state.obs_t, timestamps)
        trans = None if dec.trans is None else (dec.trans if observed else lerp_frames(dec.trans, state.obs_t, timestamps))
    elif kind == "fixed":
        grid = decode_grid(a, state.window_s, timestamps.shape[0], timestamps.device)
        dec = _decode_output(a, a.decode(state.latents, grid, shape), state.shape_param)
        rot = slerp_frames(dec.rotations, grid, timestamps)
        trans = None if dec.trans is None else lerp_frames(dec.trans, grid, timestamps)
    elif kind == "continuous":
        dec = _decode_output(a, a.decode(state.latents, timestamps, shape), state.shape_param)
        rot, trans = dec.rotations, dec.trans
    else:
        raise ValueError(f"prior {a.name!r}: unknown window kind {kind!r}")
    _check_decoded(a, Decoded(rot, trans), timestamps, state.latents)
    return apply_free_rigid(state, rot, trans, timestamps, observed)


def apply_free_rigid(state: FitState, rot: torch.Tensor, trans: torch.Tensor | None, timestamps: torch.Tensor,
                     observed: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The protocol's free rigid parameters of ``state`` composed with decoded (rot, trans) at
    ``timestamps`` (B, T): per-observed-frame root orientation (SLERP-ed) on the root, then the
    heading about y on root and translation, then per-observed-frame translation (LERP-ed) and the
    offset added. ``observed``: the timestamps are the observed ones (no interpolation)."""
    if state.root is not None:
        R = roma.special_gramschmidt(state.root.unflatten(-1, (3, 2)))
        R = R if observed else slerp_frames(R, state.obs_t, timestamps)
        rot = torch.cat([(R @ rot[:, :, 0])[:, :, None], rot[:, :, 1:]], dim=2)
    if state.heading is not None:
        zero = torch.zeros_like(state.heading)
        H = roma.rotvec_to_rotmat(torch.cat([zero, state.heading, zero], dim=-1))[:, None]  # (B, 1, 3, 3)
        rot = torch.cat([(H[:, :, None] @ rot[:, :, :1]), rot[:, :, 1:]], dim=2)
        if trans is not None:
            trans = (H @ trans[..., None])[..., 0]
    if state.trans is not None:
        free = state.trans if observed else lerp_frames(state.trans, state.obs_t, timestamps)
        trans = free if trans is None else trans + free
    if state.offset is not None:
        trans = trans + state.offset[:, None]
    return rot, trans


def _decode_output(adapter, dec, like: torch.Tensor) -> Decoded:
    """``dec``, what ``adapter.decode`` returned, checked before it is interpolated or skinned: a
    :class:`Decoded` of tensors with ``like``'s (the body's) dtype and device, with a translation
    where the prior declares ``encodes_translation`` and none where it does not. A ValueError naming
    the prior, the field and the fix otherwise (not torch's dtype error inside the body, a TypeError
    adding None, or a decoded translation silently added to the free one)."""
    name = adapter.name
    if not isinstance(dec, Decoded):
        raise ValueError(f"prior {name!r}: decode returned {type(dec).__name__}, expected a priors.base.Decoded"
                         "(rotations=..., trans=...)")
    for field_name, t in (("rotations", dec.rotations), ("trans", dec.trans)):
        if t is None and field_name == "trans":
            continue
        if not torch.is_tensor(t) or t.dtype != like.dtype or t.device != like.device:
            got = f"{t.dtype} on {t.device}" if torch.is_tensor(t) else type(t).__name__
            raise ValueError(f"prior {name!r}: decode returned {field_name} as {got}, expected {like.dtype} on "
                             f"{like.device} (the body's; timestamps are float64: cast what you compute from them "
                             "to the latents' dtype and device)")
    if adapter.encodes_translation and dec.trans is None:
        raise ValueError(f"prior {name!r} declares encodes_translation = True but decode returned trans=None: return "
                         "the decoded translation (B, T, 3), or declare encodes_translation = False (the protocol "
                         "then fits a free per-frame translation)")
    if not adapter.encodes_translation and dec.trans is not None:
        raise ValueError(f"prior {name!r} declares encodes_translation = False but decode returned a translation "
                         "(trans): the protocol fits its own free per-frame translation, and the decoded one would be "
                         "added to it unseen; return trans=None, or declare encodes_translation = True (the protocol "
                         "then uses the decoded translation, with a free constant offset)")
    return dec


def _check_decoded(adapter, dec: Decoded, timestamps: torch.Tensor, latents: dict | None = None) -> None:
    B, T = timestamps.shape
    if dec.rotations.shape[:3] != (B, T, 22) or dec.rotations.shape[-2:] != (3, 3):
        raise ValueError(
            f"prior {adapter.name!r}: decode returned rotations of shape {tuple(dec.rotations.shape)}, "
            f"expected {(B, T, 22, 3, 3)}"
        )
    if dec.trans is not None and dec.trans.shape != (B, T, 3):
        raise ValueError(f"prior {adapter.name!r}: decode returned trans {tuple(dec.trans.shape)}, expected {(B, T, 3)}")
    if not bool(torch.isfinite(dec.rotations).all()) or (dec.trans is not None and not bool(torch.isfinite(dec.trans).all())):
        bad = sorted(k for k, v in (latents or {}).items() if v.is_floating_point() and not bool(torch.isfinite(v).all()))
        if bad:  # the decoder was given NaN: a step's gradient was not finite
            raise ValueError(f"prior {adapter.name!r}: its latents {bad} are NaN or inf: a fit step had a NaN or inf "
                             "gradient (prior_term's or decode's backward at the start, e.g. a norm or sqrt at 0); "
                             "python -m benchmark check-prior checks both gradients at init_latents and mean_latents")
        raise ValueError(f"prior {adapter.name!r}: decode returned NaN or inf rotations or translations (from latents "
                         "it was given or fitted to: check its decoder on them, e.g. python -m benchmark check-prior)")


LATENT_INITS = ("sample", "mean")  # objective.latent_init (initial_latents)


def initial_latents(adapter: PriorAdapter, batch: FitBatch, generator: torch.Generator,
                    latent_init: str = "sample") -> dict[str, torch.Tensor]:
    """A fit's starting latents: ``latent_init="sample"`` (table1 v1-v2, docs/protocol.md): the adapter's
    ``init_latents`` (a random prior sample, or a deterministic encoder output); ``"mean"`` (table1
    v3): the prior's mean (``mean_latents``) where the adapter's start is a random sample, else its
    ``init_latents`` (deterministic already)."""
    if latent_init not in LATENT_INITS:
        raise ValueError(f"latent_init {latent_init!r}: choose one of {', '.join(LATENT_INITS)}")
    latents = adapter.mean_latents(batch) if latent_init == "mean" else None
    if latents is None:
        return adapter.init_latents(batch, generator)
    from benchmark.protocols.latent_checks import check_latents

    # init_latents' layout, drawn from a generator of its own (the fit's stream is not touched)
    layout = adapter.init_latents(batch, torch.Generator(device=generator.device).manual_seed(0))
    check_latents(adapter, latents, layout, "mean_latents")
    return latents


def init_state(adapter: PriorAdapter, body, batch: FitBatch, generator: torch.Generator, device,
               data_term: StaticChamfer | None = None, search_heading: bool = True,
               latent_init: str = "sample") -> FitState:
    """The initial state of a fit (see module docstring). ``data_term``: the Chamfer against
    ``batch``'s observed points (frames flattened), when the caller already built it.
    ``search_heading``: run the 8-yaw T-pose search (protocol v1); False leaves the facing at +z.
    ``latent_init``: :func:`initial_latents`."""
    B, n = batch.batch_size, batch.num_observed
    latents = {k: as_latent(adapter, k, v.detach().to(device).clone())
               for k, v in initial_latents(adapter, batch, generator, latent_init).items()}
    bounded = body.name == "anny"
    default = body.default_shape(B).to(device)
    shape_param = (torch.logit(default.clamp(1e-4, 1 - 1e-4)) if bounded else default).clone().requires_grad_(True)
    with torch.no_grad():
        rest = body.prepare(default)
        tpose = body.skin(rest, torch.eye(3, device=device).expand(B, 1, 22, 3, 3), torch.zeros(B, 1, 3, device=device))
        rest_centroid = tpose.vertices[:, 0].mean(1)  # (B, 3)
        mask = torch.arange(batch.points.shape[2], device=device) < batch.lengths[..., None]
        cen = (batch.points * mask[..., None]).sum(2) / batch.lengths.clamp_min(1)[..., None]  # (B, n, 3)
        trans0 = cen - rest_centroid[:, None]
    state = FitState(adapter=adapter, latents=latents, shape_param=shape_param, obs_t=batch.timestamps,
                     window_s=batch.window_s, bounded_shape=bounded)
    if not adapter.encodes_translation:
        state.trans = trans0.clone().requires_grad_(True)
    if not adapter.encodes_root_orientation:
        eye6 = torch.eye(3, device=device)[:, :2].reshape(6)
        state.root = eye6.expand(B, n, 6).clone().requires_grad_(True)
    if adapter.heading_normalised:
        state.heading = torch.zeros(B, 1, device=device, requires_grad=True)
    if adapter.encodes_translation:
        state.offset = trans0.mean(1).clone().requires_grad_(True)
    if search_heading:
        _initial_heading(state, body, batch, data_term)
    return state


HEADING_CANDIDATES = 8


@torch.no_grad()
def _initial_heading(state: FitState, body, batch: FitBatch, data_term: StaticChamfer | None = None) -> None:
    """Coarse search of the initial facing direction, the same for every prior.

    The body is tried at HEADING_CANDIDATES yaw angles (about y, applied to the free root
    orientation or the free heading) and each sequence keeps the yaw with the lowest initial data
    term. Without it, every prior starts facing +z and a subject walking the other way is often
    fitted backwards, whatever the prior.
    """
    if state.root is None and state.heading is None:
        return
    B, n = batch.batch_size, batch.num_observed
    if data_term is None:
        data_term = StaticChamfer(batch.points.flatten(0, 1), batch.lengths.flatten(0, 1))
    subset = body.loss_vertex_indices(1000)
    rest = body.prepare(state.shape())
    base_root = None if state.root is None else state.root.detach().clone()
    base_heading = None if state.heading is None else state.heading.detach().clone()
    scores = []
    for k in range(HEADING_CANDIDATES):
        yaw = 2 * math.pi * k / HEADING_CANDIDATES
        set_yaw(state, base_root, base_heading, torch.full((B,), yaw, device=batch.points.device))
        rot, trans = body_parameters(state, batch.timestamps, observed=True)
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
        d = data_term(verts.flatten(0, 1))
        scores.append(d.view(B, n).mean(1))
    best = torch.stack(scores, 1).argmin(1).to(batch.points.dtype)  # (B,)
    set_yaw(state, base_root, base_heading, 2 * math.pi * best / HEADING_CANDIDATES)


def set_yaw(state: FitState, base_root, base_heading, yaw: torch.Tensor) -> None:
    if state.heading is not None:
        state.heading.copy_(base_heading + yaw[:, None])
        return
    zero = torch.zeros_like(yaw)
    Y = roma.rotvec_to_rotmat(torch.stack([zero, yaw, zero], -1))[:, None]  # (B, 1, 3, 3)
    R = roma.special_gramschmidt(base_root.unflatten(-1, (3, 2)))
    state.root.copy_((Y @ R)[..., :2].flatten(-2))


def parameter_groups(state: FitState, lr: float, shape_lr_scale: float = 1.0) -> list:
    """The optimiser's parameters of ``state``: one group at ``lr``, or, with ``shape_lr_scale`` != 1,
    the body shape in a group of its own at ``lr * shape_lr_scale`` (protocol v2's ``objective.shape_lr_scale``)."""
    params = state.parameters()
    if shape_lr_scale == 1.0:
        return params
    return [{"params": [p for p in params if p is not state.shape_param]},
            {"params": [state.shape_param], "lr": lr * shape_lr_scale}]


FACING_POINTS = 256  # observed points per frame the hypotheses are scored on
FACING_VERTICES = 400  # mesh vertices (farthest-point subset) the hypotheses are scored on


def subset_batch(batch: FitBatch, points: int) -> FitBatch:
    """The first ``points`` observed points of every frame (i.i.d. uniform samples: an unbiased subset)."""
    m = min(points, batch.points.shape[2])
    return FitBatch(points=batch.points[:, :, :m], lengths=batch.lengths.clamp_max(m), timestamps=batch.timestamps,
                    window_s=batch.window_s, output_timestamps=batch.output_timestamps)


def batch_rows(batch: FitBatch, rows: torch.Tensor) -> FitBatch:
    """The sequences ``rows`` ((R,) long) of ``batch``."""
    pick = lambda x: x.index_select(0, rows.to(x.device))  # noqa: E731
    return FitBatch(points=pick(batch.points), lengths=pick(batch.lengths), timestamps=pick(batch.timestamps),
                    window_s=batch.window_s, output_timestamps=pick(batch.output_timestamps))


def state_rows(state: FitState, rows: torch.Tensor) -> FitState:
    """The sequences ``rows`` ((R,) long) of ``state``, as tensors indexed from its variables: a
    loss on them sends its gradient to those rows of ``state``'s variables (zero elsewhere)."""
    pick = lambda x: None if x is None else x.index_select(0, rows.to(x.device))  # noqa: E731
    return replace(state, latents={k: pick(v) for k, v in state.latents.items()}, shape_param=pick(state.shape_param),
                   obs_t=pick(state.obs_t), root=pick(state.root), trans=pick(state.trans),
                   heading=pick(state.heading), offset=pick(state.offset))


def row_frames(rows: torch.Tensor, n: int) -> torch.Tensor:
    """The frames (rows of a batch flattened to B x n frames) of the sequences ``rows``."""
    return (rows[:, None] * n + torch.arange(n, device=rows.device)).flatten()


@torch.no_grad()
def rows_independent(value_of, adapter: PriorAdapter, B: int, device) -> bool:
    """Whether each sequence's value of ``value_of(rows)`` (the (R,) per-sequence objective of the
    sequences ``rows``; None: the (B,) whole batch) stays the same (to float rounding: 1e-5
    relative) when it is evaluated with only some of the others: the condition under which a
    plateau descent may evaluate only the sequences still descending
    (:class:`~benchmark.protocols.kept_rows.KeptRows`). Checked once per fit, at its start, on
    three subsets (all but the first sequence, every other one, the last one), inside the adapter's
    :meth:`~priors.base.PriorAdapter.batch_rows`; a prior whose sequences interact, or whose
    per-batch state that context does not select, is then evaluated whole at every step, as before."""
    if B < 2:
        return False
    whole = value_of(None)
    for rows in (torch.arange(1, B), torch.arange(0, B, 2), torch.tensor([B - 1])):
        rows = rows.to(device)
        try:
            with adapter.batch_rows(rows):
                part = value_of(rows)
        except (ValueError, RuntimeError) as err:  # per-batch state the adapter does not select (PriorAdapter.batch_rows)
            log.info("prior %r: its objective cannot be evaluated on some sequences of the batch (%s); every step "
                     "evaluates the whole batch", adapter.name, err)
            return False
        if part.shape != (rows.numel(),) or not torch.allclose(whole[rows], part, rtol=1e-5, atol=1e-6):
            log.info("prior %r: a sequence's objective changes with the other sequences of the batch (rows %s: %s "
                     "against %s); every step evaluates the whole batch", adapter.name, rows.tolist(),
                     part.tolist(), whole[rows].tolist())
            return False
    return True


def repeat_batch(batch: FitBatch, k: int) -> FitBatch:
    """Every sequence of ``batch`` repeated ``k`` times, hypothesis-major per sequence (b0h0, b0h1, ...)."""
    rep = lambda x: x.repeat_interleave(k, dim=0)  # noqa: E731
    return FitBatch(points=rep(batch.points), lengths=rep(batch.lengths), timestamps=rep(batch.timestamps),
                    window_s=batch.window_s, output_timestamps=rep(batch.output_timestamps))


def rigid_parameters(state: FitState) -> list[torch.Tensor]:
    return [p for p in (state.root, state.trans, state.heading, state.offset) if p is not None]


def frame_chamfer(state: FitState, body, batch: FitBatch, subset, chamfer: StaticChamfer) -> torch.Tensor:
    """(B, n) the Chamfer (metres) of the mesh (vertex ``subset``) against the observed points of
    ``batch`` (``chamfer``: their StaticChamfer) at each observed frame."""
    B, n = batch.batch_size, batch.num_observed
    rot, trans = body_parameters(state, batch.timestamps, observed=True)
    rest = body.prepare(state.shape())
    verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
    return chamfer(verts.flatten(0, 1)).view(B, n)


def subset_data_term(state: FitState, body, batch: FitBatch, subset, chamfer: StaticChamfer) -> torch.Tensor:
    """(B,) the protocol's data term (mm): :func:`frame_chamfer`, mean over the observed frames."""
    return frame_chamfer(state, body, batch, subset, chamfer).mean(1) * 1000.0


@torch.no_grad()
def set_rigid(state: FitState, timestamps: torch.Tensor, rotations: torch.Tensor | None,
              trans: torch.Tensor | None) -> None:
    """Set ``state``'s free rigid parameters so that its motion at the observed ``timestamps``
    (B, n) follows a given root orientation (``rotations``: (B, n, 22, 3, 3) local rotations, or
    their roots) and translation (B, n, 3): the free root orientation to the root (priors that do not
    decode it), the free heading to the mean yaw between it and the decoded root, the free
    translation to the translation (priors that do not decode it), the free offset to the mean
    difference from the decoded translation."""
    R_obs = None if rotations is None else rotations[:, :, 0].to(state.shape_param)
    if state.root is not None and R_obs is not None:
        state.root.copy_(R_obs[..., :, :2].flatten(-2))
    if state.heading is not None and R_obs is not None:
        state.heading.zero_()
        rot, _ = body_parameters(state, timestamps, observed=True)
        rel = R_obs @ rot[:, :, 0].transpose(-1, -2)  # H with H @ decoded root = observed root
        yaw = torch.atan2(rel[..., 0, 2], rel[..., 2, 2])  # (B, n) yaw about +y
        state.heading.copy_(torch.atan2(yaw.sin().mean(1), yaw.cos().mean(1))[:, None])
    if trans is not None:
        tr_obs = trans.to(state.shape_param)
        if state.trans is not None:  # the prior does not decode translation
            state.trans.copy_(tr_obs)
        elif state.offset is not None:  # it does: align its decoded translation on average
            state.offset.zero_()
            _, tr = body_parameters(state, timestamps, observed=True)
            state.offset.copy_((tr_obs - tr).mean(1))
