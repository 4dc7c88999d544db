"""Leave-one-out study: how well per-pixel predictors built from the other photos reproduce each photo
of a posed capture on its mesh (the question behind the view-dependent radiance model, fit/models.py).

    python benchmarks/view_dependence_loo.py POSED_CAPTURE MESH [--json OUT.json]

For every photo in turn: its foreground pixels' surface points (the mesh's depth map), the other photos
sampled there (visible by depth, inside their masks, bilinear, divided by their exposure), and
predictions of the held-out pixel:

- ``average``: the plain average (what texture bakers store);
- ``cos``: weighted by the cosine between the view and the face normal;
- ``view8``, ``view20``: weighted by closeness of the view directions, exp(s (cos angle - 1)) (view-dependent
  texture mapping);
- ``linear``, ``biquadratic``: a per-pixel polynomial of the local view direction (the biquadratic is the
  view_radiance model) with a ridge prior on the view terms.

Prints PSNR per photo and pooled (PSNR of the pixel-weighted mean squared error). numpy and warp only,
no fit: it measures the photos and the mesh, not the optimizer.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img sampled at continuous pixel coordinates (centres at integers), clamped to the image."""
    h, w = img.shape[:2]
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
            + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))


class Capture:
    """The photos (linear, per unit exposure), masks, depth and face maps and face normals of a posed capture."""

    def __init__(self, capture_dir: Path, mesh_path: Path):
        from texstream.capture.capture_json import read_capture
        from texstream.capture.imageio import read_image, read_mask
        from texstream.geometry.mesh_io import load_mesh
        from texstream.geometry.visibility import Visibility

        cap = read_capture(capture_dir)
        mesh = load_mesh(mesh_path)
        self.frames = cap.frames
        self.images = [read_image(cap.image_path(f), channels=3) / f.exposure for f in self.frames]
        self.masks = [read_mask(cap.mask_path(f), im.shape[:2]) for f, im in zip(self.frames, self.images)]
        vis = Visibility(mesh, "cpu")
        self.depths, self.faces = zip(*[vis.render(f) for f in self.frames])
        v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        self.face_normals = n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-12)

    def pixels(self, h: int):
        """Foreground pixels of photo h: (photo values (N, 3), surface points, normals facing the camera,
        unit directions to the camera)."""
        f, k = self.frames[h], self.frames[h].intrinsics
        d = self.depths[h]
        jj, ii = np.nonzero(np.isfinite(d) & self.masks[h])
        z = d[jj, ii]
        cam = np.stack([(ii + 0.5 - k.cx) / k.fx * z, (jj + 0.5 - k.cy) / k.fy * z, z], 1)
        points = (cam - f.t.reshape(3)) @ f.R  # world = R^T (camera - t)
        to_cam = f.center - points
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        normals = self.face_normals[self.faces[h][jj, ii]]
        normals = np.where((np.sum(normals * to_cam, 1) < 0)[:, None], -normals, normals)
        return self.images[h][jj, ii], points, normals, to_cam

    def samples(self, k: int, points: np.ndarray, normals: np.ndarray):
        """Photo k at the points: (usable (N,), values (N, 3), unit directions to its camera)."""
        g, kk = self.frames[k], self.frames[k].intrinsics
        pc = points @ g.R.T + g.t.reshape(3)
        x = kk.fx * pc[:, 0] / pc[:, 2] + kk.cx - 0.5
        y = kk.fy * pc[:, 1] / pc[:, 2] + kk.cy - 0.5
        ok = (pc[:, 2] > 0) & (x >= 0) & (y >= 0) & (x < kk.width - 1) & (y < kk.height - 1)
        xi = np.clip(np.round(x).astype(int), 0, kk.width - 1)
        yi = np.clip(np.round(y).astype(int), 0, kk.height - 1)
        ok &= (pc[:, 2] <= self.depths[k][yi, xi] * (1 + 5e-3)) & self.masks[k][yi, xi]
        to_cam = g.center - points
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        ok &= np.sum(normals * to_cam, 1) > 0.05  # the fit's default grazing limit
        return ok, bilinear(self.images[k], x, y), to_cam


def view_features(view: np.ndarray, normals: np.ndarray, order: int) -> np.ndarray:
    """(1, v_x, v_y[, v_x^2, v_x v_y, v_y^2]) of the view in a tangent frame around the normal."""
    axis = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t = np.cross(normals, axis)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normals, t)
    x, y = np.sum(view * t, 1), np.sum(view * b, 1)
    cols = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if order >= 2 else [])
    return np.stack(cols, 1)


def predict(cap: Capture, h: int):
    """Every predictor's values for the foreground pixels of photo h from the other photos, and the truth."""
    truth, points, normals, view = cap.pixels(h)
    weighted = {"average": lambda c, a: np.ones_like(c), "cos": lambda c, a: c,
                "view8": lambda c, a: np.exp(8 * (a - 1)), "view20": lambda c, a: np.exp(20 * (a - 1))}
    num = {k: np.zeros_like(truth) for k in weighted}
    den = {k: np.zeros(len(points)) for k in weighted}
    polys = {"linear": (1, 0.1, True), "biquadratic": (2, 0.5, False)}  # order, ridge, ridge x sample count
    normal_eq = {k: (np.zeros((len(points), 3 + 3 * (o - 1), 3 + 3 * (o - 1))),
                     np.zeros((len(points), 3 + 3 * (o - 1), 3))) for k, (o, _, _) in polys.items()}
    count = np.zeros(len(points))
    for k in range(len(cap.frames)):
        if k == h:
            continue
        ok, values, to_cam = cap.samples(k, points, normals)
        cos_view, cos_between = np.sum(normals * to_cam, 1), np.sum(to_cam * view, 1)
        for name, weight in weighted.items():
            w = weight(cos_view, cos_between) * ok
            num[name] += w[:, None] * values
            den[name] += w
        for name, (order, _, _) in polys.items():
            phi = view_features(to_cam, normals, order) * ok[:, None]
            normal_eq[name][0][:] += phi[:, :, None] * phi[:, None, :]
            normal_eq[name][1][:] += phi[:, :, None] * values[:, None, :]
        count += ok
    out = {name: num[name] / np.maximum(den[name], 1e-12)[:, None] for name in weighted}
    for name, (order, ridge, per_sample) in polys.items():
        a, b = normal_eq[name]
        prior = ridge * np.eye(a.shape[1])
        prior[0, 0] = 1e-9  # the radiance along the normal is free
        a = a + prior[None] * (np.maximum(count, 1)[:, None, None] if per_sample else 1.0)
        coef = np.linalg.solve(a, b)
        out[name] = np.einsum("nf,nfc->nc", view_features(view, normals, order), coef)
    return out, truth, count > 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", type=Path, help="posed capture folder (capture.json)")
    ap.add_argument("mesh", type=Path, help="the mesh in the capture's frame")
    ap.add_argument("--json", type=Path, default=None, help="write the per-view and pooled PSNR here")
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    cap = Capture(args.capture, args.mesh)
    err: dict[str, dict[str, tuple[float, int]]] = {}
    for h, f in enumerate(cap.frames):
        preds, truth, have = predict(cap, h)
        err[f.name] = {k: (float(((p - truth) ** 2)[have].sum()), int(have.sum()) * 3) for k, p in preds.items()}
    names = list(next(iter(err.values())))
    psnr = {v: {k: 10 * np.log10(n / s) for k, (s, n) in row.items()} for v, row in err.items()}
    pooled = {k: 10 * np.log10(sum(r[k][1] for r in err.values()) / sum(r[k][0] for r in err.values())) for k in names}
    print("view", *names)
    for v, row in psnr.items():
        print(v, *[f"{row[k]:.2f}" for k in names])
    print("POOLED", *[f"{pooled[k]:.2f}" for k in names])
    if args.json:
        args.json.write_text(json.dumps({"per_view": psnr, "pooled": pooled}, indent=2))


if __name__ == "__main__":
    main()
