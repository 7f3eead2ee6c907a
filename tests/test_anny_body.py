"""The embedded Anny body: T-pose, SMPL conventions, and agreement with Anny's own forward."""

import roma
import torch

from benchmark.core.skeleton import JOINT_INDEX as J


def _identity(B=1, T=1):
    return torch.eye(3).expand(B, T, 22, 3, 3)


def test_zero_pose_is_a_t_pose(anny_body):
    out = anny_body(_identity(), torch.zeros(1, 1, 3))
    v, j = out.vertices[0, 0], out.joints[0, 0]
    # feet on the floor
    assert abs(v[:, 1].min().item()) < 1e-5
    # standing upright: head above spine above pelvis, on the vertical through the pelvis
    for name in ("spine1", "spine2", "spine3", "neck", "head"):
        assert abs(j[J[name], 0]) < 5e-3
    assert j[J["head"], 1] > j[J["neck"], 1] > j[J["spine3"], 1] > j[J["pelvis"], 1]
    # legs straight down
    for side in ("left", "right"):
        hip, knee, ankle = j[J[f"{side}_hip"]], j[J[f"{side}_knee"]], j[J[f"{side}_ankle"]]
        for a, b in ((hip, knee), (knee, ankle)):
            d = torch.nn.functional.normalize(b - a, dim=0)
            assert d[1] < -0.999
    # arms horizontal, left at +x, right at -x
    for side, sign in (("left", 1.0), ("right", -1.0)):
        chain = [j[J[f"{side}_{n}"]] for n in ("shoulder", "elbow", "wrist")]
        for a, b in zip(chain, chain[1:]):
            d = torch.nn.functional.normalize(b - a, dim=0)
            assert d[0] * sign > 0.999
    # facing +z: the toes are in front of the ankles
    assert (j[J["left_foot"], 2] - j[J["left_ankle"], 2]) > 0.05


def test_matches_anny_forward(anny_body):
    torch.manual_seed(0)
    B, T = 2, 3
    rot = roma.rotvec_to_rotmat(torch.randn(B, T, 22, 3) * 0.4)
    trans = torch.randn(B, T, 3) * 0.3
    shape = torch.rand(B, 6)
    rest = anny_body.prepare_with_anny(shape)
    ours = anny_body.skin(rest, rot, trans).vertices
    poses = anny_body.anny_bone_poses(rest, rot, trans)
    ref = anny_body.anny(
        poses, phenotype_kwargs=shape.repeat_interleave(T, 0), pose_parameterization="world"
    )["vertices"]
    ref = (ref.to(ours) @ anny_body.anny_to_world.T).reshape(B, T, -1, 3)
    err = (ref - ours).norm(dim=-1).max().item()
    assert err < 1e-4, f"max vertex error {err * 1000:.4f} mm"


def test_local_rotation_is_world_aligned(anny_body):
    # A rotation of the left shoulder about world -z lowers the left arm (the joint frame is world-aligned).
    rot = _identity().clone()
    rot[0, 0, J["left_shoulder"]] = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, -torch.pi / 2]))
    j = anny_body(rot).joints[0, 0]
    d = torch.nn.functional.normalize(j[J["left_elbow"]] - j[J["left_shoulder"]], dim=0)
    assert d[1] < -0.999


def test_translation_and_shape_gradients(anny_body):
    shape = anny_body.default_shape(1).requires_grad_(True)
    rot = roma.rotvec_to_rotmat((torch.randn(1, 2, 22, 3) * 0.2).requires_grad_(True))
    trans = torch.zeros(1, 2, 3, requires_grad=True)
    out = anny_body(rot, trans, shape)
    out.vertices.square().sum().backward()
    assert shape.grad is not None and shape.grad.abs().sum() > 0
    assert trans.grad is not None and torch.isfinite(trans.grad).all()
    # translation moves every vertex by the same vector
    out2 = anny_body(rot.detach(), trans.detach() + torch.tensor([0.1, 0.2, 0.3]), shape.detach())
    diff = out2.vertices - out.vertices.detach()
    assert torch.allclose(diff, torch.tensor([0.1, 0.2, 0.3]).expand_as(diff), atol=1e-5)


def test_shape_changes_height(anny_body):
    shape = anny_body.default_shape(2).clone()
    shape[0, 4], shape[1, 4] = 0.1, 0.9  # height
    v = anny_body(_identity(2), shape=shape).vertices
    heights = v[:, 0, :, 1].amax(-1)
    assert heights[1] > heights[0] + 0.1
    assert v[:, 0, :, 1].amin(-1).abs().max() < 1e-4  # every shape stands on the floor


def test_weights_and_landmarks(anny_body):
    w = anny_body.weights
    assert torch.allclose(w.sum(1), torch.ones(w.shape[0]), atol=1e-5)
    assert anny_body.landmark_indices.shape == (16,)
    assert len(set(anny_body.landmark_indices.tolist())) == 16


def test_a_load_in_another_dtype_leaves_the_cached_body_alone(anny_body):
    """load_anny_body caches one body per (device, dtype); nn.Module.to moves a module in place,
    so the float64 load must be a copy, not the float32 body every other caller holds, moved."""
    from benchmark.body.anny_body import _CACHED, load_anny_body

    base = load_anny_body("cpu")
    try:
        wide = load_anny_body("cpu", torch.float64)
        assert wide is not base and load_anny_body("cpu") is base
        assert {t.dtype for t in base.buffers() if t.is_floating_point()} == {torch.float32}
        assert {t.dtype for t in wide.buffers() if t.is_floating_point()} == {torch.float64}
        assert base(_identity(), torch.zeros(1, 1, 3)).vertices.dtype == torch.float32
    finally:
        _CACHED.pop(("cpu", torch.float64), None)  # the copy is not kept for the rest of the session


def test_the_one_gemm_skinning_equals_the_reference_form_values_and_gradients():
    """shared_rest_blend_skinning (the fits' loss vertices) against linear_blend_skinning: the same
    posed vertices and the same gradients for the rest vertices and the transforms, up to float32
    rounding, for a batch of sequences with frames of their own."""
    from benchmark.body.lbs import linear_blend_skinning, shared_rest_blend_skinning

    g = torch.Generator().manual_seed(3)
    B, T, V, Jn = 3, 5, 40, 22
    verts = torch.randn(B, V, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(V, Jn, generator=g, dtype=torch.float64)
    weights = weights / weights.sum(-1, keepdim=True)
    transforms = torch.randn(B, T, Jn, 3, 4, generator=g, dtype=torch.float64)
    upstream = torch.randn(B, T, V, 3, generator=g, dtype=torch.float64)
    results = []
    for form in (lambda v, w, S: linear_blend_skinning(v[:, None], w, S), shared_rest_blend_skinning):
        v, S = verts.clone().requires_grad_(True), transforms.clone().requires_grad_(True)
        out = form(v, weights, S)
        (out * upstream).sum().backward()
        results.append((out.detach(), v.grad, S.grad))
    for ref, new in zip(*results):
        assert new.shape == ref.shape
        torch.testing.assert_close(new, ref, rtol=1e-12, atol=1e-12)


def test_a_posed_vertex_subset_is_the_whole_mesh_posed_and_indexed(anny_body):
    """AnnyBody.skin with vertex_indices (the one-GEMM form) gives the whole mesh's posed vertices
    (the reference form) at those indices, to float32 rounding (< 1e-5 m), and the same joints."""
    g = torch.Generator().manual_seed(0)
    B, T = 2, 6
    rot = roma.rotvec_to_rotmat(torch.randn(B, T, 22, 3, generator=g) * 0.4)
    trans = torch.randn(B, T, 3, generator=g) * 0.5
    shape = anny_body.default_shape(B) + 0.1 * torch.rand(B, anny_body.shape_dim, generator=g)
    rest = anny_body.prepare(shape)
    idx = anny_body.loss_vertex_indices(500)
    whole = anny_body.skin(rest, rot, trans)
    subset = anny_body.skin(rest, rot, trans, vertex_indices=idx)
    assert subset.vertices.shape == (B, T, 500, 3)
    torch.testing.assert_close(subset.vertices, whole.vertices[:, :, idx], rtol=0, atol=1e-5)
    torch.testing.assert_close(subset.joints, whole.joints, rtol=0, atol=0)
