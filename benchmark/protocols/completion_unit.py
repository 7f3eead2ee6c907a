"""Executing one completion work unit: data for the unit, the fit, the evaluation, the unit result.

The data of a unit is a deterministic function of (sequence ids, table data rules, seed): the 50 fps
dense capture of each sequence's window (sampled with a per-batch capture seed that does not
depend on the prior or the cell, so every prior and cell sees the same capture), degraded for the
cell, and the ground truth at the 30 fps output timestamps (mesh, joints and a dense ground-truth
scan sampled at those timestamps).
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch

from benchmark.data.degrade import degrade, fingerprint
from benchmark.core.fit_diagnostics import sequence_diagnostics
from benchmark.data.observations import make_scans, seed_generators
from benchmark.protocols.completion import decode_output, fit, observation_batch
from benchmark.protocols.step_rules import plateau_rule
from benchmark.protocols.unit_data import UnitData, cell_degrade_seed, seed_rule, unit_seeds
from benchmark.core.surface_sampling import sample_surface

log = logging.getLogger(__name__)

NO_GT_JOINTS = "no ground-truth joints"  # the MPJPE n/a reason on captured scans


class CompletionData:
    """Builds and caches (in process) the capture and ground truth of batches of test sequences."""

    def __init__(self, table_spec: dict, body, motions_by_id: dict, seed: int):
        self.spec = table_spec
        self.seeds = seed_rule(table_spec)
        self.body = body.on_cpu()  # the data is made on the CPU whatever the run's device (BodyModel.on_cpu)
        self.motions = motions_by_id
        self.seed = seed
        self._cache: dict = {}

    def unit_data(self, sequence_ids: list[str]) -> UnitData:
        key = tuple(sequence_ids)
        if key in self._cache:
            return self._cache[key]
        d = self.spec["data"]
        window = float(d["window_s"])
        start = float(d.get("window_start_s", 0.0))
        motions = [self.motions[sid] for sid in sequence_ids]
        if start:
            motions = [m.window(float(m.timestamps[0]) + start, m.duration - start) for m in motions]
        capture_seed = unit_seeds("capture", self.seed, sequence_ids, rule=self.seeds)
        scans, gt = make_scans(self.body, motions, fps=float(d["capture_fps"]), num_points=int(d["points_per_frame"]),
                               noise_std=float(d.get("scan_noise_std", 0.0)), seed=capture_seed, duration=window)
        out_fps = float(self.spec["output_fps"])
        n_out = int(round(window * out_fps))
        t0 = scans.timestamps[:, :1]  # on the body's device, as every tensor make_scans returns
        rel = torch.arange(n_out, dtype=torch.float64, device=t0.device) / out_fps
        out_abs = t0 + rel[None]
        gt_out = gt.at(out_abs)
        gs = seed_generators(unit_seeds("gt-scan", self.seed, sequence_ids, rule=self.seeds), len(motions), "gt-scan")
        with torch.no_grad():
            gt_points = torch.cat([sample_surface(gt_out.vertices[b:b + 1], self.body.faces, int(d["points_per_frame"]), gs[b])
                                   for b in range(len(motions))])
        data = UnitData(scans=scans, out_t=rel[None].expand(len(motions), -1).clone(), gt_points=gt_points,
                        gt_joints=gt_out.joints)
        self._cache = {key: data}  # keep one batch: units of the same batch run consecutively
        return data


SCAN_TREE_SETS = 16  # the ground-truth KD-tree sets a unit's data keeps (evaluate, by sequence for captures of different sizes)
SURFACE_K = 8  # nearest mesh vertices whose incident triangles are the surface candidates of a scan point


def evaluate(body, output, data: UnitData, device, surface_points: int | None = None) -> list[dict]:
    """Per-sequence metric sums (metres, summed over output frames).

    Both Chamfer columns share the direction output vertices -> nearest ground-truth scan point
    (over the full scan). The other direction is scan point -> nearest output vertex (headline
    column) or -> nearest point on the output triangles (surface column). ``surface_points``: the
    scan -> triangles direction uses the first that many points of each scan (i.i.d. uniform
    samples, so an unbiased subsample of the same mean); None: all.

    The scan -> triangles distance of a point is the exact distance to the nearest of the
    triangles incident to its ``SURFACE_K`` nearest vertices, and never more than its vertex
    distance (exact whenever the closest surface point lies on one of them, which holds for any fit
    within a few centimetres; for far points an upper bound).

    Returns the same numbers as :func:`evaluate_reference` (the same nearest neighbours, the same
    float operations on them), faster: the scans' KD-trees are built once per batch of sequences
    (``data.cache``) and shared by every prior and cell; one tree per output mesh serves the k = 1
    and k = ``SURFACE_K`` queries; a candidate triangle is only evaluated when a bound
    (distance to its circumscribing sphere about the centroid) says it may beat the vertex
    distance; frames run on parallel threads (:func:`benchmark.metrics.chamfer.cpu_threads`).
    """
    from benchmark.metrics.chamfer import map_elements, build_tree, query_tree

    if isinstance(data.gt_points, (list, tuple)):  # captures of different sizes: each its own ground truth
        return [row for b, g in enumerate(data.gt_points) for row in evaluate(
            body, dataclasses.replace(output, vertices=output.vertices[b:b + 1], joints=output.joints[b:b + 1]),
            dataclasses.replace(data, gt_points=g, gt_joints=data.gt_joints[b:b + 1]), device, surface_points)]
    verts = output.vertices.to("cpu", torch.float32)
    B, T = verts.shape[:2]
    gt = data.gt_points.to(verts)
    v_flat, g_flat = verts.flatten(0, 1), gt.flatten(0, 1)
    n_frames, n_verts, n_scan = v_flat.shape[0], v_flat.shape[1], g_flat.shape[1]
    n_surf = n_scan if surface_points is None else min(int(surface_points), n_scan)
    gt_trees = _scan_trees(data, g_flat)
    v_np = v_flat.numpy().astype(np.float64)
    g_np = g_flat.numpy().astype(np.float64)
    idx_vg = np.empty((n_frames, n_verts), dtype=np.int64)
    idx_gv = np.empty((n_frames, n_scan), dtype=np.int64)
    k = min(SURFACE_K, n_verts)
    knn = np.empty((n_frames, n_surf, k), dtype=np.int64)

    def neighbours(i: int) -> None:
        idx_vg[i] = query_tree(gt_trees[i], v_np[i])[1]
        mesh_tree = build_tree(v_np[i])
        nn = query_tree(mesh_tree, g_np[i, :n_surf], k=k)[1].reshape(n_surf, k)
        knn[i] = nn
        idx_gv[i, :n_surf] = nn[:, 0]
        if n_surf < n_scan:
            idx_gv[i, n_surf:] = query_tree(mesh_tree, g_np[i, n_surf:])[1]

    map_elements(neighbours, n_frames)
    with torch.no_grad():  # as benchmark.metrics.chamfer.nearest_neighbors computes them
        idx_vg_t, idx_gv_t = torch.from_numpy(idx_vg), torch.from_numpy(idx_gv)
        d_vg = (v_flat - torch.gather(g_flat, 1, idx_vg_t[..., None].expand(-1, -1, 3))).norm(dim=-1)
        d_gv = (g_flat - torch.gather(v_flat, 1, idx_gv_t[..., None].expand(-1, -1, 3))).norm(dim=-1)
    vert_to_scan = d_vg.mean(1)
    chamfer = 0.5 * (vert_to_scan + d_gv.mean(1))
    faces = body.faces.cpu()
    vertex_faces = incident_faces(faces, n_verts).numpy()
    faces_np = np.ascontiguousarray(faces.numpy(), dtype=np.int64)
    scan_to_surface = torch.stack(map_elements(
        lambda i: scan_to_surface_frame(g_flat[i, :n_surf], v_flat[i], faces_np, vertex_faces, knn[i], d_gv[i, :n_surf]),
        n_frames))
    surface = 0.5 * (vert_to_scan.double() + scan_to_surface)
    return _sequence_sums(chamfer, surface, output, data, verts)


def _sequence_sums(chamfer: torch.Tensor, surface: torch.Tensor, output, data: UnitData, verts: torch.Tensor) -> list[dict]:
    """Per-sequence metric sums over the output frames: the two Chamfer columns (``(B*T,)`` per
    frame) and MPJPE of ``output``'s joints against the ground truth."""
    B, T = verts.shape[:2]
    err = (output.joints.to("cpu") - data.gt_joints.to(verts)).norm(dim=-1).mean(-1)  # (B, T)
    ch, surf = chamfer.view(B, T), surface.view(B, T)
    return [
        {"frames": T, "sums": {"chamfer_m": float(ch[b].sum()), "chamfer_surface_m": float(surf[b].sum()),
                               "mpjpe_m": float(err[b].sum())}}
        for b in range(B)
    ]


def _scan_trees(data: UnitData, g_flat: torch.Tensor) -> list:
    """The KD-trees of the ground-truth scans (one per output frame), built on first use and kept in
    ``data.cache`` (keyed by the scans' shape and storage, so a changed tensor is never served a stale tree)."""
    from benchmark.metrics.chamfer import map_elements, build_tree

    cache = getattr(data, "cache", None)
    # Unit data are never modified in place; the key still checks the storage and a cheap checksum.
    key = ("scan_trees", tuple(g_flat.shape), data.gt_points.data_ptr(), float(g_flat[:, :16].double().sum()))
    if cache is not None and key in cache:
        return cache[key]
    g_np = g_flat.numpy().astype(np.float64)
    trees = map_elements(lambda i: build_tree(np.ascontiguousarray(g_np[i])), g_np.shape[0])
    if cache is not None:  # one batch's trees, or one per sequence when its captures differ in size
        while len(cache) >= SCAN_TREE_SETS:
            cache.pop(next(iter(cache)))
        cache[key] = trees
    return trees


def incident_faces(faces: torch.Tensor, n_verts: int) -> torch.Tensor:
    """(V, width) long: the faces incident to each vertex, padded with the dummy index F."""
    F = faces.shape[0]
    order = torch.argsort(faces.reshape(-1), stable=True)
    counts = torch.bincount(faces.reshape(-1), minlength=n_verts)
    width = int(counts.max())
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(width, device=faces.device)
    idx = starts[:, None] + slot[None]
    valid = slot[None] < counts[:, None]
    return torch.where(valid, (order // 3)[idx.clamp_max(order.numel() - 1)], torch.full_like(idx, F))


def scan_to_surface_frame(points: torch.Tensor, vertices: torch.Tensor, faces: np.ndarray, vertex_faces: np.ndarray,
                          knn: np.ndarray, vertex_distance: torch.Tensor) -> torch.Tensor:
    """One frame's scan -> surface mean (float64 scalar): min(vertex distance, exact distance to the
    triangles incident to each point's ``knn`` (P, k) nearest vertices), averaged over the (P, 3)
    ``points``. ``faces`` (F, 3) int64; ``vertex_faces`` (V, width) as :func:`incident_faces` gives.
    The compiled kernel (:mod:`benchmark.metrics.surface_kernel`) where numba is installed, else the
    array path (:func:`_scan_to_surface_frame`): the same doubles either way (tested)."""
    from benchmark.metrics.surface_kernel import HAVE_NUMBA, scan_to_surface_knn

    if HAVE_NUMBA:
        best = scan_to_surface_knn(points.numpy(), vertices.numpy(), faces, vertex_faces, knn,
                                   vertex_distance.double().numpy())
        return torch.from_numpy(best).mean()
    return _scan_to_surface_frame(points, vertices, np.ascontiguousarray(faces.T), vertex_faces, knn, vertex_distance)


def _scan_to_surface_frame(points: torch.Tensor, vertices: torch.Tensor, faces_t: np.ndarray,
                           vertex_faces: np.ndarray, knn: np.ndarray, vertex_distance: torch.Tensor) -> torch.Tensor:
    """Mean over the (P, 3) scan points of min(vertex distance, exact distance to the triangles
    incident to their ``knn`` (P, k) nearest vertices), float64 scalar: the value of the reference
    :func:`scan_to_surface_distance` for one frame. ``faces_t``: (3, F) corner indices;
    ``vertex_faces``: (V, width) incident faces, padded with F.

    A candidate (point, face) pair is only evaluated when two lower bounds on its distance, the
    distance to the face's plane and ``|p - c_f| - r_f`` (c_f the face's centroid, r_f its
    largest centroid-to-corner distance: every point of the face lies within r_f of c_f), are both
    at most the point's vertex distance plus 1e-9 m: a face beyond either bound can never lower
    the minimum, so skipping it changes no bit of the result. A face met through several of the
    k vertices is evaluated once.
    """
    from benchmark.metrics.surface import distance_to_prepared_soa, prepare_triangles_soa

    F = faces_t.shape[1]
    n_points = points.shape[0]
    vd = vertex_distance.double().numpy()
    vt = vertices.double().numpy().T  # (3, V)
    corners = [tuple(torch.from_numpy(np.take(vt[i], faces_t[j])) for i in range(3)) for j in range(3)]
    prepared = prepare_triangles_soa(*corners)  # 13 x (F,)
    soa = np.stack([t.numpy() for t in prepared])  # (13, F)
    c = [sum(corners[j][i].numpy() for j in range(3)) / 3 for i in range(3)]
    r2 = None
    for corner in corners:
        d2 = sum((corner[i].numpy() - c[i]) ** 2 for i in range(3))
        r2 = d2 if r2 is None else np.maximum(r2, d2)
    ab, ac = soa[3:6], soa[6:9]
    normal = np.stack([ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2], ab[0] * ac[1] - ab[1] * ac[0]])
    norm = np.sqrt((normal ** 2).sum(0))
    flat = norm > 0
    normal = np.where(flat, normal / np.where(flat, norm, 1.0), 0.0)  # zero normal: no plane bound
    offset = (normal * np.stack(c)).sum(0)
    bounds = np.stack([*c, np.sqrt(r2), *normal, offset])  # (8, F)

    cand = np.sort(np.take(vertex_faces, knn, axis=0).reshape(n_points, -1), axis=1)  # (P, k * width)
    first = np.empty(cand.shape, dtype=bool)
    first[:, 0] = True
    np.not_equal(cand[:, 1:], cand[:, :-1], out=first[:, 1:])
    pid, col = np.nonzero(first & (cand < F))  # each (point, face) pair once
    fid = cand[pid, col]
    p64 = points.double().numpy().T  # (3, P)
    pp = np.take(p64, pid, axis=1)  # (3, n)
    bf = np.take(bounds, fid, axis=1)  # (8, n)
    sphere = np.sqrt(((pp - bf[0:3]) ** 2).sum(0)) - bf[3]
    plane = np.abs((pp * bf[4:7]).sum(0) - bf[7]) - 1e-12
    keep = np.nonzero(np.maximum(sphere, plane) <= np.take(vd, pid) + 1e-9)[0]
    pid, fid = pid[keep], fid[keep]
    tri = torch.from_numpy(np.take(soa, fid, axis=1))
    pts = torch.from_numpy(pp[:, keep])
    d = distance_to_prepared_soa(tuple(pts), tuple(tri))
    d = torch.nan_to_num(d, nan=float("inf"), posinf=float("inf"))
    best = torch.from_numpy(vd.copy()).scatter_reduce_(0, torch.from_numpy(pid), d, reduce="amin")
    return best.mean()


def evaluate_reference(body, output, data: UnitData, device, surface_points: int | None = None) -> list[dict]:
    """:func:`evaluate` as it was first written (scipy cKDTree, every tree rebuilt, every candidate
    triangle evaluated): the reference the fast path is tested against. Same return value.

    Per-sequence metric sums (metres, summed over output frames).

    Both Chamfer columns share the direction output vertices -> nearest ground-truth scan point
    (over the full scan). The other direction is scan point -> nearest output vertex (headline
    column) or -> nearest point on the output triangles (surface column). ``surface_points``: the
    scan -> triangles direction uses the first that many points of each scan (i.i.d. uniform
    samples, so an unbiased subsample of the same mean); None: all.
    """
    from benchmark.metrics.chamfer import nearest_neighbors

    verts = output.vertices.to("cpu", torch.float32)
    B, T = verts.shape[:2]
    gt = data.gt_points.to(verts)
    v_flat, g_flat = verts.flatten(0, 1), gt.flatten(0, 1)
    d_vg, _ = nearest_neighbors(v_flat, g_flat, backend="scipy")  # (B*T, V)
    d_gv, _ = nearest_neighbors(g_flat, v_flat, backend="scipy")  # (B*T, N)
    vert_to_scan = d_vg.mean(1)
    chamfer = 0.5 * (vert_to_scan + d_gv.mean(1))
    scan_to_surface = scan_to_surface_distance(g_flat[:, :surface_points], v_flat, body.faces.cpu(), d_gv[:, :surface_points])
    surface = 0.5 * (vert_to_scan.double() + scan_to_surface.double())
    return _sequence_sums(chamfer, surface, output, data, verts)


def scan_to_surface_distance(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor,
                             vertex_distance: torch.Tensor, k: int = SURFACE_K) -> torch.Tensor:
    """Reference (see :func:`evaluate_reference`): (N,) mean distance from each scan point (N, P, 3) to the mesh (N, V, 3) surface.

    Candidates: the triangles incident to each point's ``k`` nearest vertices (exact whenever the
    closest surface point lies on one of them, which holds for any fit within a few centimetres;
    for far points it is an upper bound, never above the vertex distance ``vertex_distance``).
    """
    import scipy.spatial

    from benchmark.metrics.surface import point_triangle_distance

    vf = incident_faces(faces, vertices.shape[1])  # (V, width) incident faces, padded with the dummy index F
    out = []
    for i in range(points.shape[0]):
        tree = scipy.spatial.cKDTree(vertices[i].numpy())
        _, nn = tree.query(points[i].numpy(), k=k, workers=-1)
        cand = vf[torch.from_numpy(nn)].reshape(points.shape[1], -1)  # (P, k*width)
        tri = torch.cat([vertices[i][faces], vertices.new_full((1, 3, 3), float("inf"))])[cand]  # (P, C, 3, 3)
        d = point_triangle_distance(points[i][:, None].double(), tri.double())
        d = torch.nan_to_num(d, nan=float("inf"), posinf=float("inf")).amin(1)
        out.append(torch.minimum(d, vertex_distance[i].double()).mean())
    return torch.stack(out)


def loss_vertex_count(profile: dict) -> int | None:
    value = profile.get("loss_vertices", "all")
    return None if value in (None, "all") else int(value)


def run_completion_unit(unit, table_spec: dict, profile: dict, adapter, body, data_source: CompletionData, device) -> dict:
    cell = unit.cell
    data = data_source.unit_data(unit.sequence_ids)
    # The degradation depends on the table seed, the cell and the sequences, never on the prior:
    # every prior sees the same observation in a cell (same fingerprint).
    degrade_seed = cell_degrade_seed(data_source.seed, cell["points"], cell["fps"], unit.sequence_ids,
                                     rule=seed_rule(table_spec))
    obs_offsets = None
    if hasattr(data_source, "observe"):  # captured scans (scan_completion.py): nearest capture frames
        from benchmark.protocols.scan_completion import CellNotServed

        try:
            obs, obs_offsets = data_source.observe(unit.sequence_ids, int(cell["points"]), float(cell["fps"]), degrade_seed)
        except CellNotServed as exc:  # a sparser capture than the cell: n/a, not the sparser cell under its label
            from benchmark.core.work_units import na_result

            return na_result(unit, str(exc))
    else:
        obs = degrade(data.scans, int(cell["points"]), float(cell["fps"]), seed=degrade_seed,
                      capture_fps=float(table_spec["data"]["capture_fps"]))
    offset = float(table_spec["data"].get("observation_offset_m", 0.0))
    if offset:  # fit-check --robustness's probe (benchmark/tools/fit_check.py): never set in a table
        obs = dataclasses.replace(obs, points=obs.points + offset)
    fp = fingerprint(obs)
    batch = observation_batch(obs, float(table_spec["data"]["window_s"]), data.out_t, device)
    obj = table_spec["objective"]
    g = torch.Generator().manual_seed(unit.seed)
    t0 = time.perf_counter()
    state, info = fit(adapter, body, batch, steps=int(profile["steps"]), lr=float(obj["lr"]),
                      lambda_prior=float(obj["lambda_prior"]), generator=g, device=device,
                      loss_vertices=loss_vertex_count(profile), facing=facing_rule(table_spec),
                      shape_lr_scale=float(obj.get("shape_lr_scale", 1.0)), latent_init=latent_init_rule(table_spec),
                      start_search=start_search_rule(table_spec), plateau=plateau_rule(table_spec),
                      multi_start=multi_start_rule(table_spec), optimiser=optimiser_rule(table_spec),
                      start_fit=start_fit_rule(table_spec))
    t1 = time.perf_counter()
    output, rot, trans = decode_output(state, body, batch.output_timestamps)
    sp = profile.get("surface_points", "all")
    no_joints = data.gt_joints is None
    if no_joints:  # captured scans: the evaluation's joint column is computed on zeros and dropped below
        data = dataclasses.replace(data, gt_joints=torch.zeros_like(output.joints))
    per_seq = evaluate(body, output, data, device, surface_points=None if sp in (None, "all") else int(sp))
    t2 = time.perf_counter()
    gt_pose = None if no_joints else unit_ground_truth_pose(data_source, unit.sequence_ids, data)
    diagnostics = sequence_diagnostics(info["data_trace"], rot[:, :, 0], None if gt_pose is None else gt_pose[0][:, :, 0],
                                       plateau=info.get("plateau"))
    for i, (sid, row) in enumerate(zip(unit.sequence_ids, per_seq)):
        row["id"] = sid
        row["diagnostics"] = diagnostics[i]
        if no_joints:
            row["sums"].pop("mpjpe_m", None)
            row["na"] = {"mpjpe_m": NO_GT_JOINTS}
        if data.row_extra is not None:
            row.update(data.row_extra[i])
        if obs_offsets is not None:
            row["obs_time_offset_max_s"] = obs_offsets[i]
    return {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": fp, "per_sequence": per_seq,
        "timings": {"fit_s": t1 - t0, "eval_s": t2 - t1, "facing_s": info.get("facing_s", 0.0),
                    **({"start_search_s": info["start_search_s"]} if "start_search_s" in info else {})}, "device": str(device),
        "na_reason": None, "fit_log": info["history"], **({"facing_search": {k: info[k] for k in FACING_LOG if k in info}}
                                       if any(k in info for k in FACING_LOG) else {}),
        # the runner stores it as .npz; captured scans have no ground-truth motion to store beside the fit
        "arrays": None if no_joints else unit_arrays(unit, data, batch, rot, trans, state.shape(), gt_pose),
    }


# what the facing search logs (completion.facing_search), and the limb start search's choices per stage
FACING_LOG = ("facing_yaw_rad", "facing_scores_mm", "start_choice_counts", "multi_start")


def facing_rule(spec: dict) -> str:
    """How a fit finds the facing direction (``objective.facing``; protocol version 1: ``heading8``)."""
    return str(spec["objective"].get("facing", "heading8"))


def latent_init_rule(spec: dict) -> str:
    """Where the priors' latents start (``objective.latent_init``; protocol versions 1-2: ``sample``)."""
    return str(spec["objective"].get("latent_init", "sample"))


def start_fit_rule(spec: dict) -> str:
    """The start search's brief fits (``objective.start_fit``: ``exact``, Adam on the Chamfer, when
    absent; ``smooth``, L-BFGS on the soft-min Chamfer; ``smooth-encoded``, smooth only for the start
    the encoders encode: :data:`benchmark.protocols.brief_fit.START_FITS`)."""
    from benchmark.protocols.brief_fit import check_start_fit

    return check_start_fit(str(spec["objective"].get("start_fit", "exact")))


def start_search_rule(spec: dict) -> str:
    """How per-frame priors search their start (``objective.start_search``: ``none``, the rule of
    table1 protocol versions 1-3, or ``limbs``: :func:`benchmark.protocols.start_search.limb_start_search`)."""
    return str(spec["objective"].get("start_search", "none"))


def optimiser_rule(spec: dict) -> str:
    """``objective.optimiser``: ``adam`` (every table) or ``lbfgs`` (benchmark/protocols/quasi_newton.py,
    a table1 version 8 candidate); anything else is refused naming the field."""
    from benchmark.protocols.quasi_newton import OPTIMISERS

    value = str(spec["objective"].get("optimiser", "adam"))
    if value not in OPTIMISERS:
        raise ValueError(f"objective.optimiser: {value!r} is not an optimiser of the completion fit; "
                         f"choose one of {', '.join(OPTIMISERS)}")
    return value


def multi_start_rule(spec: dict):
    """``objective.multi_start`` (:class:`benchmark.protocols.multi_start.MultiStart`), or None: one start."""
    from benchmark.protocols.multi_start import MultiStart

    try:
        return MultiStart.from_spec(spec["objective"].get("multi_start"))
    except ValueError as e:
        src = spec.get("_source") or f"benchmark/tables/{spec.get('name', '?')}.yaml"
        raise ValueError(f"{src}: {e}") from None


def unit_ground_truth_pose(data_source: CompletionData, sequence_ids, data: UnitData):
    """(rotations (B, T, 22, 3, 3), translation (B, T, 3), shape) of the ground truth at the unit's output timestamps."""
    from benchmark.data.unit_arrays import ground_truth_pose

    d = data_source.spec["data"]
    start = float(d.get("window_start_s", 0.0))
    motions = [data_source.motions[sid] for sid in sequence_ids]
    if start:
        motions = [m.window(float(m.timestamps[0]) + start, m.duration - start) for m in motions]
    return ground_truth_pose(data_source.body, motions, data.scans.timestamps[:, :1] + data.out_t)


def unit_arrays(unit, data: UnitData, batch, rot, trans, shape, gt_pose) -> dict:
    """The fitted and ground-truth motion at the output timestamps and a subsample of the
    observation, for the report's animations (:mod:`benchmark.data.unit_arrays`)."""
    from benchmark.data.unit_arrays import fit_arrays

    gt_rot, gt_trans, gt_shape = gt_pose
    return fit_arrays(unit, data.out_t, rot, trans, shape, gt_rot, gt_trans, gt_shape, batch.timestamps,
                      batch.points, batch.lengths)


# -- the protocol interface (benchmark.protocols.base.Protocol; wrapped by benchmark.protocols.builtin) --
def make_source(spec: dict, body, motions_by_id: dict, seed: int):
    from benchmark.protocols.scan_completion import ScanCompletionData, is_scan_source

    if is_scan_source(motions_by_id):
        return ScanCompletionData(spec, body, motions_by_id, seed)
    return CompletionData(spec, body, motions_by_id, seed)


def load_motions(spec: dict, data: str | None, body) -> dict:
    """--data: captured scans (``scans=DIR``, scan_completion.py) or motions (:func:`benchmark.data.table_data.load_motions`:
    a motion with a hole in its timestamps or a root teleport within the window is skipped)."""
    if data and data.startswith("scans="):
        from benchmark.protocols.scan_completion import load_scan_sequences

        return load_scan_sequences(spec, data)
    from benchmark.data.table_data import load_motions as load_motion_files

    d = spec["data"]
    return load_motion_files(data, float(d["window_s"]), body, sample_fps=float(d["capture_fps"]),
                             window=(float(d.get("window_start_s", 0.0)), float(d["window_s"])))


def run_unit(unit, spec: dict, profile: dict, adapter, body, source: CompletionData, device) -> dict:
    return run_completion_unit(unit, spec, profile, adapter, body, source, device)
