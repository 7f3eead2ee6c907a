"""The procedural motion generator and its splits (benchmark/synthetic).

Everything here runs on the hard-coded canonical skeleton (no body model), except one check of
the mesh-derived contact points on the embedded Anny body.
"""

import json
import math

import numpy as np
import pytest
import roma
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.motion import Motion
from benchmark.core.skeleton import JOINT_INDEX as J
from benchmark.core.skeleton import MIRROR
from benchmark.synthetic import splits as splits_mod
from benchmark.synthetic.actions import ACTIONS
from benchmark.synthetic.contact import GRAVITY, solve_root_track
from benchmark.synthetic.curves import FourierCurve, KeyframeCurve, window
from benchmark.synthetic.generator import GENERATOR_VERSION, Segment, SequencePlan, SyntheticSequence
from benchmark.synthetic.plans import TEST_COMPOSITION, build_segments
from benchmark.synthetic.posing import PoseBuilder, mirror_pose
from benchmark.synthetic.quality import foot_metrics
from benchmark.synthetic.rest import CANONICAL_JOINTS, CanonicalSkeletons, RestSkeleton
from benchmark.synthetic.splits import SplitSpec, build_split, content_digest, generate_split, split_plans
from benchmark.synthetic.subjects import TEST_SUBJECTS, Subject, sample_subjects

D = math.radians
CANON = CanonicalSkeletons()


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The generator works on many small tensors: on a busy 2-core machine, intra-op threads only
    contend (50x slower measured), so this module runs single-threaded and restores after."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
SUBJECT = TEST_SUBJECTS[0]


def _skeleton(subject=SUBJECT):
    return CANON.rest_skeleton(subject.phenotype)


def _plan(parts, seed=0, subject=SUBJECT):
    rng = np.random.default_rng(seed)
    return SequencePlan(subject, build_segments(rng, subject, parts), seed=seed, heading0=0.3, phase0=0.1, kind="t")


def _world_points(motion, skeleton):
    g, j = forward_kinematics(motion.rotmats().double(), skeleton.joints)
    return skeleton.posed_points(g, j) + motion.trans.double()[:, None]


# ------------------------------------------------------------------------------------------ curves


def test_fourier_curve_reproduces_a_sinusoid_and_keyframe_curve_interpolates():
    p = torch.linspace(0, 1, 200, dtype=torch.float64)
    keys = [(k / 64, 2.0 + 3.0 * math.cos(2 * math.pi * k / 64 - 0.4)) for k in range(64)]
    c = FourierCurve(keys, order=3)
    ref = 2.0 + 3.0 * torch.cos(2 * math.pi * p - 0.4)
    assert (c(p) - ref).abs().max() < 0.01  # polyline of 64 keys, ~0.5% sag
    kc = KeyframeCurve([(0, 0), (0.5, 10), (0.7, 10), (1, 0)])
    assert torch.allclose(kc(torch.tensor([0.0, 0.5, 0.7, 1.0])), torch.tensor([0.0, 10.0, 10.0, 0.0], dtype=torch.float64))
    assert (kc(torch.linspace(0.5, 0.7, 20)) - 10).abs().max() < 1e-12  # a hold stays flat (no overshoot)
    assert kc(torch.tensor([-1.0, 2.0])).tolist() == [0.0, 0.0]
    w = window(torch.tensor([0.0, 0.3, 0.5, 0.9]), 0.2, 0.8, 0.1)
    assert w.tolist() == [0.0, 1.0, 1.0, 0.0]


# ------------------------------------------------------------------------------------------ posing


def test_posing_conventions_by_forward_kinematics():
    J0 = torch.tensor(CANONICAL_JOINTS, dtype=torch.float64)
    pb = PoseBuilder(1).leg("left", flex=D(40)).leg("right", flex=D(-20), knee=D(60))
    pb.arm("left", flex=D(90)).arm("right", abd=D(90), elbow=D(90))
    _, p = forward_kinematics(pb.rot, J0)
    p = p[0]
    assert p[J["left_knee"], 2] > 0.2  # hip flexion swings the thigh forward
    assert p[J["right_ankle"], 2] < -0.3  # knee flexion folds the shank backward
    assert p[J["left_wrist"], 2] - p[J["left_shoulder"], 2] > 0.45  # arm flexed to the front
    assert abs(p[J["left_wrist"], 1] - p[J["left_shoulder"], 1]) < 1e-6
    # right arm in T-pose, forearm bent 90 deg: forward, not up or down
    fore = p[J["right_wrist"]] - p[J["right_elbow"]]
    assert fore[2] > 0.24 and abs(fore[1]) < 1e-6
    # mirror_pose gives the mirror image (x -> -x, left <-> right)
    _, pm = forward_kinematics(mirror_pose(pb.rot), J0)
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    assert torch.allclose(pm[0][list(MIRROR)] * flip, p, atol=1e-12)


def test_level_foot_and_planted_abduction():
    n = 30
    knee = torch.linspace(0, D(110), n, dtype=torch.float64)
    pb = PoseBuilder(n).root(pitch=D(20), roll=D(5))
    pb.leg("left", flex=0.8 * knee, abd=D(10), knee=knee, dorsi=D(0), level=True, plant=True)
    g, j = forward_kinematics(pb.rot, torch.tensor(CANONICAL_JOINTS, dtype=torch.float64))
    foot = g[:, J["left_ankle"]]
    # level: the foot's up axis stays world up, whatever the root, hip and knee angles
    assert (foot[:, :, 1] - torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)).abs().max() < 1e-9
    # planted: the ankle's sideways offset from the hip, in the pelvis frame, matches the straight
    # leg's 2 L sin(abd) (independent naive check with thigh = shank = 1)
    R_root = pb.rot[:, 0]
    v = (R_root.transpose(-1, -2) @ (j[:, J["left_ankle"]] - j[:, J["left_hip"]])[..., None])[..., 0]
    L = 0.5 * (0.38 + 0.40)
    assert (v[:, 0] - 2 * L * math.sin(D(10))).abs().max() < 0.01


# ------------------------------------------------------------------------------------------ contact


def test_contact_solver_pins_the_lowest_point_and_flies_a_parabola():
    N = 241
    t = torch.linspace(0, 1, N, dtype=torch.float64)
    pts = torch.zeros(N, 2, 3, dtype=torch.float64)
    pts[:, 0, 1] = -0.9  # point 0 is the lowest: it moves backward at 1.5 m/s relative to the root
    pts[:, 0, 2] = -1.5 * t
    pts[:, 1, 1] = -0.5
    pts[:, 1, 0] = 2.0 * t  # point 1 is high up: its motion must not matter
    track = solve_root_track(t, pts, torch.zeros(N, dtype=torch.float64))
    assert torch.allclose(track.xz[:, 1], 1.5 * t, atol=1e-9)  # root moves forward 1.5 m/s
    assert track.xz[:, 0].abs().max() < 1e-9
    # flight from grid 60 to 180 (0.25 s .. 0.75 s): ballistic, continuous at both ends
    air = torch.zeros(N, dtype=torch.float64)
    air[61:180] = 1.0
    track = solve_root_track(t, pts, air)
    assert len(track.flights) == 1
    t0, t1, y0, v0 = track.flights[0].tolist()
    assert (t0, t1) == (0.25, 0.75) and y0 == pytest.approx(0.9)
    assert v0 == pytest.approx(GRAVITY * 0.5 / 2)  # same height at both ends
    ground = torch.full((N,), 0.9, dtype=torch.float64)
    y = track.height(t, ground)
    assert float(y.max()) == pytest.approx(0.9 + v0**2 / (2 * GRAVITY), abs=1e-4)
    assert float(y[60]) == pytest.approx(0.9) and float(y[180]) == pytest.approx(0.9)
    # horizontal velocity kept through the flight
    assert torch.allclose(track.xz[:, 1], 1.5 * t, atol=1e-9)


# ------------------------------------------------------------------------------------------ sequences


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_every_action_runs_and_stands_on_the_floor(name):
    dur = 2.8 if name == "cartwheel" else 2.0
    seq = SyntheticSequence(_plan([(name, dur, {})], seed=3), _skeleton())
    m = seq.to_motion(30)
    assert m.poses.shape == (m.num_frames, 22, 3) and torch.isfinite(m.poses).all()
    pts = _world_points(m, seq.skeleton)
    assert pts[..., 1].min() > -1e-4  # nothing below the floor
    assert pts[..., 1].amin(-1).max() < 0.45  # always near the floor (jump apex ~ 0.3 m)


def test_sample_is_vectorised_and_continuous_in_time():
    plan = _plan([("walk", 1.5, {}), ("run", 1.5, {}), ("boxing", 1.5, {}), ("jump", 2.0, {})], seed=5)
    seq = SyntheticSequence(plan, _skeleton())
    rng = np.random.default_rng(0)
    t = torch.tensor(rng.uniform(0, seq.duration - 1e-3, 300), dtype=torch.float64)
    poses, trans = seq.sample(t)
    # any order, one at a time or all together: the same values
    p1, tr1 = seq.sample(t[7:8])
    assert torch.allclose(p1[0], poses[7], atol=1e-9) and torch.allclose(tr1[0], trans[7], atol=1e-9)
    # small dt, small change (also across the three cross-fades and the jump's flight)
    dt = 1e-4
    t_all = torch.cat([t, torch.tensor([1.5, 3.0, 4.5], dtype=torch.float64) - dt / 2])
    a_p, a_t = seq.sample(t_all)
    b_p, b_t = seq.sample(t_all + dt)
    ang = roma.rotmat_geodesic_distance(roma.rotvec_to_rotmat(a_p), roma.rotvec_to_rotmat(b_p))
    assert ang.max() < 30 * dt  # joint rates stay below 30 rad/s
    assert (b_t - a_t).norm(dim=-1).max() < 12 * dt  # the root moves below 12 m/s
    with pytest.raises(ValueError, match="outside the sequence"):
        seq.sample(torch.tensor([seq.duration + 0.1]))


def test_transitions_are_continuous_on_a_dense_grid():
    plan = _plan([("idle", 1.0, {}), ("walk", 2.0, {}), ("sidestep", 1.5, {}), ("kick", 2.0, {})], seed=11)
    seq = SyntheticSequence(plan, _skeleton())
    t = torch.arange(0, seq.duration, 1 / 480, dtype=torch.float64)
    poses, trans = seq.sample(t)
    R = roma.rotvec_to_rotmat(poses)
    step = roma.rotmat_geodesic_distance(R[1:], R[:-1]).amax(-1)
    assert step.max() < 25 / 480
    assert (trans[1:] - trans[:-1]).norm(dim=-1).max() < 8 / 480


def test_feet_do_not_slide_or_go_through_the_floor():
    parts = [[("walk", 4.4, {})], [("run", 4.4, {})], [("boxing", 4.4, {})], [("sidestep", 4.4, {})]]
    motions = [SyntheticSequence(_plan(p, seed=i), _skeleton()).to_motion(50) for i, p in enumerate(parts)]
    fm = foot_metrics(motions)  # skeleton contact points from each motion's meta
    assert fm["worst_floor_penetration"] < 1e-4
    assert fm["median_stance_foot_speed"] < 0.03
    assert fm["stance_samples"] > 0.4 * 2 * fm["frames"]


def test_foot_metrics_against_hand_computed_values():
    T = 51
    t = torch.arange(T, dtype=torch.float64) / 50
    trans = torch.zeros(T, 3)
    trans[:, 0] = 0.5 * t.float()  # the whole body glides at 0.5 m/s: both feet slide
    trans[:, 1] = -0.02  # and stands 2 cm into the floor
    m = Motion(torch.zeros(T, 22, 3), trans, t, shape=torch.tensor(SUBJECT.phenotype), body="anny")
    fm = foot_metrics([m], body=CANON)
    assert fm["median_stance_foot_speed"] == pytest.approx(0.5, rel=1e-4)
    assert fm["worst_floor_penetration"] == pytest.approx(0.02, abs=1e-6)
    assert fm["stance_samples"] == 2 * T
    trans[:, 0] = 0.0
    trans[:, 1] = 0.05  # floating 5 cm: no stance at all
    fm = foot_metrics([Motion(torch.zeros(T, 22, 3), trans, t, shape=torch.tensor(SUBJECT.phenotype))], body=CANON)
    assert fm["stance_samples"] == 0 and fm["worst_floor_penetration"] == 0.0


# ------------------------------------------------------------------------------------------ splits


def test_test_split_composition():
    plans = split_plans("test")
    assert len(plans) == 170
    kinds = [p.kind for p in plans]
    assert {k: kinds.count(k) for k in set(kinds)} == TEST_COMPOSITION
    assert kinds.count("cartwheel") == 1
    assert sum("cartwheel" in [s.action for s in p.segments] for p in plans) == 1
    subjects = {p.subject.name: p.subject for p in plans}
    assert len(subjects) == 4
    assert sorted(s.sex for s in subjects.values()) == ["female", "female", "male", "male"]
    heights = {s.phenotype[4] for s in subjects.values()}
    weights = {s.phenotype[3] for s in subjects.values()}
    assert len(heights) >= 3 and len(weights) >= 3
    counts = [sum(p.subject.name == n for p in plans) for n in subjects]
    assert max(counts) - min(counts) <= 1
    assert all(p.duration >= 4.0 + 0.4 - 1e-9 for p in plans)
    assert splits_mod.SPLITS["test"].fps == 50.0
    # boxing, kicking, sidestepping, walking and running kinds all present
    actions = {s.action for p in plans for s in p.segments}
    assert {"boxing", "kick", "sidestep", "walk", "walk_backward", "walk_curved", "jog", "run", "cartwheel"} <= actions


def test_train_and_val_are_disjoint_from_test_and_cover_all_actions():
    train = split_plans("train")
    val = split_plans("val")
    test_names = {s.name for s in TEST_SUBJECTS}
    train_subj = {p.subject.name: p.subject.phenotype for p in train}
    val_subj = {p.subject.name: p.subject.phenotype for p in val}
    assert len(train_subj) == 12 and len(val_subj) == 2
    assert not (set(train_subj) & test_names) and not (set(val_subj) & test_names) and not (set(train_subj) & set(val_subj))
    test_ph = {s.phenotype for s in TEST_SUBJECTS}
    assert not (set(train_subj.values()) & test_ph)
    assert {s.action for p in train for s in p.segments} == set(ACTIONS)
    hours = sum(p.duration for p in train) / 3600
    assert 1.5 < hours < 4.0
    assert {p.seed for p in train}.isdisjoint({p.seed for p in split_plans("test")})


def test_test_split_motions_and_determinism():
    a = generate_split("test", CANON, limit=3)
    b = generate_split("test", CANON, limit=3)
    c = generate_split("test", CANON, seed=7, limit=3)
    for m in a:
        assert m.fps == pytest.approx(50.0) and m.duration >= 4.0
        assert m.body == "anny" and m.shape.shape == (6,)
        assert m.source.startswith("synthetic:test:")
        assert {"subject", "actions", "seed", "kind", "skeleton"} <= set(m.meta)
        assert tuple(m.shape.tolist()) == pytest.approx(next(s.phenotype for s in TEST_SUBJECTS if s.name == m.meta["subject"]))
        assert m.meta["actions"][0]["start"] == 0.0 and m.meta["actions"][-1]["end"] == pytest.approx(4.4)
    for x, y in zip(a, b):  # same seed: the same bytes
        assert x.poses.numpy().tobytes() == y.poses.numpy().tobytes()
        assert x.trans.numpy().tobytes() == y.trans.numpy().tobytes()
        assert content_digest(x) == content_digest(y)
    assert all(content_digest(x) != content_digest(z) for x, z in zip(a, c))  # another seed differs


def _tiny_split(monkeypatch):
    """A split "tiny" of two short sequences, registered for the test."""
    subjects = sample_subjects(2, 5, "tiny")
    spec = SplitSpec(
        "tiny", 5, 30.0, lambda seed: subjects,
        lambda subj, seed: splits_mod.plan_random_split(subj, seed, per_subject=1, duration=(2.0, 2.5)),
        "two short sequences",
    )
    monkeypatch.setitem(splits_mod.SPLITS, "tiny", spec)


def test_build_split_cache_roundtrip_and_rebuild(tmp_path, monkeypatch):
    _tiny_split(monkeypatch)
    first = build_split("tiny", body=CANON, root=tmp_path)
    folder = tmp_path / "tiny"
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["generator_version"] == GENERATOR_VERSION and manifest["seed"] == 5
    assert manifest["count"] == 2 and len(manifest["files"]) == 2
    mtimes = {f.name: f.stat().st_mtime_ns for f in folder.glob("*.npz")}
    again = build_split("tiny", body=CANON, root=tmp_path)  # from the cache: files untouched
    assert {f.name: f.stat().st_mtime_ns for f in folder.glob("*.npz")} == mtimes
    assert [content_digest(m) for m in again] == [content_digest(m) for m in first]
    # a generator-version change in the manifest triggers a rebuild, with the same content
    manifest["generator_version"] = "0-old"
    (folder / "manifest.json").write_text(json.dumps(manifest))
    rebuilt = build_split("tiny", body=CANON, root=tmp_path)
    assert json.loads((folder / "manifest.json").read_text())["generator_version"] == GENERATOR_VERSION
    assert [content_digest(m) for m in rebuilt] == [content_digest(m) for m in first]
    # a corrupted file fails its sha256 and is rebuilt
    victim = folder / manifest["files"][0]["file"]
    victim.write_bytes(b"not an npz")
    build_split("tiny", body=CANON, root=tmp_path)
    assert content_digest(Motion.load(victim)) == content_digest(first[0])


def test_two_processes_asking_for_an_unbuilt_split_build_it_once(tmp_path, monkeypatch):
    """`run table1` and `run sls` started together on a fresh checkout both built the test split into
    one folder, each deleting and rewriting the files the other was writing. The second now waits
    for the first and reads what it built (an flock; two threads hold separate open files, as two
    processes do)."""
    import threading
    import time

    _tiny_split(monkeypatch)
    real = splits_mod.generate_split
    calls = []

    def slow(*a, **k):
        calls.append(threading.get_ident())
        time.sleep(0.5)  # the other thread arrives while this one builds
        return real(*a, **k)

    monkeypatch.setattr(splits_mod, "generate_split", slow)
    results = [None, None]

    def ask(i):
        results[i] = build_split("tiny", body=CANON, root=tmp_path)

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
        time.sleep(0.1)
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert [content_digest(m) for m in results[0]] == [content_digest(m) for m in results[1]]
    assert (tmp_path / ".tiny.lock").exists() and json.loads((tmp_path / "tiny" / "manifest.json").read_text())["count"] == 2


def test_plan_errors_name_the_problem():
    with pytest.raises(ValueError, match="contiguous"):
        SequencePlan(SUBJECT, [Segment("walk", 0, 1.0), Segment("run", 1.2, 2.0)], seed=0)
    with pytest.raises(KeyError, match="did you mean"):
        SequencePlan(SUBJECT, [Segment("wlak", 0, 1.0)], seed=0)
    with pytest.raises(ValueError, match="phenotype"):
        Subject("x", (0.5, 0.5, 0.5))


# ------------------------------------------------------------------------------------------ body


def test_contact_points_from_the_embedded_body(anny_body):
    shape = torch.tensor(TEST_SUBJECTS[3].phenotype)
    sk = RestSkeleton.from_body(anny_body, shape)
    with torch.no_grad():
        rest = anny_body.prepare(shape[None])
        out = anny_body(torch.eye(3).expand(1, 1, 22, 3, 3), torch.zeros(1, 1, 3), rest=rest)
    v = out.vertices[0, 0].double()
    assert torch.allclose(sk.joints, rest.joints[0].double(), atol=1e-5)
    # the skinned contact points in the T-pose are mesh vertices, the lowest on the floor
    g, j = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(1, 22, 3, 3), sk.joints)
    p = sk.posed_points(g, j)[0]
    d = torch.cdist(p, v, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values
    assert d.max() < 1e-4
    assert abs(float(p[:, 1].min())) < 1e-5
    assert 0.05 < sk.ankle_sole < 0.1 and 0.02 < sk.toe_sole < 0.06
    # a short walk on this body's mesh: no vertex below the floor by more than 1 cm
    m = SyntheticSequence(_plan([("walk", 1.2, {})], subject=TEST_SUBJECTS[3]), sk).to_motion(25)
    fm = foot_metrics([m], body=anny_body)
    assert fm["worst_floor_penetration"] < 0.01
    assert fm["median_stance_foot_speed"] < 0.05


def test_body_skeleton_does_not_depend_on_the_thread_count(anny_body):
    """The splits are keyed by the skeleton's bits: a process on two threads and a worker on one must
    compute the same skeleton, or each rebuilds the other's split (seen: 1.9e-7 m apart)."""
    import torch

    from benchmark.synthetic.rest import BodySkeletons
    from benchmark.synthetic.splits import _skeleton_digest

    threads = torch.get_num_threads()
    digests = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            digests.append(_skeleton_digest("test", 0, BodySkeletons(anny_body)))
    finally:
        torch.set_num_threads(threads)
    assert digests[0] == digests[1]
    assert torch.get_num_threads() == threads


def test_build_split_never_deletes_files_it_did_not_write(tmp_path, monkeypatch):
    _tiny_split(monkeypatch)
    folder = tmp_path / "tiny"
    folder.mkdir()
    mine = folder / "my_capture.npz"
    mine.write_bytes(b"a user's own file")
    stale = folder / "tiny_0007.npz"  # what an interrupted build of the split leaves: its own name
    stale.write_bytes(b"partial")
    with pytest.raises(FileExistsError, match=r"my_capture\.npz.*MOTION_BENCHMARK_CACHE"):
        build_split("tiny", body=CANON, root=tmp_path)
    assert mine.read_bytes() == b"a user's own file" and stale.exists()
    mine.unlink()
    build_split("tiny", body=CANON, root=tmp_path, rebuild=True)  # its own files only: rebuilt
    assert not stale.exists() and sorted(p.name for p in folder.glob("*.npz")) == ["tiny_0000.npz", "tiny_0001.npz"]
