"""The ``sls`` fit: decoding the anchors, the objective with its adaptive (GradNorm) weights and the
optimisation of one batch against its observation (the rules: :mod:`benchmark.protocols.sls`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.protocols.latent_checks import prior_values
from benchmark.protocols.facing import facing_search
from benchmark.protocols.fit_state import (FitState, apply_free_rigid, body_parameters, init_state, parameter_groups,
                                           row_frames, rows_independent, state_rows)
from benchmark.protocols.brief_fit import check_start_fit, search_fit
from benchmark.protocols.start_search import (START_SEARCH_RULES, is_prior_free, prior_free_start,
                                              searched_start)
from benchmark.protocols.step_rules import PlateauRule, optimise, optimise_to_plateau
from benchmark.protocols.sls_data import Observation
from priors.base import AnchorDecoder, FitBatch, PriorAdapter

# Term scales: D in mm (x1e3 of metres), M in cm^2 (x1e4 of m^2), T in (10 ms)^2 (x1e4 of s^2).
DENSE_SCALE, MOCAP_SCALE, TIME_SCALE = 1e3, 1e4, 1e4
GRAD_FLOOR = 1e-12


def uses_anchor_decoder(adapter) -> bool:
    """Whether the adapter decodes its anchors itself (an :class:`~priors.base.AnchorDecoder`)."""
    return isinstance(adapter, AnchorDecoder)


def _rigid(state: FitState, rot: torch.Tensor, trans: torch.Tensor | None, timestamps: torch.Tensor):
    """The free rigid parameters of ``state`` applied to decoded (rot, trans) at ``timestamps``."""
    rot, trans = apply_free_rigid(state, rot, trans, timestamps)
    if trans is None:
        raise ValueError(f"prior {state.adapter.name!r}: decode_anchors gave no translation and the protocol has none free")
    return rot, trans


def decode_anchors(state: FitState, anchor_t: torch.Tensor, index: torch.Tensor | None):
    """Rotations (B, k, 22, 3, 3), translation (B, k, 3) and decoded timestamps (B, k) or None at
    the anchors ``index`` (None: all). ``anchor_t`` (B, A) are the anchors' true timestamps."""
    a = state.adapter
    if uses_anchor_decoder(a):
        shape = state.shape() if a.shape_conditioned else None
        dec, tau_hat = a.decode_anchors(state.latents, shape)
        B, A = anchor_t.shape
        if dec.rotations.shape[:3] != (B, A, 22) or tuple(tau_hat.shape) != (B, A):
            raise ValueError(f"prior {a.name!r}: decode_anchors gave rotations {tuple(dec.rotations.shape)} and tau_hat "
                             f"{tuple(tau_hat.shape)}, expected ({B}, {A}, 22, 3, 3) and ({B}, {A})")
        rot, trans = dec.rotations, dec.trans
        if index is not None:
            rot, tau_hat = rot[:, index], tau_hat[:, index]
            trans = None if trans is None else trans[:, index]
        t = anchor_t if index is None else anchor_t[:, index]
        rot, trans = _rigid(state, rot, trans, t)
        return rot, trans, tau_hat
    if index is not None and torch.equal(anchor_t[:, index], state.obs_t):
        rot, trans = body_parameters(state, state.obs_t, observed=True)
    else:
        rot, trans = body_parameters(state, anchor_t if index is None else anchor_t[:, index])
    return rot, trans, None


# ============================================================================ fit
@dataclass
class AdaptiveWeights:
    """Closed-form GradNorm weights per (term, sequence); see :mod:`benchmark.protocols.sls`."""

    active: list
    batch: int
    alpha: float = 1.5
    smoothing: float = 0.5
    every: int = 10

    def __post_init__(self):
        self.w = torch.ones(len(self.active), self.batch, dtype=torch.float64)
        self.initial: torch.Tensor | None = None

    def due(self, step: int) -> bool:
        return len(self.active) > 1 and step % max(self.every, 1) == 0

    def update(self, losses: torch.Tensor, grad_norms: torch.Tensor) -> None:
        """losses, grad_norms: (n_terms, B) unweighted term values and their latent-gradient norms."""
        losses = losses.detach().double().cpu()
        grad_norms = grad_norms.detach().double().cpu()
        if self.initial is None:
            self.initial = losses.clamp_min(1e-12)
        ratio = (losses / self.initial).clamp_min(1e-12)
        r = ratio / ratio.mean(0, keepdim=True)
        target = r.pow(self.alpha) / grad_norms.clamp_min(GRAD_FLOOR)
        target = len(self.active) * target / target.sum(0, keepdim=True)
        self.w = (1 - self.smoothing) * self.w + self.smoothing * target


def _latent_grad_norms(terms: list[torch.Tensor], latents: list[torch.Tensor]) -> torch.Tensor:
    """(n_terms, B): per sequence, |d term_b / d latents_b| over all latent tensors."""
    B = terms[0].shape[0]
    rows = []
    for term in terms:
        grads = torch.autograd.grad(term.sum(), latents, retain_graph=True, allow_unused=True)
        sq = torch.zeros(B, dtype=torch.float64, device=term.device)
        for g in grads:
            if g is not None:
                sq = sq + g.reshape(B, -1).double().square().sum(1)
        rows.append(sq.sqrt())
    return torch.stack(rows)


def active_terms(adapter, obs: Observation, objective: dict) -> list[str]:
    terms = []
    if obs.points is not None:
        terms.append("dense")
    terms.append("mocap")
    if uses_anchor_decoder(adapter) and objective.get("time_term", True):
        terms.append("time")
    return terms


def sls_start(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, objective: dict, generator, device,
              lr: float, lam: float) -> tuple[FitState, dict]:
    """The start search of ``objective.start_search`` (sls protocol v4, table1's rule of versions 4-5
    with sls's facing): ``limbs``: a per-frame prior searches its limbs per observed anchor
    (:func:`~benchmark.protocols.start_search.limb_start_search`); ``observation``: also, every other
    prior with a motion encoder starts from the prior-free body's limb-searched start (facing +z,
    the data rules' facing), encoded (:func:`~benchmark.protocols.start_search.encoded_start`);
    ``none`` (versions 1-3): ``state`` as it is."""
    rule = str(objective.get("start_search", "none"))
    if rule not in START_SEARCH_RULES:
        raise ValueError(f"sls: unknown objective.start_search {rule!r}; choose one of {', '.join(START_SEARCH_RULES)}")
    start_fit = check_start_fit(str(objective.get("start_fit", "exact")))  # the search's brief fits (as table1's)
    if rule == "none":
        return state, {}
    if rule == "observation" and is_prior_free(adapter):  # its start is the prior-free start, cached per observation
        state, log = prior_free_start(body, batch, generator, device, lr, lam, facing="aligned",
                                      start_fit=search_fit(start_fit, encoded=False))
        state.adapter = adapter
        return state, log
    return searched_start(adapter, body, batch, state, rule, generator, device, lr, lam, facing="aligned", start_fit=start_fit)


def fit_sls(adapter: PriorAdapter, body, obs: Observation, anchor_t: torch.Tensor, steps: int, objective: dict,
            generator: torch.Generator, device, loss_vertices: int | None = None,
            plateau: PlateauRule | None = None, keep_held: bool = True) -> tuple[FitState, dict]:
    """Optimise one batch against its observation (see :mod:`benchmark.protocols.sls`).

    ``plateau``: the step rule of protocol v4 (:class:`~benchmark.protocols.step_rules.PlateauRule`,
    judged on each sequence's unweighted active data terms plus lambda x prior): ``steps`` is then
    the cap. None: ``steps`` steps of cosine decay (versions 1-3).

    ``keep_held``: under ``plateau``, the steps between two updates of the adaptive weights evaluate
    only the sequences still descending (:class:`~benchmark.protocols.kept_rows.KeptRows`; the
    steps that update the weights, which change every sequence's objective, are evaluated whole).
    False evaluates the whole batch at every step (the same fit to float rounding)."""
    lr = float(objective["lr"])
    lam = float(objective["lambda_prior"])
    ad = objective.get("adaptive", {}) or {}
    lr_final = float(objective.get("lr_final_fraction", 0.1))
    B, n = obs.landmarks.shape[:2]
    idx = obs.index.to(device)
    anchor_t = anchor_t.to(device)
    obs_t = obs.timestamps.to(device)
    lm = obs.landmarks.to(device)
    pts = None if obs.points is None else obs.points.to(device)
    cap = objective.get("init_scan_points")
    init_pts = lm if pts is None else torch.cat([pts if cap in (None, "all") else pts[:, :, : int(cap)], lm], dim=2)
    batch = FitBatch(points=init_pts, lengths=torch.full((B, n), init_pts.shape[2], dtype=torch.long, device=device),
                     timestamps=obs_t, window_s=float(anchor_t[:, -1].max()), output_timestamps=anchor_t)
    facing = str(objective.get("facing", "heading8"))
    latent_init = str(objective.get("latent_init", "sample"))  # v3: "mean" (as table1 v3)
    if facing == "search":
        state, _ = facing_search(adapter, body, batch, generator, device, lr, lam, latent_init=latent_init)
    elif facing in ("heading8", "aligned"):  # aligned: start facing +z, as the data rules align every sequence
        state = init_state(adapter, body, batch, generator, device, search_heading=facing == "heading8",
                           latent_init=latent_init)
    else:
        raise ValueError(f"sls: unknown objective.facing {facing!r}; choose heading8 (protocol v1), aligned or search")
    t_search = time.perf_counter()
    state, search_log = sls_start(adapter, body, batch, state, objective, generator, device, lr, lam)
    if search_log:
        search_log = {**search_log, "start_search_s": time.perf_counter() - t_search}
    subset = body.loss_vertex_indices(loss_vertices)
    lm_idx = body.landmark_indices.to(device)
    skin_idx = lm_idx if pts is None else (None if subset is None else torch.cat([subset.to(device), lm_idx]))
    terms_used = active_terms(adapter, obs, objective)
    weights = AdaptiveWeights(terms_used, B, alpha=float(ad.get("alpha", 1.5)), smoothing=float(ad.get("smoothing", 0.5)),
                              every=int(ad.get("every", 10)))
    latents = [v for v in state.latents.values() if v.requires_grad]  # not the constant_latents
    # the observed points never move: their search structures are built once (same values as chamfer_loss)
    dense = None if pts is None else StaticChamfer(pts.flatten(0, 1))

    trace = []  # (B,) the unweighted sum of the active data terms at every step (fit diagnostics)
    objective_trace = []  # (B,) that sum plus lambda x prior at every step: the plateau rule (protocol v4)

    term_trace = []  # (n_terms, B) the unweighted active data terms at every step
    prior_trace = []  # (B,) the prior term at every step
    dense_rows = {}

    def terms_of(st: FitState, rows):
        """The unweighted active terms ((R,) each) and the prior term of the sequences ``rows`` of
        ``st`` (None: the whole batch, ``st`` is ``state``)."""
        pick = (lambda x: x) if rows is None else (lambda x: x.index_select(0, rows))  # noqa: E731
        rot, trans, tau_hat = decode_anchors(st, pick(anchor_t), idx)
        rest = body.prepare(st.shape())
        verts = body.skin(rest, rot, trans, vertex_indices=skin_idx).vertices  # (R, n, K, 3)
        pred_lm = verts[:, :, -lm_idx.numel():] if skin_idx is not None else verts.index_select(2, lm_idx)
        terms = {"mocap": (pred_lm - pick(lm)).square().sum(-1).mean((1, 2)) * MOCAP_SCALE}
        if pts is not None:
            v = verts[:, :, : verts.shape[2] - lm_idx.numel()] if skin_idx is not None else verts
            if rows is None:
                chamfer = dense
            else:
                key = tuple(rows.tolist())
                if key not in dense_rows:
                    dense_rows.clear()
                    dense_rows[key] = dense.select(row_frames(rows, n))
                chamfer = dense_rows[key]
            terms["dense"] = chamfer(v.flatten(0, 1)).view(verts.shape[0], n).mean(1) * DENSE_SCALE
        if "time" in terms_used:
            terms["time"] = (tau_hat.double() - pick(obs_t)).square().mean(1).to(verts.dtype) * TIME_SCALE
        return [terms[k] for k in terms_used], prior_values(adapter, st.latents)

    def record(values, prior):
        trace.append(sum(v.detach() for v in values))
        term_trace.append(torch.stack([v.detach() for v in values]))
        prior_trace.append(prior.detach())
        objective_trace.append(trace[-1] + lam * prior.detach())

    def step_loss(step):
        values, prior = terms_of(state, None)
        record(values, prior)
        if weights.due(step):
            weights.update(torch.stack([v.detach() for v in values]), _latent_grad_norms(values, latents))
        w = weights.w.to(device=device, dtype=values[0].dtype)
        data = sum(w[i] * values[i] for i in range(len(values)))

        def log():
            entry = {"prior": float(prior.detach().mean())}
            for i, k in enumerate(terms_used):
                entry[k] = float(values[i].detach().mean())
                entry[f"w_{k}"] = float(weights.w[i].mean())
            return entry

        return (data + lam * prior).sum(), log

    def rows_loss(step, rows):  # a step between weight updates (whole_at): the rows still descending
        with adapter.batch_rows(rows):
            values, prior = terms_of(state_rows(state, rows), rows)
        record(values, prior)
        w = weights.w[:, rows.cpu()].to(device=device, dtype=values[0].dtype)
        data = sum(w[i] * values[i] for i in range(len(values)))

        def log():  # the traces' last entries, completed to the whole batch (KeptRows.fill)
            entry = {"prior": float(prior_trace[-1].mean())}
            for i, k in enumerate(terms_used):
                entry[k] = float(term_trace[-1][i].mean())
                entry[f"w_{k}"] = float(weights.w[i].mean())
            return entry

        return (data + lam * prior).sum(), log

    def value_of(rows):  # the per-sequence objective at the start (unit weights), for the check
        values, prior = terms_of(state if rows is None else state_rows(state, rows), rows)
        return sum(values) + lam * prior

    params = parameter_groups(state, lr, float(objective.get("shape_lr_scale", 1.0)))  # as table1 v2
    plateau_log = {}
    if plateau is None:
        history = optimise(adapter.name, params, steps, lr, lr_final, step_loss)
    else:
        keep = keep_held and rows_independent(value_of, adapter, B, device)
        history, plateau_log = optimise_to_plateau(adapter.name, params, steps, lr, lr_final, step_loss, objective_trace,
                                                   plateau, rows_loss=rows_loss if keep else None,
                                                   row_traces=(trace, term_trace, prior_trace), whole_at=weights.due)
    return state, {"history": history, "terms": terms_used, "data_trace": torch.stack(trace) if trace else torch.zeros(0, B),
                   "weights": {k: weights.w[i].tolist() for i, k in enumerate(terms_used)}, **search_log,
                   **({"plateau": plateau_log} if plateau_log else {})}
