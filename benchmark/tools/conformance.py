"""The conformance kit: ``python -m benchmark check-prior NAME``.

Runs an adapter through a tiny completion table (one short sequence of smooth motion, two cells,
a few optimiser steps) and reports pass/fail per check: the adapter's declaration, latent shapes,
decode shapes, finite losses, gradients reaching the latents, determinism under a seed,
decoding at arbitrary timestamps where the adapter claims it (continuous priors), and sequences
that do not depend on each other (:meth:`priors.base.PriorAdapter.batch_rows`).
"""

from __future__ import annotations

import math
import logging

import roma
import torch

from benchmark.data.observations import PointCloudSequence
from benchmark.core.skeleton import NUM_JOINTS
from benchmark.core.surface_sampling import sample_surface

log = logging.getLogger(__name__)

CELLS = ({"points": 100, "fps": 5}, {"points": 1000, "fps": 10})


def toy_observation(body, duration: float = 2.0, capture_fps: float = 10.0, points: int = 1000, seed: int = 0):
    """One sequence of smooth synthetic motion (small sinusoidal joint rotations, slow walk forward)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(int(round(duration * capture_fps)), dtype=torch.float64) / capture_fps
    amp = torch.rand(NUM_JOINTS, 3, generator=g) * 0.3
    phase = torch.rand(NUM_JOINTS, 3, generator=g) * 2 * math.pi
    aa = amp * torch.sin(2 * math.pi * 1.0 * t[:, None, None].float() + phase)
    rot = roma.rotvec_to_rotmat(aa)[None]  # (1, T, 22, 3, 3)
    trans = torch.zeros(1, len(t), 3)
    trans[0, :, 2] = 0.8 * t.float()
    with torch.no_grad():
        out = body(rot, trans)
        pts = sample_surface(out.vertices, body.faces, points, g)
    T = len(t)
    return PointCloudSequence(points=pts, lengths=torch.full((1, T), points, dtype=torch.long),
                              timestamps=t[None].clone(), frame_mask=torch.ones(1, T, dtype=torch.bool))


class _Report:
    def __init__(self):
        self.rows = []

    def check(self, name, fn):
        try:
            detail = fn()
            self.rows.append((name, True, detail or ""))
            return True
        except Exception as exc:  # a failing check is a row, not a crash
            self.rows.append((name, False, f"{type(exc).__name__}: {exc}"))
            log.debug("check %s failed", name, exc_info=True)
            return False

    def print(self):
        width = max(len(r[0]) for r in self.rows)
        for name, ok, detail in self.rows:
            print(f"  [{'PASS' if ok else 'FAIL'}] {name.ljust(width)}  {detail}")

    @property
    def ok(self):
        return all(r[1] for r in self.rows)


def check_prior(name: str, size: str = "embedded", weights: str | None = None, steps: int = 5, verbose: bool = True) -> bool:
    from benchmark.body import get_body
    from benchmark.run.registry import make_adapter
    from benchmark.data.degrade import degrade
    from benchmark.protocols.completion import fit, observation_batch
    from benchmark.protocols.fit_state import body_parameters, init_state
    from benchmark.protocols.latent_checks import check_latents, prior_values
    from priors.base import MotionEncoder, PriorAdapter, interfaces_of

    rep = _Report()
    ctx = {}

    def load():
        ctx["adapter"] = make_adapter(name, size=size, weights=weights)
        a = ctx["adapter"]
        if not isinstance(a, PriorAdapter):
            raise TypeError(f"{type(a).__name__} does not subclass priors.base.PriorAdapter")
        return f"{type(a).__name__}, window {a.window.kind}, {a.parameter_count():,} parameters"

    if not rep.check("instantiate", load):
        rep.print()
        return False
    a = ctx["adapter"]
    body = get_body("anny")
    scans = toy_observation(body)
    window_s = 2.0
    out_t = (torch.arange(60, dtype=torch.float64) / 30.0)[None]

    def declaration():
        if a.window.kind not in ("per-frame", "fixed", "continuous"):
            raise ValueError(f"window.kind {a.window.kind!r}")
        if a.window.kind == "fixed" and not (a.window.frames and a.window.fps):
            raise ValueError("fixed windows need frames and fps")
        if not a.name or a.name == "prior":
            raise ValueError("set a registry name")
        if a.name != name:
            raise ValueError(f"name = {a.name!r}, but the prior is registered as {name!r} (its entry point): set "
                             f"name = {name!r} in the adapter class (errors and logs name it by its name)")
        if a.has_encoder and not isinstance(a, MotionEncoder):
            raise ValueError("has_encoder is True but the adapter is not a priors.base.MotionEncoder (encode_motion)")
        return (f"translation={a.encodes_translation} root={a.encodes_root_orientation} heading_normalised={a.heading_normalised}"
                f" interfaces: {', '.join(interfaces_of(a)) or 'none'}")

    rep.check("declaration", declaration)

    for cell in CELLS:
        obs = degrade(scans, cell["points"], cell["fps"], seed=1)
        batch = observation_batch(obs, window_s, out_t, "cpu")
        label = f"{cell['points']} pts / {cell['fps']} fps"

        def latents():
            lat = a.init_latents(batch, torch.Generator().manual_seed(0))
            for k, v in lat.items():
                if v.shape[0] != batch.batch_size:
                    raise ValueError(f"latent {k!r} has batch {v.shape[0]}, expected {batch.batch_size}")
                if not torch.isfinite(v).all():
                    raise ValueError(f"latent {k!r} is not finite")
            return ", ".join(f"{k} {tuple(v.shape)}" for k, v in lat.items())

        rep.check(f"{label}: init_latents shapes", latents)

        def mean_latents():
            mean = a.mean_latents(batch)
            if mean is None:
                return "none: init_latents is the start (deterministic)"
            check_latents(a, mean, a.init_latents(batch, torch.Generator().manual_seed(0)), "mean_latents")
            return "init_latents' keys and shapes"

        rep.check(f"{label}: mean_latents", mean_latents)

        if isinstance(a, MotionEncoder):
            def encoder():
                # what the table1 starts encode: a per-frame prior the motion at the observed frames
                # (every latent, their shapes), a window prior the motion at the output frames
                st = init_state(a, body, batch, torch.Generator().manual_seed(0), "cpu")
                per_frame = a.window.kind == "per-frame"
                t = batch.timestamps if per_frame else batch.output_timestamps
                with torch.no_grad():
                    rot, tr = body_parameters(st, t, observed=per_frame)
                    enc = a.encode_motion(rot, tr, t)
                check_latents(a, enc, st.latents, "encode_motion", partial=not per_frame, shapes=per_frame, extra=True)
                n = batch.num_observed
                whole = sorted(k for k, v in st.latents.items() if v.dim() < 2 or v.shape[1] != n)
                if per_frame and whole:  # table1's limb start search picks every latent frame by frame
                    raise ValueError(f"latents {whole} are not per observed frame ((B, {n}, ...)): a per-frame prior "
                                     "with encode_motion gets table1's limb start search, which chooses every latent "
                                     "frame by frame; make each latent per observed frame along dimension 1")
                return ", ".join(f"{k} {tuple(v.shape)}" for k, v in enc.items())

            rep.check(f"{label}: encode_motion keys", encoder)

        def decode_shapes():
            st = init_state(a, body, batch, torch.Generator().manual_seed(0), "cpu")
            rot, tr = body_parameters(st, batch.output_timestamps)
            if rot.shape != (1, out_t.shape[1], 22, 3, 3) or tr.shape != (1, out_t.shape[1], 3):
                raise ValueError(f"rotations {tuple(rot.shape)}, translation {tuple(tr.shape)}")
            orth = (rot.transpose(-1, -2) @ rot - torch.eye(3)).abs().max()
            if orth > 1e-4:
                raise ValueError(f"rotations not orthonormal (max error {orth:.2e})")
            return f"rotations {tuple(rot.shape)}"

        rep.check(f"{label}: decode at output timestamps", decode_shapes)

        def gradients(latent_init="sample"):
            st = init_state(a, body, batch, torch.Generator().manual_seed(0), "cpu", latent_init=latent_init)
            rot, tr = body_parameters(st, batch.timestamps, observed=True)
            verts = body.skin(body.prepare(st.shape()), rot, tr).vertices
            from benchmark.metrics.chamfer import chamfer_loss

            # the data term alone: a prior term reaches the latents even when the decoder ignores them
            data = chamfer_loss(verts.flatten(0, 1), batch.points.flatten(0, 1), b_lengths=batch.lengths.flatten()).sum()
            data.backward()
            constant = set(a.constant_latents)  # e.g. the window length a decoder reads
            free = {k: v for k, v in st.latents.items() if k not in constant}
            where = "init_latents" if latent_init == "sample" else "mean_latents (table1's start)"
            bad = [k for k, v in free.items() if v.grad is not None and not torch.isfinite(v.grad).all()]
            if bad:
                raise ValueError(f"the data term's gradient at {where} is NaN or inf for latents {bad}: decode's "
                                 "backward is not finite there (e.g. a norm or sqrt at 0); the fit would turn them NaN")
            dead = [k for k, v in free.items() if v.grad is None or v.grad.abs().sum() == 0]
            if dead and latent_init == "sample":  # (a mean start may be a stationary point)
                raise ValueError(f"the decoded motion does not depend on latents {dead}: no finite non-zero gradient "
                                 "of the data term reaches them (does decode() read them, without detaching?)")
            for v in free.values():
                v.grad = None
            prior = prior_values(a, st.latents).sum()
            if not torch.isfinite(prior):
                raise ValueError(f"prior term is {prior.item()}")
            if prior.requires_grad:
                prior.backward()
            grads = [v.grad for v in free.values() if v.grad is not None]
            if any(not torch.isfinite(g).all() for g in grads):
                raise ValueError(f"prior_term's gradient at {where} is NaN or inf (e.g. a norm or sqrt at 0, where "
                                 "the start is): the fit's first step would turn the latents NaN")
            if prior.item() != 0.0 and not grads:
                raise ValueError(f"prior_term is {prior.item():.4g} but no gradient of it reaches the latents (computed "
                                 "from detached latents, .item() or numpy?): the fit would add a constant, i.e. fit "
                                 "with no prior at all")
            return ("the data term's and prior term's gradients reach every latent, finite" if latent_init == "sample"
                    else "finite gradients of the data and prior terms")

        rep.check(f"{label}: gradients reach the latents", gradients)
        if a.mean_latents(batch) is not None:
            rep.check(f"{label}: gradients at mean_latents", lambda: gradients("mean"))

        def decode_depends_on_latents():
            st = init_state(a, body, batch, torch.Generator().manual_seed(0), "cpu")
            constant = set(a.constant_latents)
            with torch.no_grad():
                rot0, tr0 = body_parameters(st, batch.output_timestamps)
                g = torch.Generator().manual_seed(1)
                for k, v in st.latents.items():
                    if k in constant:
                        continue
                    saved = v.detach().clone()
                    v.add_(0.1 * torch.randn(v.shape, generator=g, dtype=v.dtype).to(v.device))
                    rot1, tr1 = body_parameters(st, batch.output_timestamps)
                    v.copy_(saved)
                    moved = max((rot1 - rot0).abs().max().item(), (tr1 - tr0).abs().max().item())
                    if not moved > 1e-6:
                        raise ValueError(f"moving latent {k!r} by 0.1 (per element) leaves the decoded motion unchanged "
                                         f"(largest change {moved:.1e}): decode() must depend on it")
            return "moving any latent moves the decoded motion"

        rep.check(f"{label}: decoded motion depends on the latents", decode_depends_on_latents)

        def finite_and_deterministic():
            runs = []
            for _ in range(2):
                st, info = fit(a, body, batch, steps=steps, lr=0.03, lambda_prior=0.01, loss_vertices=1500,
                               generator=torch.Generator().manual_seed(0), device="cpu")
                for h in info["history"]:
                    if not math.isfinite(h["data_mm"]) or not math.isfinite(h["prior"]):
                        raise ValueError(f"non-finite loss {h}")
                rot, _ = body_parameters(st, batch.output_timestamps)
                orth = (rot.transpose(-1, -2) @ rot - torch.eye(3)).abs().max()
                if orth > 1e-4:  # a decoder that is orthonormal at its start only (raw matrices as latents)
                    raise ValueError(f"after {steps} steps decode's rotations are not orthonormal (max error "
                                     f"{orth:.2e}): decode through a rotation map, e.g. sixd_to_matrix")
                runs.append((rot.detach(), info["history"][-1]["data_mm"]))
            diff = (runs[0][0] - runs[1][0]).abs().max().item()
            if diff > 1e-5:
                raise ValueError(f"two fits under the same seed differ by {diff:.2e}")
            return f"{steps} steps, final data term {runs[0][1]:.1f} mm, repeat identical"

        rep.check(f"{label}: finite losses, determinism under a seed", finite_and_deterministic)

    if a.window.kind == "continuous":
        def arbitrary():
            st = init_state(a, body, batch, torch.Generator().manual_seed(0), "cpu")
            ts = torch.tensor([[0.0, 0.0137, 0.5, 1.234, 1.999]], dtype=torch.float64)
            rot, _ = body_parameters(st, ts)
            if rot.shape[1] != 5:
                raise ValueError(f"asked 5 timestamps, got {rot.shape[1]}")
            return "decodes at 5 irregular timestamps"

        rep.check("decode at arbitrary timestamps", arbitrary)

    def independent():
        # two sequences (the toy motion at two degradations): each one's decoded motion and prior
        # term, evaluated alone inside batch_rows, are what the pair gives it
        from benchmark.protocols.fit_state import batch_rows, state_rows

        obs = [degrade(scans, 100, 5, seed=s) for s in (1, 2)]
        pair = observation_batch(PointCloudSequence(points=torch.cat([o.points for o in obs]),
                                                    lengths=torch.cat([o.lengths for o in obs]),
                                                    timestamps=torch.cat([o.timestamps for o in obs]),
                                                    frame_mask=torch.cat([o.frame_mask for o in obs])),
                                 window_s, out_t.expand(2, -1), "cpu")
        st = init_state(a, body, pair, torch.Generator().manual_seed(0), "cpu")
        with torch.no_grad():
            for v in st.latents.values():  # away from the start, where a prior term may be zero for any batch
                if v.requires_grad:  # not the constant_latents
                    v.add_(0.05)
            rot, tr = body_parameters(st, pair.output_timestamps)
            prior = prior_values(a, st.latents)
            for i in range(2):
                rows = torch.tensor([i])
                try:
                    with a.batch_rows(rows):
                        one = state_rows(st, rows)
                        rot1, tr1 = body_parameters(one, batch_rows(pair, rows).output_timestamps)
                        prior1 = a.prior_term(one.latents)
                except (ValueError, RuntimeError) as err:
                    raise ValueError(f"sequence {i} of a batch of two cannot be decoded alone ({err}); an adapter that "
                                     "keeps per-batch tensors selects their rows in batch_rows(rows)") from err
                moved = max(float((rot1 - rot[i:i + 1]).abs().max()), float((tr1 - tr[i:i + 1]).abs().max()),
                            float((prior1 - prior[i:i + 1]).abs().max() / prior[i].abs().clamp_min(1.0)))
                if moved > 1e-4:
                    raise ValueError(f"sequence {i} decoded alone differs from the same sequence in a batch of two by "
                                     f"{moved:.1e}: decode and prior_term must treat sequences independently, and an "
                                     "adapter that keeps per-batch tensors selects their rows in batch_rows(rows)")
        return "each sequence alone (batch_rows) is what the batch gives it"

    rep.check("sequences independent", independent)

    if verbose:
        print(f"check-prior {name} ({size}):")
        rep.print()
        print("PASS" if rep.ok else "FAIL")
    return rep.ok
