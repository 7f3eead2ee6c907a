"""``python -m benchmark complete INPUT --prior NAME --out OUT``: apply a prior to one capture.

INPUT is a scan folder (the layout of :mod:`benchmark.loaders.scans`), a harness / AMASS ``.npz``
motion or a BVH. The observation is made under the table1 rules: a motion is scanned like the
table's capture (``capture_fps``, ``points_per_frame`` of ``benchmark/tables/table1.yaml``); a scan
folder is used as captured. Then, as in a table1 cell: the frames nearest in time to ``--fps``
(default 10, table1's densest rate), a seeded random subset of ``--points`` per frame (default:
all of them), one window (``--window``, default table1's 4 s, shorter if the input is), and the
table1 fit (:func:`benchmark.protocols.completion.fit`: objective, initialisation, Adam, the
plateau step rule of table1 v6) with the profile's step cap and loss-vertex subset.

Writes to OUT (a folder):

- ``motion.npz``: the completed motion at 30 fps (poses, trans, shape, timestamps from the window
  start, body), the harness format (``data convert`` reads it back);
- ``meshes/frame_XXXX.ply`` with ``--meshes``: one mesh per output frame;
- ``preview.webp``: an animation, when the report renderer (``benchmark.report``) is installed;
- ``diagnostics.json``: what is printed: the data term's history, convergence, and, where the
  truth is known (a motion input, or a scan folder written by ``data make-scans`` with its
  ``ground_truth/motion.npz``), MPJPE and root-orientation / facing errors;
- ``.benchmark-output.json``: the marker (:func:`benchmark.core.outdir.claim_out_dir`): ``--force``
  replaces only a folder holding it and nothing but the files above.

OUT is checked before anything loads: a writable folder, apart from the input (not the capture
folder, not inside it, not around it), empty or an earlier ``complete``'s output with ``--force``.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

OUTPUT_FPS = 30.0
COMMAND = "complete"
# what complete writes into --out (the marker lists them; --force replaces only these)
OUTPUT_ENTRIES = ("motion.npz", "meshes", "preview.webp", "preview.gif", "diagnostics.json")


def check_complete_args(args) -> tuple[Path, list[str]]:
    """The checks made before anything loads: the input exists; --out is a writable folder apart from
    the input (not the capture folder, inside it or around it: its frames would be mixed with the
    output); a non-empty --out needs --force and must hold only an earlier ``complete``'s output
    (:func:`benchmark.core.outdir.claim_out_dir`). Returns (the folder, the earlier output's entries, to
    be replaced once the fit has succeeded). The numbers are range-checked by the parser."""
    from benchmark.core.outdir import check_not_overlapping, claim_out_dir

    path = Path(args.input)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scan folder or motion file")
    kind = "input scan folder" if path.is_dir() else "input file"
    check_not_overlapping(args.out, [(kind, path)])
    return claim_out_dir(args.out, COMMAND, bool(getattr(args, "force", False)))


def _observation_from_motion(motion, body, spec: dict, window: float, points, fps: float, seed: int):
    from benchmark.data.degrade import degrade
    from benchmark.data.observations import make_scans
    from benchmark.core.work_units import stable_seed

    d = spec["data"]
    scans, _ = make_scans(body, [motion], fps=float(d["capture_fps"]), num_points=int(d["points_per_frame"]),
                          noise_std=float(d.get("scan_noise_std", 0.0)), seed=stable_seed("capture", seed, motion.source),
                          duration=window)
    obs = degrade(scans, points, fps, seed=stable_seed("degrade", seed, points, fps), capture_fps=float(d["capture_fps"]))
    return obs, float(motion.timestamps[0])


def _load_input(path: Path, args, body, spec: dict):
    """(observation, window start in the input's time, window, truth Motion or None, description)."""
    from benchmark.loaders.convert import load_motion
    from benchmark.loaders.scans import ScanSequence
    from benchmark.core.motion import Motion, shape_for_body
    from benchmark.protocols.scan_completion import ScanCompletionData
    from benchmark.core.work_units import stable_seed

    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scan folder or motion file")
    window_spec = float(spec["data"]["window_s"])
    if path.is_dir():
        seq = ScanSequence(path, up=args.up, units=args.units, fps=args.capture_fps, rate_flag="--capture-fps")
        start = args.start
        if not 0 <= start < seq.duration:
            raise ValueError(f"{path}: --start {start} s lies outside the capture ({seq.duration:.3f} s)")
        window = min(window_spec if args.window is None else args.window, seq.duration - start)
        wspec = copy.deepcopy(spec)
        wspec["data"].update(window_s=window, window_start_s=start)
        source = ScanCompletionData(wspec, body, {path.name: seq}, args.seed)
        try:
            obs, offsets = source.observe([path.name], args.points, args.fps,
                                          stable_seed("degrade", args.seed, args.points, args.fps, path.name))
        except ValueError as exc:  # the capture's own limits, said as the options that hit them
            from benchmark.protocols.scan_completion import CellNotServed

            if isinstance(exc, CellNotServed):
                raise ValueError(f"--points {args.points}: {exc}; give fewer points") from None
            if "no distinct frame for every instant" in str(exc):
                raise ValueError(f"--fps {args.fps:g}: {exc}; give a lower --fps") from None
            raise
        t_start = float(obs.timestamps[0, 0])
        truth_file = path / "ground_truth" / "motion.npz"
        truth = shape_for_body(Motion.load(truth_file), body, str(truth_file)) if truth_file.is_file() else None
        what = (f"scan folder {path}: {len(seq.frames)} frames at {seq.capture_fps:.4g} fps; observed "
                f"{obs.num_frames} frames (largest offset from the nominal instants {1000 * offsets[0]:.1f} ms)")
        return obs, t_start, window, truth, what
    if args.up != "y" or args.units != "m":
        raise ValueError("--up / --units apply to scan folders; motion files are converted by their loaders")
    motion = shape_for_body(load_motion(path), body, str(path))
    if not 0 <= args.start < motion.duration:
        raise ValueError(f"{path}: --start {args.start} s lies outside the motion ({motion.duration:.3f} s)")
    if args.start:
        motion = motion.window(float(motion.timestamps[0]) + args.start, motion.duration - args.start)
    # the capture samples the motion from its first frame: a 120-frame 30 fps motion (4.0 s) serves a
    # 50 fps capture up to its last frame, 3.967 s: 199 capture frames, a window of 3.98 s, not 4 s
    capture_fps = float(spec["data"]["capture_fps"])
    captured = (math.floor(motion.span * capture_fps + 1e-6) + 1) / capture_fps
    window = min(window_spec if args.window is None else args.window, motion.duration, captured)
    obs, t_start = _observation_from_motion(motion, body, spec, window, args.points, args.fps, args.seed)
    what = (f"motion {path} ({motion.num_frames} frames at {motion.fps:.4g} fps), scanned at "
            f"{spec['data']['capture_fps']} fps x {spec['data']['points_per_frame']} points; observed {obs.num_frames} frames")
    return obs, t_start, window, motion, what


def truth_diagnostics(body, rot, output, truth, abs_t: torch.Tensor) -> dict:
    """MPJPE, root-orientation and facing errors of the output against the truth (degrees, mm), the
    figures of :func:`benchmark.core.fit_diagnostics.root_errors`."""
    import roma

    from benchmark.core.fit_diagnostics import BACKWARDS_DEG, root_errors
    from benchmark.data.observations import ground_truth_at

    gt = ground_truth_at(body, [truth], abs_t[None].to(torch.float64))
    mpjpe = (output.joints[0].cpu() - gt.joints[0].cpu().to(output.joints.dtype)).norm(dim=-1).mean()
    R_gt = roma.rotvec_to_rotmat(truth.resample(abs_t).poses[:, 0].double())
    geo, facing = root_errors(rot[0, :, 0].detach().cpu().double().numpy(), R_gt.numpy())
    return {"mpjpe_mm": float(mpjpe) * 1000.0, "root_orientation_err_deg_mean": float(geo.mean()),
            "facing_err_deg_mean": float(facing.mean()), "facing_err_deg_max": float(facing.max()),
            "frames_facing_backwards": int((facing > BACKWARDS_DEG).sum())}


def convergence(history: list[dict], data_trace, plateau: dict | None = None) -> dict:
    """The data term's first and last values and the fit's convergence: under table1's plateau rule
    (protocol v6, ``plateau``: the fit's log) its verdict, the steps taken and the objective's change
    over the rule's window; else the versions 1-5 figure
    (:func:`benchmark.core.fit_diagnostics.convergence`)."""
    from benchmark.core.fit_diagnostics import CONVERGED_MAX_DECREASE, CONVERGENCE_WINDOW
    from benchmark.core.fit_diagnostics import convergence as decrease

    trace = [float(v) for v in data_trace[:, 0]]
    rel = decrease(trace)
    out = {"data_mm_first": history[0]["data_mm"], "data_mm_last": history[-1]["data_mm"],
           "data_decrease_last10": rel if math.isfinite(rel) else None,
           "window_steps": max(1, math.ceil(CONVERGENCE_WINDOW * len(trace))),
           "converged": bool(math.isfinite(rel) and rel <= CONVERGED_MAX_DECREASE)}
    if plateau is not None:
        out.update(rule="plateau", converged=bool(plateau["converged"][0]), steps=int(plateau["steps"]),
                   plateau_decrease=plateau["plateau_decrease"][0])
    return out


def _preview(out: Path, output, truth_vertices, body, out_t, obs) -> str:
    """Render the preview with the report's renderer if it exists; the message says what happened."""
    try:
        from benchmark.report.animate import SequenceMotion, animate
    except ImportError as exc:
        return f"preview skipped: the report renderer (benchmark.report.animate) is not available ({exc})"
    try:
        fit_v = output.vertices[0].cpu().numpy()
        fit_j = output.joints[0].cpu().numpy()
        zeros = np.zeros(len(out_t))
        motion = SequenceMotion(
            sequence_id="complete", t=out_t.numpy(), fit_vertices=fit_v, fit_joints=fit_j,
            gt_vertices=fit_v if truth_vertices is None else truth_vertices, gt_joints=fit_j,
            root_err_deg=zeros, facing_err_deg=zeros, obs_t=obs.timestamps[0].numpy() - float(obs.timestamps[0, 0]),
            obs_points=obs.points[0].numpy(), obs_lengths=obs.lengths[0].numpy())
        path = animate(motion, body, out / "preview.webp", title="complete")
        return f"preview: {path}"
    except Exception as exc:  # the renderer is optional; its failure must not lose the fit
        return f"preview failed ({type(exc).__name__}: {exc}); the motion and meshes are written"


def run_complete(args) -> dict:
    """``complete``: the checks, then the fit and its outputs (:func:`_complete`); a folder this run
    created for ``--out`` and left empty (it failed before writing) is removed."""
    t_begin = time.perf_counter()
    created = not Path(args.out).expanduser().exists()
    out, earlier = check_complete_args(args)
    try:
        return _complete(args, out, earlier, t_begin)
    except BaseException:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # made for this run, which wrote nothing: not left behind
        raise


def _complete(args, out: Path, earlier: list[str], t_begin: float) -> dict:
    import roma

    from benchmark.body import get_body
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.core.motion import Motion
    from benchmark.protocols.completion import decode_output, fit, observation_batch
    from benchmark.protocols.completion_unit import latent_init_rule, loss_vertex_count, start_fit_rule, start_search_rule
    from benchmark.protocols.step_rules import plateau_rule
    from benchmark.run.registry import make_adapter
    from benchmark.synthetic.scan_set import write_ply_mesh

    spec = load_table_spec("table1")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    profile_name = args.profile or ("full" if device.startswith("cuda") else "quick")
    profile = get_profile(profile_name, table="table1")
    steps = int(profile["steps"] if args.steps is None else args.steps)
    if steps < 1:
        raise ValueError(f"--steps {steps}: the fit needs at least 1 step")
    body = get_body(args.body, device=device)
    obs, t_start, window, truth, what = _load_input(Path(args.input), args, body, spec)
    print(what)
    n_out = int(round(window * OUTPUT_FPS))
    out_t = torch.arange(n_out, dtype=torch.float64) / OUTPUT_FPS
    batch = observation_batch(obs, window, out_t[None], device)
    adapter = make_adapter(args.prior, size=args.size, weights=args.weights, device=device)
    obj = spec["objective"]
    print(f"fitting {args.prior} ({args.size}) under the table1 rules: {batch.num_observed} observed frames, "
          f"up to {int(batch.lengths.max())} points each, window {window:g} s, profile {profile_name!r} "
          f"({steps} steps, loss vertices {profile.get('loss_vertices', 'all')}), device {device}")
    t0 = time.perf_counter()
    state, info = fit(adapter, body, batch, steps=steps, lr=float(obj["lr"]), lambda_prior=float(obj["lambda_prior"]),
                      generator=torch.Generator().manual_seed(args.seed), device=device,
                      loss_vertices=loss_vertex_count(profile), facing=args.facing,
                      shape_lr_scale=float(obj.get("shape_lr_scale", 1.0)), latent_init=latent_init_rule(spec),
                      start_search=start_search_rule(spec), plateau=plateau_rule(spec), start_fit=start_fit_rule(spec))
    fit_s = time.perf_counter() - t0
    output, rot, trans = decode_output(state, body, batch.output_timestamps)

    # the fit is done: an earlier complete's files in --out (checked at the start) are replaced now
    from benchmark.core.outdir import remove_entries, write_marker

    out.mkdir(parents=True, exist_ok=True)
    remove_entries(out, earlier)
    write_marker(out, COMMAND, OUTPUT_ENTRIES)
    shape = state.shape()[0].detach().cpu()
    motion = Motion(poses=roma.rotmat_to_rotvec(rot[0].cpu().double()).float(), trans=trans[0].cpu(), timestamps=out_t,
                    shape=shape, body=body.name, source=f"complete:{args.prior}:{args.input}",
                    meta={"prior": args.prior, "size": args.size, "input": str(args.input), "window_start_s": t_start,
                          "points": args.points, "fps": args.fps, "profile": profile_name, "steps": steps,
                          "seed": args.seed, "table": "table1", "protocol_version": spec["protocol_version"]})
    motion_path = motion.save(out / "motion.npz")
    print(f"wrote {motion_path}: {n_out} frames at {OUTPUT_FPS:g} fps (timestamps from the window start)")
    if args.meshes:
        mesh_dir = out / "meshes"
        mesh_dir.mkdir(exist_ok=True)
        faces = body.faces.cpu().numpy()
        for t in range(n_out):
            write_ply_mesh(mesh_dir / f"frame_{t:04d}.ply", output.vertices[0, t].cpu().numpy(), faces)
        print(f"wrote {n_out} meshes to {mesh_dir}/")

    history = info["history"]
    diag = {"input": str(args.input), "prior": args.prior, "fit_s": fit_s, "history": history,
            "convergence": convergence(history, info["data_trace"], info.get("plateau"))}
    print("data term (Chamfer, mm, on the loss vertices) by step: "
          + ", ".join(f"{h['step']}: {h['data_mm']:.2f}" for h in history))
    c = diag["convergence"]
    if c.get("rule") == "plateau":
        change = c["plateau_decrease"]
        shown = "n/a (the cap is below the rule's least steps)" if change is None else f"{100 * change:.2f}%"
        print(f"convergence: {c['data_mm_first']:.2f} -> {c['data_mm_last']:.2f} mm in {c['steps']} steps; objective "
              f"change over the plateau window at the fit's last (reduced) learning rate {shown} "
              f"({'converged' if c['converged'] else 'not converged within the step cap: raise it (--steps, --profile full)'})")
    elif c["data_decrease_last10"] is None:
        print(f"convergence: {c['data_mm_first']:.2f} -> {c['data_mm_last']:.2f} mm; one step: nothing to judge "
              "convergence by (not converged)")
    else:
        print(f"convergence: {c['data_mm_first']:.2f} -> {c['data_mm_last']:.2f} mm; decrease over the last "
              f"{c['window_steps']} steps {100 * c['data_decrease_last10']:.2f}% "
              f"({'converged' if c['converged'] else 'still decreasing: more steps (--steps, --profile full) may help'})")
    truth_vertices = None
    if truth is not None:
        abs_t = out_t + t_start
        if float(abs_t[-1]) > float(truth.timestamps[-1]) + 1e-6 or float(abs_t[0]) < float(truth.timestamps[0]) - 1e-6:
            print("ground truth: does not cover the output window; no errors against it")
        else:
            d = truth_diagnostics(body, rot, output, truth, abs_t)
            diag["truth"] = d
            print(f"against the ground truth: MPJPE {d['mpjpe_mm']:.1f} mm; root orientation error "
                  f"{d['root_orientation_err_deg_mean']:.1f} deg (mean); facing error {d['facing_err_deg_mean']:.1f} deg "
                  f"(mean), {d['facing_err_deg_max']:.1f} deg (max), {d['frames_facing_backwards']} of {n_out} frames "
                  "facing backwards")
    else:
        print("no ground truth: MPJPE and facing errors are not computed")
    message = _preview(out, output, truth_vertices, body, out_t, obs) if not args.no_preview else "preview: not asked"
    print(message)
    diag["preview"] = message
    diag["wall_s"] = time.perf_counter() - t_begin
    (out / "diagnostics.json").write_text(json.dumps(diag, indent=2))
    write_marker(out, COMMAND, OUTPUT_ENTRIES, files=True)  # the meshes it wrote: a later --force replaces only them
    print(f"done in {diag['wall_s']:.1f} s (fit {fit_s:.1f} s); diagnostics: {out / 'diagnostics.json'}")
    return diag
