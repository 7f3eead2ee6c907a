"""A small CPU renderer for the report's animations: numpy splatting with a z-buffer, no OpenGL.

Each frame shows two orthographic views side by side, *front* (the camera faces the ground truth's
mean facing direction, so a fit that looks away shows its back) and *side* (90 degrees to the
left of it). The view follows the ground truth's root horizontally, so a drifting fit drifts out
of the frame. Drawn in each view:

- the fitted mesh, its face centroids splatted (2 x 2 pixels, nearest wins, back faces culled) and
  shaded by their normals, coloured by per-vertex error (distance to the same vertex of the
  ground-truth mesh, mm; a face takes the mean of its three vertices);
- the ground truth as a translucent skeleton (22 joints, 21 bones);
- the observed points of an observed frame, on the rendered frame nearest to its timestamp;
- a header with the time, the root-orientation error and, on frames where the fit faces more than
  90 degrees away from the ground truth, a red BACKWARDS banner and a red border.

Pure numpy + Pillow (text, encoding): runs headless anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


ERROR_MAX_MM = 200.0  # colour scale of per-vertex error: 0 .. ERROR_MAX_MM (clamped)
VIEW_HEIGHT_M = 2.3  # metres shown vertically
BACKGROUND = (246, 246, 246)
BACKWARDS_COLOUR = (215, 25, 28)
WEBP_QUALITY = 50  # lossy WebP: 250-300 kB for 60 frames of 2 x 140 x 190 pixels
WEBP_METHOD = 2  # encoder effort 0 (fast) .. 6 (small)


def error_lut(n: int = 256) -> np.ndarray:
    """(n, 3) uint8 colours of the error scale (matplotlib's 'turbo', the same as the legend)."""
    from matplotlib import colormaps

    return (colormaps["turbo"](np.linspace(0.0, 1.0, n))[:, :3] * 255).astype(np.uint8)


def face_samples(vertices: np.ndarray, faces: np.ndarray, values: np.ndarray):
    """Per face of (T, V, 3) vertices: centroids (T, F, 3), unit normals pointing outwards (the
    side away from the mesh's centroid, whatever the winding) and the mean of per-vertex ``values``
    (T, V). Face centroids are the splatted samples: denser than the vertices (two per quad), they
    leave no holes between the vertex rings of the limbs at the report's resolution."""
    import torch

    v = torch.from_numpy(np.ascontiguousarray(vertices, dtype=np.float32))
    f = torch.from_numpy(np.asarray(faces, dtype=np.int64))
    a, b, c = v[:, f[:, 0]], v[:, f[:, 1]], v[:, f[:, 2]]
    centroids = (a + b + c) / 3
    normals = torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a, dim=-1), dim=-1)
    if ((centroids[0] - v[0].mean(0)) * normals[0]).sum(-1).mean() < 0:
        normals = -normals
    val = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
    fval = (val[:, f[:, 0]] + val[:, f[:, 1]] + val[:, f[:, 2]]) / 3
    return centroids.numpy(), normals.numpy(), fval.numpy()


@dataclass
class Camera:
    """Orthographic camera: ``right``, ``up`` and ``view`` (into the scene) unit vectors."""

    right: np.ndarray
    up: np.ndarray
    view: np.ndarray


def cameras(facing: np.ndarray) -> tuple[Camera, Camera]:
    """Front and side cameras for a subject facing ``facing`` (horizontal, y up)."""
    f = np.array([facing[0], 0.0, facing[2]], dtype=np.float64)
    f = f / max(np.linalg.norm(f), 1e-9) if np.linalg.norm(f) > 1e-9 else np.array([0.0, 0.0, 1.0])
    up = np.array([0.0, 1.0, 0.0])
    front_view = -f  # the camera stands in front of the subject and looks back at it
    side_view = np.cross(up, f)  # looks at the subject's left side
    side_view /= np.linalg.norm(side_view)
    return (Camera(np.cross(front_view, up), up, front_view), Camera(np.cross(side_view, up), up, side_view))


class Canvas:
    """One animation frame: two views of ``size`` = (width, height) pixels side by side."""

    def __init__(self, size: tuple[int, int], header: int = 16):
        self.w, self.h = size
        self.header = header
        self.rgb = np.empty((header + self.h, 2 * self.w, 3), dtype=np.uint8)
        self.clear()

    def clear(self):
        self.rgb[:] = BACKGROUND

    def project(self, cam: Camera, points: np.ndarray, centre: np.ndarray):
        """Pixel columns, rows (floats, within one view) and depth of (N, 3) points."""
        s = self.h / VIEW_HEIGHT_M
        p = points - centre
        x = p @ cam.right * s + self.w / 2
        y = self.h / 2 - p @ cam.up * s
        return x, y, p @ cam.view

    def splat_mesh(self, view: int, cam: Camera, vertices, normals, colours, centre):
        """Z-buffered 2 x 2 splats of the camera-facing ones of (N, 3) surface samples (outward
        (N, 3) normals) with (N, 3) uint8 colours, Lambert-shaded."""
        facing = normals @ cam.view
        keep = facing < 0.1  # a little slack keeps the silhouette closed
        x, y, z = self.project(cam, vertices[keep], centre)
        col = (colours[keep] * (0.35 + 0.65 * np.abs(facing[keep]))[:, None]).astype(np.uint8)
        xi = np.floor(x).astype(np.int64)
        yi = np.floor(y).astype(np.int64)
        n = len(z)
        # depth rank (nearest first) in the low bits of one int64 key per pixel sample: one sort of
        # the keys groups the samples by pixel with the nearest first
        order = np.argsort(z, kind="stable")
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        xs = np.concatenate([xi, xi + 1, xi, xi + 1])
        ys = np.concatenate([yi, yi, yi + 1, yi + 1])
        rk = np.concatenate([rank] * 4)
        ok = (xs >= 0) & (xs < self.w) & (ys >= 0) & (ys < self.h)
        key = np.sort(((ys[ok] * self.w + xs[ok]) << 20) | rk[ok])
        first = np.ones(len(key), dtype=bool)
        first[1:] = (key[1:] >> 20) != (key[:-1] >> 20)
        key = key[first]
        pix, rk = key >> 20, key & ((1 << 20) - 1)
        self.view(view)[pix // self.w, pix % self.w] = col[order[rk]]

    def view(self, view: int) -> np.ndarray:
        return self.rgb[self.header:, view * self.w:(view + 1) * self.w]

    def dots(self, view: int, cam: Camera, points, centre, colour, alpha: float = 1.0, size: int = 1):
        x, y, _ = self.project(cam, points, centre)
        xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        img = self.view(view)
        for dx in range(size):
            for dy in range(size):
                xs, ys = xi + dx, yi + dy
                ok = (xs >= 0) & (xs < self.w) & (ys >= 0) & (ys < self.h)
                if alpha >= 1.0:
                    img[ys[ok], xs[ok]] = colour
                else:
                    old = img[ys[ok], xs[ok]].astype(np.float32)
                    img[ys[ok], xs[ok]] = (old * (1 - alpha) + np.asarray(colour, np.float32) * alpha).astype(np.uint8)

    def skeleton(self, view: int, cam: Camera, joints, parents, centre, colour=(20, 20, 20), alpha=0.55):
        """Bones as translucent dotted lines (12 samples per pixel of length) and joints as dots."""
        x, y, _ = self.project(cam, joints, centre)
        pts = []
        for j, p in enumerate(parents):
            if p < 0:
                continue
            n = int(max(abs(x[j] - x[p]), abs(y[j] - y[p]))) + 2
            a = np.linspace(0.0, 1.0, n)[:, None]
            pts.append(joints[p] * (1 - a) + joints[j] * a)
        if pts:
            self.dots(view, cam, np.concatenate(pts), centre, colour, alpha)
        self.dots(view, cam, joints, centre, colour, alpha, size=2)

    def floor(self, view: int, cam: Camera, centre, height: float = 0.0):
        row = int(self.h / 2 - (height - centre[1]) * self.h / VIEW_HEIGHT_M)
        if 0 <= row < self.h:
            self.view(view)[row, :] = (200, 200, 200)

    def border(self, colour, width: int = 3):
        self.rgb[:width], self.rgb[-width:] = colour, colour
        self.rgb[:, :width], self.rgb[:, -width:] = colour, colour


def render_frames(fit_vertices, gt_vertices, faces, gt_joints, parents, root_err, facing_err, t, obs_t=None,
                  obs_points=None, obs_lengths=None, size=(150, 200), title: str = "") -> list:
    """PIL images of one sequence: fitted and ground-truth vertices (T, V, 3) metres, ground-truth
    joints (T, 22, 3), per-frame root and facing errors (degrees), output timestamps t (T,)."""
    from PIL import Image, ImageDraw, ImageFont

    T = len(t)
    lut = error_lut()
    err_mm = np.linalg.norm(fit_vertices - gt_vertices, axis=-1) * 1000.0  # (T, V)
    samples, normals, face_err = face_samples(fit_vertices, faces, err_mm)
    cidx = np.clip(face_err / ERROR_MAX_MM * (len(lut) - 1), 0, len(lut) - 1).astype(np.int64)
    gt_root = gt_joints[:, 0]
    facing = heading_mean(gt_vertices, gt_joints)
    cams = cameras(facing)
    mid_y = float(np.median(gt_vertices[..., 1].max(-1) + gt_vertices[..., 1].min(-1)) / 2)
    floor_y = float(gt_vertices[..., 1].min())
    canvas = Canvas(size)
    try:
        font = ImageFont.load_default(size=11)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    # each observed frame is drawn on the rendered frame nearest to its timestamp
    shown = np.full(len(obs_t) if obs_t is not None else 0, -1)
    if obs_points is not None and len(t):
        near = np.abs(np.asarray(obs_t, dtype=np.float64)[:, None] - t[None]).argmin(1)
        ok = np.abs(t[near] - obs_t) <= 0.5 / max(_rate(t), 1e-9) + 1e-6
        shown = np.where(ok, near, -1)
    frames = []
    for i in range(T):
        canvas.clear()
        centre = np.array([gt_root[i, 0], mid_y, gt_root[i, 2]])
        for v, cam in enumerate(cams):
            canvas.floor(v, cam, centre, floor_y)
            canvas.splat_mesh(v, cam, samples[i], normals[i], lut[cidx[i]], centre)
            canvas.skeleton(v, cam, gt_joints[i], parents, centre)
            for k in np.flatnonzero(shown == i):
                pts = obs_points[k, : int(obs_lengths[k])].astype(np.float64)
                canvas.dots(v, cam, pts, centre, (0, 0, 0), 1.0, size=2)
        backwards = facing_err[i] > 90.0
        if backwards:
            canvas.rgb[:canvas.header] = BACKWARDS_COLOUR
            canvas.border(BACKWARDS_COLOUR)
        img = Image.fromarray(canvas.rgb)
        draw = ImageDraw.Draw(img)
        text = f"{title}  t={t[i]:.2f}s  root {root_err[i]:.0f}°"
        draw.text((4, 2), text + ("  BACKWARDS" if backwards else ""), fill=(255, 255, 255) if backwards else (0, 0, 0),
                  font=font)
        draw.text((4, canvas.header + 2), "front", fill=(90, 90, 90), font=font)
        draw.text((canvas.w + 4, canvas.header + 2), "side", fill=(90, 90, 90), font=font)
        draw.line([(canvas.w, canvas.header), (canvas.w, canvas.rgb.shape[0])], fill=(180, 180, 180))
        frames.append(img)
    return frames


def heading_mean(gt_vertices, gt_joints) -> np.ndarray:
    """The ground truth's mean facing direction from its hips and shoulders (robust to the body
    model's axes): the horizontal normal of the left-right axis, on the side the chest points."""
    from benchmark.core.skeleton import JOINT_INDEX

    lr = (gt_joints[:, JOINT_INDEX["left_hip"]] - gt_joints[:, JOINT_INDEX["right_hip"]]
          + gt_joints[:, JOINT_INDEX["left_shoulder"]] - gt_joints[:, JOINT_INDEX["right_shoulder"]])
    lr = lr.mean(0)
    fwd = np.cross(lr, np.array([0.0, 1.0, 0.0]))  # for y up, z forward, x left: (x) x (y) = z
    return fwd


def _rate(t: np.ndarray) -> float:
    return 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 30.0


def save_animation(frames: list, path, fps: float) -> str:
    """Write ``frames`` as an animated WebP (when Pillow has WebP) or GIF; returns the format."""
    from PIL import features

    duration = int(round(1000.0 / fps))
    path = str(path)
    if path.endswith(".webp"):
        if not features.check("webp"):
            raise RuntimeError("Pillow was built without WebP support; use a .gif path")
        frames[0].save(path, save_all=True, append_images=frames[1:], duration=duration, loop=0, quality=WEBP_QUALITY,
                       method=WEBP_METHOD)
        return "webp"
    pal = [f.convert("P", palette=1, colors=64, dither=0) for f in frames]  # 1 = Image.ADAPTIVE
    pal[0].save(path, save_all=True, append_images=pal[1:], duration=duration, loop=0, optimize=False, disposal=1)
    return "gif"
