"""Mitsuba 3: differentiable rendering of the same mesh, cameras and lights, per-texel textures, its Adam.

The scene: texstream's mesh (positions, vertex normals, UVs; v flipped to Mitsuba's row order, so a
texture row is the same atlas row as texstream's grid), one ``perspective`` sensor per photo (the
photo's pose and focal length, ``stratified`` sampler without jitter at 1 sample per pixel and a box
filter: one ray through each pixel centre, as texstream's renderer and the synthetic photos have),
one ``point`` emitter moved to each photo's light (position and RGB intensity set through
``mi.traverse`` before each render), the ``prb`` integrator with ``max_depth`` 2 (direct light and
shadow rays: what the photos contain).

The BSDF is Mitsuba's ``principled`` with three textures on texstream's atlas grid, all optimised:
``base_color`` (RGB), ``roughness`` and ``metallic`` (one channel each); specular 0.5. It is not the
Lafortune model (a GGX microfacet lobe with Fresnel against a cosine lobe), so it is compared on what
both produce: held-out renders against the held-out photos (same foreground masks, same pooled
PSNR), with Mitsuba rendering its own model.

Optimisation: ``mi.ad.Adam`` (learning rate ``lr``), each step renders ``views_per_step`` training
views (a shuffled cycle through all of them), accumulates the gradient of the mean squared error over
their foreground pixels (photo mask, saturated pixels left out), steps, and clamps the textures to
their ranges. Start: base colour pi x texstream's initial diffuse guess (the percentile estimate all
Lafortune peers start from), roughness 0.3, metallic 0.
"""

from __future__ import annotations

import numpy as np

import time

from common import HeldOut, Recorder, build_problem, fit_config, schedule


def find_libllvm() -> str | None:
    """The newest libLLVM shared library on the system (Dr.Jit's LLVM backend needs LLVM >= 16 for the
    intrinsics Mitsuba 3.9 emits: with Debian 12's default LLVM 14 or 15 it aborts with "Cannot select
    fminimum"), or None."""
    import glob
    import re

    found = []
    for pattern in ("/usr/lib/x86_64-linux-gnu/libLLVM-*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM-*.so*",
                    "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib/x86_64-linux-gnu/libLLVM.so.*"):
        for path in glob.glob(pattern):
            m = re.search(r"LLVM[-.](?:so\.)?(\d+)", path) or re.search(r"llvm-(\d+)", path)
            if m:
                found.append((int(m.group(1)), path))
    return max(found)[1] if found else None


def prepare_llvm() -> None:
    """Point Dr.Jit at the newest libLLVM unless DRJIT_LIBLLVM_PATH is set already (before importing it)."""
    import os

    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        path = find_libllvm()
        if path:
            os.environ["DRJIT_LIBLLVM_PATH"] = path

ROUGHNESS0 = 0.3


def c2w_mitsuba(frame) -> np.ndarray:
    """Mitsuba's camera-to-world matrix of a frame (OpenCV world-to-camera R, t; Mitsuba's camera looks
    along +z with +x to the left and +y up, so OpenCV's x and y flip)."""
    R = np.asarray(frame.R, np.float64)
    t = np.asarray(frame.t, np.float64)
    m = np.eye(4)
    m[:3, :3] = R.T
    m[:3, 3] = -R.T @ t
    return m @ np.diag([-1.0, -1.0, 1.0, 1.0])


class MitsubaScene:
    """The mesh, a sensor per frame and one point light, with the three textures as parameters."""

    def __init__(self, data, base_color: np.ndarray, roughness: np.ndarray, metallic: np.ndarray, frames: list,
                 diffuse_only: bool = False):
        import drjit as dr
        import mitsuba as mi

        self.mi, self.dr = mi, dr
        mesh = data.scene.mesh
        V = np.asarray(mesh.vertices, np.float32)
        F = np.asarray(mesh.faces, np.uint32)
        N = np.asarray(mesh.vertex_normals(), np.float32)
        uv = np.asarray(mesh.uvs, np.float32).copy()
        uv[:, 1] = 1.0 - uv[:, 1]  # Mitsuba's texture row 0 is at v = 0, texstream's at v = 1
        tex = lambda a: {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(a, np.float32)), "raw": True,  # noqa: E731
                         "filter_type": "bilinear", "wrap_mode": "clamp"}
        bsdf = mi.load_dict({"type": "principled", "base_color": tex(base_color), "roughness": tex(roughness),
                             "metallic": tex(metallic), "specular": 0.5} if not diffuse_only else
                            {"type": "diffuse", "reflectance": tex(base_color)})  # the conventions' test
        props = mi.Properties()
        props["bsdf"] = bsdf
        m = mi.Mesh("ornament", V.shape[0], F.shape[0], props, True, True)
        mp = mi.traverse(m)
        mp["vertex_positions"] = mi.Float(V.ravel())
        mp["faces"] = mi.UInt32(F.ravel())
        mp["vertex_normals"] = mi.Float(N.ravel())
        mp["vertex_texcoords"] = mi.Float(uv.ravel())
        mp.update()
        self.scene = mi.load_dict({"type": "scene", "integrator": {"type": "prb", "max_depth": 2},
                                   "light": {"type": "point", "position": [0.0, 0.0, 0.0],
                                             "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
                                   "ornament": m})
        self.scoring = mi.load_dict({"type": "path", "max_depth": 2})
        self.params = mi.traverse(self.scene)
        self.keys = {"base_color": "ornament.bsdf.base_color.data", "roughness": "ornament.bsdf.roughness.data",
                     "metallic": "ornament.bsdf.metallic.data"}
        if diffuse_only:
            self.keys = {"base_color": "ornament.bsdf.reflectance.data"}
        self.params.keep(list(self.keys.values()) + ["light.position", "light.intensity.value"])
        self.sensors = [self.sensor(f) for f in frames]
        self.frames = frames

    def sensor(self, frame):
        mi = self.mi
        k = frame.intrinsics
        fov = float(np.degrees(2.0 * np.arctan(0.5 * k.width / k.fx)))
        return mi.load_dict({"type": "perspective", "fov": fov, "fov_axis": "x",
                             "to_world": mi.ScalarTransform4f(c2w_mitsuba(frame).tolist()),
                             "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                             "film": {"type": "hdrfilm", "width": int(k.width), "height": int(k.height),
                                      "rfilter": {"type": "box"}, "pixel_format": "rgb", "sample_border": False}})

    def set_light(self, frame) -> None:
        mi = self.mi
        self.params["light.position"] = mi.Point3f(*[float(x) for x in frame.light.position])
        self.params["light.intensity.value"] = mi.Color3f(*[float(x) for x in frame.light.intensity])
        self.params.update()

    def render(self, k: int, seed: int = 0):
        """Photo-space render (exposure applied) of frame k as a Dr.Jit tensor (H, W, 3)."""
        self.set_light(self.frames[k])
        img = self.mi.render(self.scene, self.params, sensor=self.sensors[k], spp=1, seed=seed)
        return img * float(self.frames[k].exposure)


def run(data, device: str, iterations: int, views_per_step: int = 8, lr: float = 0.02) -> dict:
    prepare_llvm()
    import drjit as dr
    import mitsuba as mi

    from texstream.fit.optim.fitter import initial_guess
    from texstream.fit.stages.stage import render_model

    mi.set_variant("cuda_ad_rgb" if device.startswith("cuda") else "llvm_ad_rgb")
    warp_device = device if device.startswith("cuda") else "cpu"
    if not device.startswith("cuda"):
        dr.set_thread_count(1)  # one core, like Warp's CPU kernels and the other CPU peers (docs/peers.md)
    cfg = fit_config(data, "bilinear")
    prob = build_problem(data, cfg, warp_device)
    lay = prob.layout
    bake = data.scene.bake
    lafortune = HeldOut(data, prob, lay, warp_device)
    # foreground of each held-out and validation view as texstream scores it: photo mask and render coverage
    neutral = lafortune.grid(lay.defaults()[None].repeat(prob.n, 0))
    held_masks = [render_model(data.scene.mesh, neutral, lay, f, warp_device)[1] & m
                  for f, m in zip(data.held_frames, data.held_masks)]
    val_masks = [render_model(data.scene.mesh, neutral, lay, f, warp_device)[1] & m
                 for f, m in zip(data.val_frames, data.val_masks)]
    train_masks = []
    for img, m, f in zip(data.train_images, data.train_masks, data.train_frames):
        sat = float(f.saturation) if f.saturation is not None else np.inf
        train_masks.append((m & (img.max(axis=2) < sat)).astype(np.float32))

    p0, _ = initial_guess(prob, cfg)
    base0 = lafortune.grid(np.clip(p0 * np.pi, 0.0, 1.0))[..., 0:3]  # rho_d columns: albedo = pi rho_d
    H, W = bake.height, bake.width
    ms = MitsubaScene(data, base0, np.full((H, W, 1), ROUGHNESS0), np.zeros((H, W, 1)), data.train_frames)
    photos = [mi.TensorXf(np.ascontiguousarray(im, np.float32)) for im in data.train_images]
    masks = [mi.TensorXf(np.ascontiguousarray(m[..., None].repeat(3, 2))) for m in train_masks]
    npix = [float(m.sum() * 3) for m in train_masks]
    bounds = {"base_color": (0.0, 1.0), "roughness": (0.02, 1.0), "metallic": (0.0, 1.0)}

    opt = mi.ad.Adam(lr=lr)
    for name, key in ms.keys.items():
        opt[key] = ms.params[key]
    ms.params.update(opt)
    rng = np.random.default_rng(0)
    order = []

    def step(it: int) -> float:
        total = 0.0
        for _ in range(views_per_step):
            if not order:
                order.extend(rng.permutation(len(ms.frames)).tolist())
            k = order.pop()
            img = ms.render(k, seed=it)
            loss = dr.sum(dr.square(img - photos[k]) * masks[k], axis=None) / (npix[k] * views_per_step)
            dr.backward(loss)
            total += float(loss.array[0]) if hasattr(loss, "array") else float(loss)
        opt.step()
        for name, key in ms.keys.items():
            opt[key] = dr.clip(opt[key], *bounds[name])
        ms.params.update(opt)
        return total

    def textures() -> dict:
        return {name: np.array(ms.params[key]) for name, key in ms.keys.items()}

    step(0)  # JIT compilation of the render and its adjoint (not timed); the run restarts from the start
    for name, key in ms.keys.items():
        start = {"base_color": base0, "roughness": np.full((H, W, 1), ROUGHNESS0), "metallic": np.zeros((H, W, 1))}[name]
        opt[key] = mi.TensorXf(np.ascontiguousarray(start, np.float32))
        opt.reset(key)  # Adam's moments back to zero
    ms.params.update(opt)
    order.clear()
    rng = np.random.default_rng(0)

    sync = dr.sync_thread
    rec = Recorder(sync)
    rec.start()
    snaps = schedule(iterations)
    rec.snap(0, np.zeros(1), textures=textures())
    for it in range(1, iterations + 1):
        loss = step(it)
        if it in snaps:
            rec.snap(it, np.zeros(1), textures=textures(), train_psnr_db=float(-10 * np.log10(max(loss, 1e-30))))

    trace, val_seconds = [], []
    for t, it, _, extra in rec.snaps:
        tx = extra.pop("textures")
        for name, key in ms.keys.items():
            ms.params[key] = mi.TensorXf(np.ascontiguousarray(tx[name], np.float32))
        ms.params.update()
        t0 = time.perf_counter()
        val_views = score_views(ms, data.val_frames, data.val_images, val_masks)
        val_seconds.append(time.perf_counter() - t0)
        views = score_views(ms, data.held_frames, data.held_images, held_masks)
        trace.append({"time_s": t, "iteration": it, "heldout_psnr_db": pooled_db(views),
                      "worst_psnr_db": float(min(views)), "val_psnr_db": pooled_db(val_views),
                      "val_worst_psnr_db": float(min(val_views)), **{k: v for k, v in extra.items()}})
    return {"trace": trace, "texels": int(H * W), "mitsuba": mi.__version__, "variant": mi.variant(),
            "settings": f"principled BSDF (base_color RGB, roughness, metallic textures {W}x{H}), prb max_depth 2, "
                        f"1 spp at pixel centres, mi.ad.Adam lr {lr}, {views_per_step} views per step, "
                        f"{iterations} steps", "val_check_s": float(np.median(val_seconds))}


def score_views(ms: MitsubaScene, frames: list, photos: list, masks: list) -> list[float]:
    """Per-view PSNR (dB) of Mitsuba's renders of its current textures against ``photos`` on ``masks``."""
    mi = ms.mi
    views = []
    for f, photo, mk in zip(frames, photos, masks):
        ms.set_light(f)
        # scored with the non-differentiable path tracer at the same depth (the same image for a point
        # light: its one light path is the emitter sample); prb's primal render of a new sensor after
        # the optimisation crashed the cuda_ad_rgb variant (segmentation fault, Mitsuba 3.9.1, H100)
        img = np.array(mi.render(ms.scene, sensor=held_sensor(ms, f), integrator=ms.scoring, spp=1)) * float(f.exposure)
        d = (img[mk] - photo[mk]).astype(np.float64)
        views.append(10 * np.log10(1.0 / max(float(np.mean(d * d)), 1e-30)))
    return views


def pooled_db(views: list[float]) -> float:
    """PSNR of the views' mean squared error (texstream's heldout_psnr pooling)."""
    return float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))


_HELD_SENSORS: dict = {}


def held_sensor(ms: MitsubaScene, frame):
    key = (id(ms), frame.file_path)
    if key not in _HELD_SENSORS:
        _HELD_SENSORS[key] = ms.sensor(frame)
    return _HELD_SENSORS[key]
