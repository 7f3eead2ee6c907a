"""The run report (python -m benchmark report): the stored fit arrays, the renderer, the page, and
the page in a real headless browser (skipped where Chromium and its driver are not installed).

One tiny table1 run is made per module: 1 prior x 2 cells of a copy of the table1 spec on two
handmade 2.2 s motions (2 s window, 2,000 points per capture frame, 3 optimiser steps)."""

import copy
import html.parser
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.core.motion import Motion


def _motion(seed: int, seconds: float = 2.2, fps: float = 50.0, subject: str = "s", turn: float = 0.4) -> Motion:
    """Smooth handmade motion: sinusoidal joint rotations, a slow turn, walking forward."""
    g = torch.Generator().manual_seed(seed)
    n = int(round(seconds * fps))
    t = torch.arange(n, dtype=torch.float64) / fps
    amp = torch.rand(22, 3, generator=g) * 0.3
    phase = torch.rand(22, 3, generator=g) * 2 * math.pi
    poses = amp * torch.sin(2 * math.pi * 1.2 * t[:, None, None].float() + phase)
    poses[:, 0] = torch.stack([torch.zeros(n), turn * t.float(), torch.zeros(n)], -1)
    trans = torch.stack([0.1 * t.float(), 0.9 + 0.02 * torch.sin(6 * t.float()), 0.9 * t.float()], -1)
    return Motion(poses=poses, trans=trans, timestamps=t, shape=torch.full((6,), 0.5), body="anny",
                  source=f"hand{seed}", meta={"subject": subject})


def tiny_spec() -> dict:
    spec = copy.deepcopy(load_table_spec("table1"))
    spec["grid"] = {"points": [100], "fps": [5, 10]}
    spec["data"].update({"window_s": 2.0, "points_per_frame": 2000})
    spec["paper"] = {"columns": ["100/5", "100/10"], "chamfer_mm": {"no-prior": [30.0, 25.0]}}
    # what the report reads and draws, not the fit's rules: the cheap version 1 start (no facing or
    # limb search, 40 s of this 3-step run) is enough
    spec["objective"] = {**spec["objective"], "facing": "heading8", "start_search": "none"}
    return spec


@pytest.fixture(scope="module")
def run_dir(anny_body, tmp_path_factory):
    from benchmark.run.table_run import run_table

    root = tmp_path_factory.mktemp("report_run")
    data = root / "data"
    for sid, m in {"a": _motion(1, subject="s1"), "b": _motion(2, subject="s2", turn=-0.3)}.items():
        m.save(data / f"{sid}.npz")
    profile = {**get_profile("smoke"), "sequences": 2, "steps": 3, "loss_vertices": 500, "surface_points": 100}
    out = run_table(tiny_spec(), profile, ["no-prior"], anny_body, "cpu", 0, root / "run", data=str(data))
    assert not out["failures"]
    return root / "run"


# ------------------------------------------------------------------------------ stored arrays
def test_units_store_the_scored_fit(run_dir, anny_body):
    """Each unit's .npz holds the very motion that was scored: re-skinning its fit against its
    ground truth gives the MPJPE of the unit JSON."""
    import roma

    from benchmark.data.unit_arrays import read_arrays

    units = sorted((run_dir / "units").glob("*.json"))
    assert len(units) == 2
    for path in units:
        unit = json.loads(path.read_text())
        arrays = read_arrays(path.with_suffix(".npz"))
        assert str(arrays["spec_hash"]) == unit["spec_hash"]
        assert list(arrays["sequence_ids"]) == unit["sequence_ids"]
        B, T = arrays["t"].shape
        assert arrays["fit_quat"].shape == (B, T, 22, 4) and arrays["fit_quat"].dtype == np.float32
        assert np.allclose(np.linalg.norm(arrays["fit_quat"], axis=-1), 1.0, atol=1e-5)
        assert arrays["obs_points"].shape[:2] == arrays["obs_t"].shape and arrays["obs_points"].shape[2] <= 128

        def joints(prefix):
            rot = roma.unitquat_to_rotmat(torch.from_numpy(arrays[f"{prefix}_quat"]))
            rest = anny_body.prepare(torch.from_numpy(arrays[f"{prefix}_shape"]))
            return anny_body.skin(rest, rot, torch.from_numpy(arrays[f"{prefix}_trans"])).joints

        with torch.no_grad():
            err = (joints("fit") - joints("gt")).norm(dim=-1).mean(-1)  # (B, T)
        for b, row in enumerate(unit["per_sequence"]):
            assert row["frames"] == T
            assert float(err[b].sum()) == pytest.approx(row["sums"]["mpjpe_m"], rel=2e-3, abs=1e-4)


def test_write_arrays_is_atomic_and_rejects_objects(tmp_path):
    from benchmark.data.unit_arrays import read_arrays, write_arrays

    path = write_arrays(tmp_path / "u.npz", {"a": np.arange(3, dtype=np.float32)})
    assert read_arrays(path)["a"].tolist() == [0, 1, 2]
    with pytest.raises(TypeError, match="not plain numpy arrays"):
        write_arrays(tmp_path / "v.npz", {"a": np.array([{}], dtype=object)})
    assert not (tmp_path / "v.npz").exists() and not list(tmp_path.glob(".*.tmp"))


# ------------------------------------------------------------------------------ renderer
def test_root_errors_flag_a_turned_fit():
    import roma

    from benchmark.core.fit_diagnostics import root_errors

    yaw = torch.tensor([0.0, 0.5, math.pi, 2.0])
    fit = roma.rotvec_to_rotmat(torch.stack([torch.zeros(4), yaw, torch.zeros(4)], -1)).double().numpy()
    gt = np.repeat(np.eye(3)[None], 4, 0)
    root, facing = root_errors(fit, gt)
    assert np.allclose(facing, np.degrees(yaw.numpy()), atol=1e-4)
    assert np.allclose(root, facing, atol=1e-4)
    tilt = roma.rotvec_to_rotmat(torch.tensor([[0.3, 0.0, 0.0]])).double().numpy()  # pitch only: same facing
    root, facing = root_errors(tilt, gt[:1])
    assert facing[0] == pytest.approx(0.0, abs=1e-4) and root[0] == pytest.approx(math.degrees(0.3), abs=1e-4)


def test_quat_to_rotmat_matches_roma():
    import roma

    from benchmark.report.animate import quat_to_rotmat

    q = roma.random_unitquat(50, generator=torch.Generator().manual_seed(0)).double()
    assert np.allclose(quat_to_rotmat(q.numpy()), roma.unitquat_to_rotmat(q).numpy(), atol=1e-12)


def test_splat_nearest_point_wins_like_a_naive_zbuffer():
    from benchmark.report.render import Camera, Canvas

    rng = np.random.default_rng(0)
    n = 400
    pts = rng.uniform(-0.15, 0.15, (n, 3))
    cols = rng.integers(0, 255, (n, 3)).astype(np.uint8)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))  # all facing the camera (view is -z)
    cam = Camera(np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, -1.0]))
    canvas = Canvas((24, 24), header=0)
    canvas.splat_mesh(0, cam, pts, normals, cols, np.zeros(3))
    # naive reference: every sample, nearest (smallest depth) first per pixel
    x, y, z = canvas.project(cam, pts, np.zeros(3))
    shade = 0.35 + 0.65 * np.abs(normals @ cam.view)
    expect = {}
    for i in np.argsort(z, kind="stable"):
        for dx in (0, 1):
            for dy in (0, 1):
                px, py = int(np.floor(x[i])) + dx, int(np.floor(y[i])) + dy
                if 0 <= px < 24 and 0 <= py < 24 and (py, px) not in expect:
                    expect[(py, px)] = (cols[i] * shade[i]).astype(np.uint8)
    img = canvas.view(0)
    assert expect
    for (py, px), c in expect.items():
        assert img[py, px].tolist() == c.tolist()


# ------------------------------------------------------------------------------ the page
class _Refs(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs, self.hrefs, self.ids, self.tables = [], [], set(), 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.srcs.append(a["src"])
        if tag == "a" and "href" in a:
            self.hrefs.append(a["href"])
        if "id" in a:
            self.ids.add(a["id"])
        self.tables += tag == "table"


def _check_page(index: Path) -> _Refs:
    refs = _Refs()
    refs.feed(index.read_text(encoding="utf-8"))
    assert refs.tables >= 4 and refs.srcs
    for src in refs.srcs:
        assert not src.startswith(("http:", "https:", "/")), src  # self-contained, relative
        assert (index.parent / src).is_file(), src
    for href in refs.hrefs:
        assert href.startswith("#") and href[1:] in refs.ids, href
    return refs


@pytest.fixture(scope="module")
def report(run_dir, tmp_path_factory):
    from benchmark.report import build_report

    return build_report(run_dir, tmp_path_factory.mktemp("report") / "rep", sequences=1)


def test_report_has_tables_plots_and_animations(report):
    from PIL import Image

    refs = _check_page(report)
    text = report.read_text(encoding="utf-8")
    assert "no-prior (paper)" in text and "Sequence breakdown" in text and "Diagnostics" in text
    anims = [s for s in refs.srcs if "anim__" in s]
    assert len(anims) == 2  # one sequence per cell
    for src in anims:
        path = report.parent / src
        assert path.stat().st_size < 400_000
        with Image.open(path) as im:
            assert im.n_frames == 30  # 2 s at 15 fps
            im.seek(10)
            assert np.asarray(im.convert("RGB")).std() > 10  # something drawn
    assert any("__vs_points" in s or "__vs_fps" in s for s in refs.srcs)
    assert any("__spread" in s for s in refs.srcs)


def test_report_of_a_run_without_stored_fits(run_dir, tmp_path):
    from benchmark.report import build_report

    old = tmp_path / "old_run"
    shutil.copytree(run_dir, old)
    for f in (old / "units").glob("*.npz"):
        f.unlink()
    index = build_report(old, sequences=1)
    assert index == old / "report" / "index.html"
    refs = _check_page(index)
    assert not [s for s in refs.srcs if "anim__" in s]
    text = index.read_text(encoding="utf-8")
    assert text.count("animation unavailable") == 2 and "no stored fit" in text


def test_a_column_shown_as_another_s_is_animated_once(run_dir, tmp_path):
    """A same_cells column (benchmark.run.same_cells) reads its source's units: no second rendering
    of the same files (two workers could write one file at once), and the page says where they are."""
    import copy as copy_

    from benchmark.report import build_report

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    path = run / "table1.json"
    table = json.loads(path.read_text())
    table["grid"]["fps"].append(20)
    for row in table["rows"]:
        cell = copy_.deepcopy(next(c for c in row["cells"] if c["fps"] == 10))
        row["cells"].append({**cell, "fps": 20, "same_as": {"fps": 10}, "units": 0})
    path.write_text(json.dumps(table))
    index = build_report(run, tmp_path / "r", sequences=1, workers=2)
    refs = _check_page(index)
    assert len([s for s in refs.srcs if "anim__" in s]) == 2  # the two computed cells', not three
    assert "the fits of column 10 fps: animated there" in index.read_text(encoding="utf-8")


def test_units_of_another_run_into_the_folder_are_not_shown_under_the_table(run_dir, tmp_path):
    """A later run into the folder under other settings (stopped before it wrote its table) leaves
    units that are not the table's: the report shows none of their numbers or fits under its cells."""
    from benchmark.data.unit_arrays import arrays_path
    from benchmark.report import build_report

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    unit_file = sorted((run / "units").glob("*.json"))[0]
    unit = json.loads(unit_file.read_text())
    for row in unit["per_sequence"]:
        row["sums"] = {k: 2.0 * v for k, v in row["sums"].items()}  # another fit of the same cell
    unit_file.write_text(json.dumps(unit))
    index = build_report(run, tmp_path / "r", sequences=1)
    text = index.read_text(encoding="utf-8")
    assert text.count("are not the ones table1.json was made from") == 1
    assert arrays_path(run, unit["unit_id"]).exists()  # the file is there; the page does not use it
    refs = _check_page(index)
    assert len([s for s in refs.srcs if "anim__" in s]) == 1  # the other cell's only


def test_a_failing_animation_is_said_on_the_page(run_dir, tmp_path):
    from benchmark.report import build_report

    index = build_report(run_dir, tmp_path / "r", sequences=1, body_spec="no-such-body")
    text = index.read_text(encoding="utf-8")
    assert text.count("failed: FileNotFoundError") == 2 and "no-such-body" in text and "anim__" not in text
    _check_page(index)


@pytest.mark.slow
def test_report_with_worker_processes(run_dir, tmp_path):
    from PIL import Image

    from benchmark.report import build_report

    index = build_report(run_dir, tmp_path / "r", sequences=1, workers=2)
    anims = [s for s in _check_page(index).srcs if "anim__" in s]
    assert len(anims) == 2
    for src in anims:
        with Image.open(index.parent / src) as im:
            assert im.n_frames == 30


def test_cli_report_and_its_errors(run_dir, tmp_path, capsys):
    from benchmark.cli import main

    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--sequences", "0"]) == 0
    assert (tmp_path / "r" / "index.html").is_file() and "wrote" in capsys.readouterr().out
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["report", str(empty)]) == 2
    assert "holds no table JSON" in capsys.readouterr().err


# ------------------------------------------------------------------------------ in a browser
def _chromium():
    for exe in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(exe)
        if path:
            return path
    return None


def test_report_in_headless_chromium(report):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    browser, driver_path = _chromium(), shutil.which("chromedriver")
    if not browser or not driver_path:
        pytest.skip("Chromium or chromedriver is not installed (apt-get install -y chromium chromium-driver)")
    from PIL import Image
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1300,1800",
                "--allow-file-access-from-files"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    os.environ.setdefault("SE_OFFLINE", "true")  # never let Selenium Manager look for downloads
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
    try:
        driver.set_page_load_timeout(60)
        driver.get(report.resolve().as_uri())
        driver.execute_async_script(
            "const done = arguments[arguments.length - 1];"
            "Promise.all([...document.images].map(i => i.decode().catch(() => null))).then(() => done(true));")
        state = driver.execute_script(
            "return {tables: document.querySelectorAll('table.results').length,"
            " images: [...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth]),"
            " links: [...document.querySelectorAll('a[href]')].map(a => [a.getAttribute('href'),"
            "   a.getAttribute('href').startsWith('#') ? !!document.getElementById(a.getAttribute('href').slice(1)) : null])};")
        errors = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
    assert not errors, errors
    assert state["tables"] >= 4
    assert state["images"] and all(ok and w > 0 for _, ok, w in state["images"]), state["images"]
    assert any("anim__" in src for src, _, _ in state["images"])
    assert state["links"] and all(ok for _, ok in state["links"]), [link for link in state["links"] if not link[1]]
    import io

    shot = np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=np.float32)
    assert shot.std() > 10 and (shot < 128).mean() > 0.005  # not blank: text and tables drawn


def test_a_motion_tables_cell_says_its_protocol_stores_no_motion(tmp_path):
    """The motion tables never store fitted motions: the report says so instead of asking for a rerun
    (which would store none either); a completion cell without its .npz still gets the rerun hint."""
    from types import SimpleNamespace

    from benchmark.report.cells import CellReport, diagnose

    for protocol, expected in (("inbetween", "the inbetween protocol stores no fitted motion"),
                               ("completion", "Rerun the table with --resume never")):
        run = SimpleNamespace(tables=[{"table": "t", "protocol": protocol}], npz_path=lambda u: tmp_path / "none.npz")
        cr = CellReport(table="t", prior="hmvae", cell={"gap": 5}, anchor="a", units=[{"unit_id": "t__hmvae__gap=5__b000"}])
        diagnose(run, cr, tmp_path, 1, "gif", None, 10.0, [])
        assert expected in cr.no_animation
