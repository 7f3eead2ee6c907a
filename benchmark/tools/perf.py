"""``python -m benchmark perf``: speed of the hot paths, measured side by side in one run.

Reports ratios between implementations measured in the same process, on the same inputs (never
absolute targets checked against another machine's numbers), prints one markdown table and writes
it with a JSON of every figure to ``--out`` (``perf.md`` and ``perf.json``):

- the project's Chamfer loss (forward + backward, the fixed observed points' search grids built
  once and the vertices moved between calls, as in a fit) and metric against scipy ``cKDTree``
  (``workers=1``) and pykdtree used directly (both trees built per call), at 100 / 1,000 / 10,000
  points against 3,000 and 13,718 vertices;
- the evaluation's scan -> surface distance (and the exact point -> surface distance) against its
  reference implementation, ``trimesh.proximity`` and libigl where installed;
- the whole per-frame evaluation (every table1 metric) against its reference implementation;
- body skinning frames/s;
- seconds per Adam step of the completion fit in each table1 cell (quick profile, ``no-prior``);
- on CUDA, the tiled Chamfer path against ``torch.cdist``, with peak memory.

CPU comparisons run on one thread (torch and pykdtree), the baselines' own setting, and are timed
in CPU seconds of the process (``time.process_time``), so that other jobs on the machine do not
enter the figures (they still share caches and memory bandwidth).
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

import numpy as np
import torch


from benchmark.tools.perf_clock import CLOCK, timeit
from benchmark.tools.perf_plateau import cell_batch, format_plateau, plateau_descent_compare, quick_unit
from benchmark.tools.perf_skinning import skinning_perf, subset_skinning


# ----------------------------------------------------------------------------- Chamfer


def _baseline_loss(a: torch.Tensor, b: torch.Tensor, tree_cls, query) -> torch.Tensor:
    """What a user would write: per frame, a tree on each set, both queries, the matched pairs'
    Euclidean distances in torch (so the loss has a gradient); sum over frames."""
    a_np = a.detach().double().numpy()
    b_np = b.double().numpy()
    total = a.new_zeros(())
    for n in range(a.shape[0]):
        i_ab = torch.from_numpy(np.asarray(query(tree_cls(b_np[n]), a_np[n]), dtype=np.int64))
        i_ba = torch.from_numpy(np.asarray(query(tree_cls(a_np[n]), b_np[n]), dtype=np.int64))
        d_ab = (a[n] - b[n][i_ab]).square().sum(-1).clamp_min(1e-12).sqrt().mean()
        d_ba = (b[n] - a[n][i_ba]).square().sum(-1).clamp_min(1e-12).sqrt().mean()
        total = total + 0.5 * (d_ab + d_ba)
    return total


def _baseline_metric(a: torch.Tensor, b: torch.Tensor, tree_cls, query_dist) -> list[float]:
    a_np, b_np = a.double().numpy(), b.double().numpy()
    return [0.5 * (query_dist(tree_cls(b_np[n]), a_np[n]).mean() + query_dist(tree_cls(a_np[n]), b_np[n]).mean())
            for n in range(a.shape[0])]


def chamfer_compare(frames: int = 4, points=(100, 1000, 10000), vertices=(3000, 13718), repeats: int = 3,
                    seed: int = 0) -> list[dict]:
    """ms per frame of the Chamfer loss (forward + backward) and metric, project vs scipy cKDTree
    (workers=1) vs pykdtree, on body-sized ellipsoid clouds (``a`` the vertices, ``b`` the points)."""
    from scipy.spatial import cKDTree

    from benchmark.metrics.chamfer import chamfer_distance, chamfer_loss, pykdtree_class
    from benchmark.metrics.static_chamfer import StaticChamfer
    from benchmark.metrics.perf import synthetic_pair

    kd = pykdtree_class()
    rows = []
    for n_vertices in vertices:
        for n_points in points:
            a, b = synthetic_pair(frames, n_points, n_vertices, torch.device("cpu"), seed)
            static = StaticChamfer(b)
            # Each timed call sees the vertices moved, as an optimiser step moves them (a 5 mm shift
            # and 2 mm per vertex from the base): the previous call's neighbours, which start each
            # search, are near but not the answers. The first (untimed) call fills the caches.
            g = torch.Generator().manual_seed(seed + 1)
            moves = [(a.detach() + 0.005 * torch.randn(frames, 1, 3, generator=g)
                      + 0.002 * torch.randn(a.shape, generator=g)).requires_grad_(True) for _ in range(8)]
            step = [0]

            def project_loss():
                x = moves[step[0] % len(moves)]
                step[0] += 1
                x.grad = None
                static(x).sum().backward()

            def scipy_loss():
                a.grad = None
                _baseline_loss(a, b, cKDTree, lambda t, q: t.query(q, workers=1)[1]).backward()

            row = {"vertices": n_vertices, "points": n_points, "frames": frames}
            row["loss_project_ms"] = 1e3 * timeit(project_loss, repeats) / frames
            row["loss_ckdtree_ms"] = 1e3 * timeit(scipy_loss, repeats) / frames
            row["metric_project_ms"] = 1e3 * timeit(lambda: chamfer_distance(a.detach(), b), repeats) / frames
            row["metric_ckdtree_ms"] = 1e3 * timeit(
                lambda: _baseline_metric(a.detach(), b, cKDTree, lambda t, q: t.query(q, workers=1)[0]), repeats) / frames
            if kd is not None:
                def pyk_loss():
                    a.grad = None
                    _baseline_loss(a, b, kd, lambda t, q: t.query(q)[1]).backward()

                row["loss_pykdtree_ms"] = 1e3 * timeit(pyk_loss, repeats) / frames
                row["metric_pykdtree_ms"] = 1e3 * timeit(
                    lambda: _baseline_metric(a.detach(), b, kd, lambda t, q: t.query(q)[0]), repeats) / frames
            with torch.no_grad():
                ref = chamfer_loss(a, b, backend="scipy")
                row["loss_max_abs_diff_m"] = float((static(a) - ref).abs().max())
            for kind in ("loss", "metric"):
                for base in ("ckdtree", "pykdtree"):
                    if f"{kind}_{base}_ms" in row:
                        row[f"{kind}_vs_{base}"] = row[f"{kind}_project_ms"] / row[f"{kind}_{base}_ms"]
            rows.append(row)
    return rows


# ----------------------------------------------------------------------------- point -> surface


def _posed_mesh(body, seed: int = 0):
    """One posed output mesh (float32 vertices) and a 10,000-point scan of a slightly different
    pose (the ground truth), as an evaluation sees them."""
    import roma

    from benchmark.core.surface_sampling import sample_surface

    g = torch.Generator().manual_seed(seed)
    shape = body.default_shape(1)
    rest = body.prepare(shape)
    rot = roma.rotvec_to_rotmat(torch.randn(1, 2, 22, 3, generator=g) * 0.15)
    rot2 = roma.rotvec_to_rotmat(roma.rotmat_to_rotvec(rot) + torch.randn(1, 2, 22, 3, generator=g) * 0.05)
    with torch.no_grad():
        out = body.skin(rest, rot, torch.zeros(1, 2, 3))
        gt = body.skin(rest, rot2, torch.full((1, 2, 3), 0.01))
        scan = sample_surface(gt.vertices, body.faces, 10000, g)
    return out, gt, scan


def surface_compare(n_points: int = 2000, slow_points: int = 200, repeats: int = 3) -> dict:
    """ms per frame of the scan -> surface distance of ``n_points`` scan points to a 13,718-vertex
    body mesh: the evaluation's path (triangles of the 8 nearest vertices, mesh tree included)
    vs its reference implementation, the project's exact distance
    (:func:`benchmark.metrics.surface.points_to_surface_distance`), ``trimesh.proximity`` (on
    ``slow_points`` points, scaled) and libigl (where installed)."""
    from benchmark.body.anny_body import load_anny_body
    from benchmark.metrics.chamfer import build_tree, query_tree
    from benchmark.metrics.surface import points_to_surface_distance
    from benchmark.protocols.completion_unit import (SURFACE_K, incident_faces, scan_to_surface_distance,
                                                     scan_to_surface_frame)

    body = load_anny_body("cpu")
    out, _, scan = _posed_mesh(body)
    verts = out.vertices[0, 0].float()
    pts = scan[0, 0, :n_points].float()
    faces = body.faces.cpu()
    vf = incident_faces(faces, verts.shape[0])
    vf_np, faces_np = vf.numpy(), np.ascontiguousarray(faces.numpy(), dtype=np.int64)

    def project():
        tree = build_tree(verts.double().numpy())
        d, nn = query_tree(tree, pts.double().numpy(), k=SURFACE_K)
        vd = (pts - verts[nn[:, 0]]).norm(dim=-1)
        return scan_to_surface_frame(pts, verts, faces_np, vf_np, nn, vd)

    def reference():
        from benchmark.metrics.chamfer import nearest_neighbors

        vd, _ = nearest_neighbors(pts[None], verts[None], backend="scipy")
        return scan_to_surface_distance(pts[None], verts[None], faces, vd)[0]

    v64, p64, f64 = verts.double().numpy(), pts.double().numpy(), faces.numpy()
    res = {"points": n_points, "vertices": int(verts.shape[0]), "faces": int(faces.shape[0])}
    res["eval_project_ms"] = 1e3 * timeit(project, repeats)
    res["eval_reference_ms"] = 1e3 * timeit(reference, repeats)
    res["eval_value_diff_m"] = abs(float(project()) - float(reference()))
    res["exact_project_ms"] = 1e3 * timeit(lambda: points_to_surface_distance(p64, v64, f64, workers=1), repeats)
    exact = points_to_surface_distance(p64, v64, f64, workers=1)
    try:
        import trimesh

        mesh = trimesh.Trimesh(v64, f64, process=False)
        sub = p64[:slow_points]
        res["trimesh_ms"] = 1e3 * timeit(lambda: trimesh.proximity.closest_point(mesh, sub), 1) * n_points / slow_points
        res["trimesh_max_abs_diff_m"] = float(np.abs(trimesh.proximity.closest_point(mesh, sub)[1] - exact[:slow_points]).max())
    except ImportError as err:  # trimesh.proximity needs rtree
        res["trimesh_ms"] = None
        res["trimesh_missing"] = str(err)
    try:
        import igl

        res["libigl_ms"] = 1e3 * timeit(lambda: igl.point_mesh_squared_distance(p64, v64, f64), repeats)
        d2 = igl.point_mesh_squared_distance(p64, v64, f64)[0]
        res["libigl_max_abs_diff_m"] = float(np.abs(np.sqrt(d2) - exact).max())
    except ImportError as err:
        res["libigl_ms"] = None
        res["libigl_missing"] = str(err)
    for key in ("eval_reference_ms", "trimesh_ms", "libigl_ms"):
        if res.get(key):
            res[f"exact_project_vs_{key[:-3]}"] = res["exact_project_ms"] / res[key]
    res["eval_project_vs_reference"] = res["eval_project_ms"] / res["eval_reference_ms"]
    return res


def evaluation_compare(frames: int = 8, repeats: int = 2) -> dict:
    """ms per output frame of the table1 evaluation (vertex Chamfer, surface Chamfer with 2,000
    scan points, MPJPE; 13,718 vertices, 10,000-point scans): the project's path, its scan trees
    cached as in a table run, vs :func:`~benchmark.protocols.completion_unit.evaluate_reference`."""
    from types import SimpleNamespace

    from benchmark.body.anny_body import load_anny_body
    from benchmark.protocols.completion_unit import evaluate, evaluate_reference
    from benchmark.protocols.unit_data import UnitData

    body = load_anny_body("cpu")
    outs, gts, scans = zip(*(_posed_mesh(body, seed=s) for s in range(max(1, frames // 2))))
    cat = lambda xs: torch.cat(list(xs), dim=1)  # noqa: E731
    output = SimpleNamespace(vertices=cat(o.vertices for o in outs), joints=cat(o.joints for o in outs))
    data = UnitData(scans=None, out_t=torch.zeros(1, output.vertices.shape[1]), gt_points=cat(scans),
                    gt_joints=cat(g.joints for g in gts))
    n = output.vertices.shape[1]
    fast = evaluate(body, output, data, "cpu", surface_points=2000)  # also builds the cached scan trees
    ref = evaluate_reference(body, output, data, "cpu", surface_points=2000)
    res = {"frames": n, "surface_points": 2000}
    res["project_ms"] = 1e3 * timeit(lambda: evaluate(body, output, data, "cpu", surface_points=2000), repeats) / n
    res["reference_ms"] = 1e3 * timeit(lambda: evaluate_reference(body, output, data, "cpu", surface_points=2000), repeats) / n
    res["project_vs_reference"] = res["project_ms"] / res["reference_ms"]
    res["max_abs_diff_mm"] = max(abs(x["sums"][m] - y["sums"][m]) * 1e3 / x["frames"]
                                 for x, y in zip(fast, ref) for m in x["sums"])
    return res


# ----------------------------------------------------------------------------- fit steps


def adam_steps_table1(steps: int = 4, prior: str = "no-prior") -> list[dict]:
    """Seconds per Adam step of the completion fit in each table1 cell, quick-profile sizes
    (its sequences, loss vertices and batch), one unit per cell; the heading search excluded."""
    from benchmark.protocols import completion_unit as cu
    from benchmark.protocols.completion import fit
    from benchmark.run.registry import make_adapter

    spec, profile, body, data = quick_unit()
    adapter = make_adapter(prior, size="embedded", weights=None, device="cpu")
    rows = []
    for points in spec["grid"]["points"]:
        for fps in spec["grid"]["fps"]:
            batch = cell_batch(spec, data, points, fps)
            per_step = {}
            for form in ("reference", "gemm"):
                stamps = []
                with subset_skinning(form):
                    fit(adapter, body, batch, steps=steps + 1, lr=float(spec["objective"]["lr"]),
                        lambda_prior=float(spec["objective"]["lambda_prior"]), generator=torch.Generator().manual_seed(0),
                        device="cpu", loss_vertices=cu.loss_vertex_count(profile),
                        callback=lambda step, loss: stamps.append(CLOCK()))
                per_step[form] = float(np.median(np.diff(stamps)))
            rows.append({"cell": f"{points}/{fps}", "sequences": batch.batch_size, "observed_frames": int(batch.points.shape[0] * batch.points.shape[1]),
                         "loss_vertices": cu.loss_vertex_count(profile), "s_per_step": per_step["gemm"],
                         "s_per_step_reference_skinning": per_step["reference"]})
    return rows


# ----------------------------------------------------------------------------- CUDA


def cuda_compare(frames: int = 16, n_points: int = 10000, n_vertices: int = 13718) -> dict | None:
    """CUDA only: the tiled Chamfer loss (forward + backward) vs ``torch.cdist``, ms per frame and
    peak memory. None without CUDA."""
    if not torch.cuda.is_available():
        return None
    from benchmark.metrics.chamfer import chamfer_loss
    from benchmark.metrics.perf import synthetic_pair

    dev = torch.device("cuda")
    a, b = synthetic_pair(frames, n_points, n_vertices, dev, 0)

    def tiled():
        a.grad = None
        chamfer_loss(a, b, backend="tiled", reduction="sum").backward()

    def cdist():
        a.grad = None
        d = torch.cdist(a, b)
        (0.5 * (d.min(2).values.mean(1) + d.min(1).values.mean(1))).sum().backward()

    res = {"device": torch.cuda.get_device_name(dev), "frames": frames, "points": n_points, "vertices": n_vertices}
    for name, fn in (("tiled", tiled), ("cdist", cdist)):
        torch.cuda.reset_peak_memory_stats(dev)
        try:
            res[f"{name}_ms"] = 1e3 * timeit(fn, 3) / frames
            res[f"{name}_peak_mib"] = torch.cuda.max_memory_allocated(dev) / 2**20
        except torch.cuda.OutOfMemoryError:
            res[f"{name}_ms"] = None
            res[f"{name}_peak_mib"] = "out of memory"
            torch.cuda.empty_cache()
    if res.get("tiled_ms") and res.get("cdist_ms"):
        res["tiled_vs_cdist"] = res["tiled_ms"] / res["cdist_ms"]
    return res


# ----------------------------------------------------------------------------- report


def _fmt(x, digits: int = 3) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    return str(x)


def format_report(r: dict) -> str:
    lines = [f"# benchmark perf ({r['machine']['cpu']}, {r['machine']['cores']} cores, torch {r['machine']['torch']}, "
             f"device {r['machine']['device']})", ""]
    if r.get("chamfer"):
        lines += ["## Chamfer, ms per frame (one thread); ratio = project / baseline", "",
                  "| vertices x points | loss: project | cKDTree | pykdtree | ratio cKD | ratio pyk "
                  "| metric: project | cKDTree | pykdtree | ratio cKD | ratio pyk |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for c in r["chamfer"]:
            lines.append(f"| {c['vertices']} x {c['points']} | {_fmt(c['loss_project_ms'])} | {_fmt(c['loss_ckdtree_ms'])} "
                         f"| {_fmt(c.get('loss_pykdtree_ms'))} | {_fmt(c['loss_vs_ckdtree'], 2)} | {_fmt(c.get('loss_vs_pykdtree'), 2)} "
                         f"| {_fmt(c['metric_project_ms'])} | {_fmt(c['metric_ckdtree_ms'])} | {_fmt(c.get('metric_pykdtree_ms'))} "
                         f"| {_fmt(c['metric_vs_ckdtree'], 2)} | {_fmt(c.get('metric_vs_pykdtree'), 2)} |")
        lines.append("")
    if r.get("surface"):
        s = r["surface"]
        lines += [f"## Point -> surface, {s['points']} points vs a {s['vertices']}-vertex mesh, ms per frame", "",
                  "| path | ms | ratio to project |", "| --- | --- | --- |",
                  f"| evaluation (8-nearest-vertex triangles), project | {_fmt(s['eval_project_ms'])} | 1 |",
                  f"| evaluation, reference implementation | {_fmt(s['eval_reference_ms'])} | {_fmt(s['eval_reference_ms'] / s['eval_project_ms'], 2)} |",
                  f"| exact, project (points_to_surface_distance) | {_fmt(s['exact_project_ms'])} | {_fmt(s['exact_project_ms'] / s['eval_project_ms'], 2)} |"]
        for key, name in (("trimesh_ms", "exact, trimesh.proximity"), ("libigl_ms", "exact, libigl AABB")):
            missing = s.get(key.replace("_ms", "_missing"), "not installed")
            lines.append(f"| {name} | {_fmt(s.get(key))} | "
                         f"{_fmt(s[key] / s['eval_project_ms'], 2) if s.get(key) else missing} |")
        lines.append("")
    if r.get("evaluation"):
        e = r["evaluation"]
        lines += [f"## Evaluation, every table1 metric: project {_fmt(e['project_ms'])} ms/frame, reference "
                  f"{_fmt(e['reference_ms'])} ms/frame (ratio {_fmt(e['project_vs_reference'], 2)}; largest metric "
                  f"difference {e['max_abs_diff_mm']:.2g} mm)", ""]
    if r.get("skinning"):
        sk = r["skinning"]
        lines += [f"## Skinning ({sk['vertices']} vertices, batch of {sk['frames']}): forward {sk['forward_fps']:.0f} frames/s, "
                  f"forward+backward {sk['forward_backward_fps']:.0f} frames/s", ""]
        lv = sk.get("loss_vertices")
        if lv:
            lines += [f"Loss vertices ({lv['sequences']} sequences x {lv['frames']} frames x {lv['vertices']} vertices), forward + "
                      f"backward: reference form {lv['reference_s']:.3f} s, one GEMM per sequence {lv['gemm_s']:.3f} s (ratio "
                      f"{lv['gemm_vs_reference']:.2f}; largest difference {lv['max_abs_diff_m']:.1g} m)", ""]
    if r.get("adam"):
        lines += ["## table1 fit, seconds per Adam step (quick profile, one unit)", "",
                  "| cell | observed frames | s/step | s/step, reference skinning | ratio |", "| --- | --- | --- | --- | --- |"]
        lines += [f"| {a['cell']} | {a['observed_frames']} | {a['s_per_step']:.3f} | {_fmt(a.get('s_per_step_reference_skinning'))} | "
                  f"{_fmt(a['s_per_step'] / a['s_per_step_reference_skinning'], 2) if a.get('s_per_step_reference_skinning') else ''} |"
                  for a in r["adam"]]
        lines.append("")
    if r.get("plateau"):
        lines += format_plateau(r["plateau"])
    if r.get("lists"):
        from benchmark.tools.perf_lists import format_lists

        lines += format_lists(r["lists"])
    if r.get("soft_chamfer"):
        from benchmark.tools.perf_soft import format_soft

        lines += format_soft(r["soft_chamfer"])
    if r.get("cuda"):
        c = r["cuda"]
        lines += [f"## CUDA ({c['device']}): tiled {_fmt(c.get('tiled_ms'))} ms/frame, peak {_fmt(c.get('tiled_peak_mib'))} MiB; "
                  f"torch.cdist {_fmt(c.get('cdist_ms'))} ms/frame, peak {_fmt(c.get('cdist_peak_mib'))} MiB", ""]
    return "\n".join(lines)


def check_perf_out(out: str | Path) -> Path:
    """Before any measurement: ``out`` is a writable folder (:func:`benchmark.core.outdir.check_out_dir`)
    and the ``perf.md`` / ``perf.json`` already in it, which the run replaces, were written by perf
    (a file of the same name written by someone else is refused, never overwritten)."""
    from benchmark.core.outdir import OutDirError, check_out_dir

    folder = check_out_dir(out, min_free_bytes=1 << 20)
    for name, ours in (("perf.json", _is_perf_json), ("perf.md", _is_perf_md)):
        path = folder / name
        if (path.exists() or path.is_symlink()) and not ours(path):
            raise OutDirError(f"--out {folder}: {path} was not written by `python -m benchmark perf`, which would replace "
                              "it; move it away or choose another --out")
    return folder


def _is_perf_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return path.is_file() and not path.is_symlink() and isinstance(data, dict) and isinstance(data.get("machine"), dict)


def _is_perf_md(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(64)
    except OSError:
        return False
    return path.is_file() and not path.is_symlink() and head.startswith("# benchmark perf (")


def run_perf(device: str = "cpu", quick: bool = True, out: str | Path = "perf", parts=None) -> dict:
    """Run every comparison (or ``parts``, a subset of chamfer, surface, evaluation, skinning, adam,
    soft-chamfer, cuda, plateau, lists; plateau and lists, a few minutes each, only when named), print
    the table, write ``perf.md`` and ``perf.json`` to ``out``; return the figures.
    ``out`` is checked first (:func:`check_perf_out`)."""
    out = check_perf_out(out)
    parts = set(parts or ("chamfer", "surface", "evaluation", "skinning", "adam", "soft-chamfer", "cuda"))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    report = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": cores, "torch": torch.__version__,
                          "device": device, "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "torch_threads": 1}}
    try:
        if "chamfer" in parts:
            report["chamfer"] = chamfer_compare(frames=4 if quick else 16)
        if "surface" in parts:
            report["surface"] = surface_compare()
        if "evaluation" in parts:
            report["evaluation"] = evaluation_compare(frames=8 if quick else 32)
        if "skinning" in parts:
            report["skinning"] = skinning_perf(device)
        if "adam" in parts:
            report["adam"] = adam_steps_table1(steps=4 if quick else 10)
        if "plateau" in parts:
            report["plateau"] = plateau_descent_compare()
        if "lists" in parts:
            from benchmark.tools.perf_lists import lists_compare

            report["lists"] = lists_compare()
        if "soft-chamfer" in parts:
            from benchmark.tools.perf_soft import soft_chamfer_compare

            report["soft_chamfer"] = soft_chamfer_compare()
        if "cuda" in parts and device.startswith("cuda"):
            report["cuda"] = cuda_compare()
    finally:
        torch.set_num_threads(threads)
    text = format_report(report)
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    (out / "perf.md").write_text(text + "\n")
    (out / "perf.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out / 'perf.md'} and {out / 'perf.json'}")
    return report
