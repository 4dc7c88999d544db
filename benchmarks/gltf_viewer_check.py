"""An exported glb as independent viewers show it: three.js (Debian's libjs-three, r111) in headless Chromium, and
optionally Blender's Cycles (PyPI's bpy), with a photo's camera and point light, scored against the photo and
against texstream's own render (JSON + a side-by-side PNG: photo, texstream, three.js linear / gamma 2.2 / r111
defaults, Blender).

    apt-get install -y libjs-three          # /usr/share/javascript/three; chromium at /usr/bin/chromium
    python3 -m venv V && V/bin/pip install bpy                    # optional: Blender 5 as a Python module
    python benchmarks/gltf_viewer_check.py EXPORT/model.glb CAPTURE MODEL --frame frame_00007 \\
        --blender V/bin/python --out benchmarks/results/gltf_viewer_cpu

Why this is an independent check: the page is three.js's GLTFLoader and MeshStandardMaterial, nothing of
texstream's; three.js r111 reads the core metallic-roughness material and ignores KHR_materials_specular (a core-only
viewer). The Python side only serves the files, places the camera and light, and reads the pixels back.

How: a local HTTP server (stdlib) serves three.js, GLTFLoader.js, the glb and a page; Chromium (headless, WebGL on
SwiftShader) opens the page, which loads the glb, sets the camera from the frame's pinhole intrinsics and pose
(the projection matrix built from fx, fy, cx, cy, so pixel centres match texstream's rays) and a PointLight at
the frame's light (decay 2, physically correct lights: irradiance = intensity / r^2, texstream's convention, so
the glTF light's candela equal capture.json's radiant intensity), renders one frame and POSTs the pixels back.
Renders (``--variants``):

- ``linear``: the scene into a float render target (linear, unclipped, no output encoding): the material as the
  viewer shades it, without the canvas's 8 bits and encoding. The headline number.
- ``gamma22``: the canvas as three.js r111's glTF set-up shows it (renderer.gammaOutput = true, gammaFactor
  = 2.2: r111 has no renderer.outputEncoding, which came in r112; its "sRGB output" is a 2.2 power), read back
  in 8 bits and decoded with the same power; scored twice more as ``gamma22_as_srgb``: the same bytes decoded
  as an sRGB display shows them.
- ``r111_defaults``: the canvas with r111's default output (linear values written to the canvas, no encoding),
  decoded as sRGB, as a display shows them: what a page written for newer three.js gets from r111
  (``renderer.outputEncoding = sRGBEncoding`` does not exist there).
- ``legacy_lights``: ``linear`` without physicallyCorrectLights (r111's default: irradiance multiplied by pi and
  no 1/r^2 falloff for a light of distance 0): the light units a viewer's default gives.
- ``shadows``: ``linear`` with a shadow-casting point light (cube shadow map), as texstream's renderer casts
  shadows.
- ``no_mipmaps``: ``linear`` with every texture's minification filter linear without mipmaps (r111 resizes a
  non-power-of-two texture to the power of two below when mipmaps are asked for, WebGL 1).

With ``--blender PY`` (a Python with PyPI's ``bpy``): Blender's Cycles, whose glTF importer reads
KHR_materials_specular (Principled BSDF's Specular Tint), renders the glb in a subprocess (direct light only, no
world light, a point light of radius 0 and 4 pi x intensity watts, checked on a Lambertian plane by
:func:`blender_calibration`), with Principled's multiple-scattering GGX and with single-scattering GGX.

Scores (PSNR, peak 1, over the foreground: texstream's render coverage, the photo's mask and the viewer's
coverage): against the photo, and against texstream's render of the model folder (render/renderer.py, shadows
on). docs/export.md has the README demo's numbers.
"""

from __future__ import annotations

import argparse
import base64
import http.server
import json
import math
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

THREE = Path("/usr/share/javascript/three")
VARIANTS = ("linear", "gamma22", "r111_defaults", "legacy_lights", "shadows", "no_mipmaps")

BLENDER_SCRIPT = r"""
import json, math, sys
import bpy
import addon_utils  # Blender's own module, importable once bpy is
from mathutils import Matrix
p = json.loads(open(sys.argv[-1]).read())
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable("io_scene_gltf2")
sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.cycles.samples = p["samples"]
sc.cycles.use_denoising = False
sc.cycles.max_bounces = 0  # direct light only, as texstream's renderer
sc.cycles.filter_width = 0.01  # samples at the pixel centre, as texstream's one ray per pixel
sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = p["width"], p["height"], 100
sc.render.film_transparent = True
sc.view_settings.view_transform = "Standard"
sc.world = bpy.data.worlds.new("black")
sc.world.color = (0.0, 0.0, 0.0)
if sc.world.node_tree is not None:  # a new world may come with a grey background node: no ambient light here
    for n in sc.world.node_tree.nodes:
        if n.type == "BACKGROUND":
            n.inputs["Strength"].default_value = 0.0
if p["scene"] == "calibration":  # a Lambertian plane of albedo 0.5 (specular off) at the origin, facing +z
    bpy.ops.mesh.primitive_plane_add(size=p["plane_size"])
    mat = bpy.data.materials.new("lambert")
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bpy.context.object.data.materials.append(mat)
else:
    bpy.ops.import_scene.gltf(filepath=p["glb"])  # glTF's +y up back to Blender's +z: texstream's world frame
    for m in bpy.data.materials:
        for n in m.node_tree.nodes:
            if n.type == "BSDF_PRINCIPLED":
                n.distribution = p["distribution"]
cam = bpy.data.cameras.new("cam")
cam.sensor_fit, cam.sensor_width = "HORIZONTAL", 36.0
cam.lens = p["fx"] * 36.0 / p["width"]
cam.shift_x = (p["width"] / 2 - p["cx"]) / p["width"]
cam.shift_y = (p["cy"] - p["height"] / 2) / p["width"]
cam.clip_start, cam.clip_end = p["near"], p["far"]
cam_obj = bpy.data.objects.new("cam", cam)
cam_obj.matrix_world = Matrix([p["camera_to_world"][4 * i:4 * i + 4] for i in range(4)])
sc.collection.objects.link(cam_obj)
sc.camera = cam_obj
light = bpy.data.lights.new("flash", "POINT")
light.energy, light.color = p["light_watts"], p["light_color"]
light.shadow_soft_size = 0.0
light_obj = bpy.data.objects.new("flash", light)
light_obj.location = p["light_position"]
sc.collection.objects.link(light_obj)
sc.render.image_settings.file_format = "OPEN_EXR"
sc.render.image_settings.color_depth = "32"
sc.render.filepath = p["out"]
bpy.ops.render.render(write_still=True)
"""

PAGE = r"""<!doctype html><html><head><meta charset="utf-8"></head><body>
<script src="three.js"></script><script src="GLTFLoader.js"></script>
<script>
function post(obj) { var x = new XMLHttpRequest(); x.open('POST', 'result', true); x.send(JSON.stringify(obj)); }
window.onerror = function (m, s, l) { post({error: m + ' at ' + s + ':' + l}); };
fetch('params.json').then(function (r) { return r.json(); }).then(function (p) {
  var W = p.width, H = p.height, v = p.variant;
  var canvas = document.createElement('canvas'); canvas.width = W; canvas.height = H;
  document.body.appendChild(canvas);
  var renderer = new THREE.WebGLRenderer({canvas: canvas, antialias: false, preserveDrawingBuffer: true, alpha: true});
  renderer.setPixelRatio(1); renderer.setSize(W, H, false);
  renderer.physicallyCorrectLights = (v !== 'legacy_lights');
  renderer.gammaOutput = (v === 'gamma22'); renderer.gammaFactor = 2.2;
  renderer.toneMapping = THREE.NoToneMapping;
  renderer.setClearColor(0x000000, 0);
  renderer.shadowMap.enabled = (v === 'shadows');
  var scene = new THREE.Scene();
  var light = new THREE.PointLight(new THREE.Color(p.light_color[0], p.light_color[1], p.light_color[2]),
                                   p.light_intensity, 0, 2);
  light.position.set(p.light_position[0], p.light_position[1], p.light_position[2]);
  if (v === 'shadows') { light.castShadow = true; light.shadow.mapSize.set(2048, 2048);
    light.shadow.camera.near = p.near; light.shadow.camera.far = p.far; light.shadow.bias = -p.shadow_bias; }
  scene.add(light);
  var camera = new THREE.Camera();
  camera.matrixAutoUpdate = false;
  camera.matrix.fromArray(p.camera_to_world); camera.matrixWorld.copy(camera.matrix);
  camera.projectionMatrix.fromArray(p.projection);
  camera.projectionMatrixInverse.getInverse(camera.projectionMatrix);
  new THREE.GLTFLoader().load('model.glb', function (gltf) {
    var info = {};
    gltf.scene.traverse(function (o) {
      if (!o.isMesh) return;
      o.castShadow = o.receiveShadow = (v === 'shadows');
      var m = o.material;
      info = {type: m.type, metalness: m.metalness, roughness: m.roughness,
              map_encoding: m.map ? m.map.encoding : null, map_size: m.map ? [m.map.image.width, m.map.image.height] : null};
      if (v === 'no_mipmaps') ['map', 'metalnessMap', 'roughnessMap'].forEach(function (k) {
        if (m[k]) { m[k].minFilter = THREE.LinearFilter; m[k].generateMipmaps = false; m[k].needsUpdate = true; } });
    });
    scene.add(gltf.scene);
    var pixels, gl = renderer.getContext();
    if (v !== 'gamma22' && v !== 'r111_defaults') {
      var rt = new THREE.WebGLRenderTarget(W, H, {type: THREE.FloatType, format: THREE.RGBAFormat,
                                                  minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter});
      renderer.setRenderTarget(rt); renderer.render(scene, camera);
      var f = new Float32Array(W * H * 4); renderer.readRenderTargetPixels(rt, 0, 0, W, H, f);
      pixels = new Uint8Array(f.buffer); renderer.setRenderTarget(null);
    } else {
      renderer.render(scene, camera);
      pixels = new Uint8Array(W * H * 4); gl.readPixels(0, 0, W, H, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    }
    var s = ''; for (var i = 0; i < pixels.length; i += 32768) s += String.fromCharCode.apply(null, pixels.subarray(i, i + 32768));
    post({pixels: btoa(s), float: pixels.length === W * H * 16, material: info, revision: THREE.REVISION});
  }, undefined, function (e) { post({error: 'GLTFLoader: ' + e}); });
});
</script></body></html>"""


def projection(fx: float, fy: float, cx: float, cy: float, w: int, h: int, near: float, far: float) -> np.ndarray:
    """OpenGL projection of a pinhole camera (capture convention: pixel centres at +0.5, rows down), column-major."""
    p = np.zeros((4, 4))
    p[0, 0], p[0, 2] = 2 * fx / w, 1 - 2 * cx / w
    p[1, 1], p[1, 2] = 2 * fy / h, 2 * cy / h - 1
    p[2, 2], p[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
    p[3, 2] = -1.0
    return p.T.reshape(-1)


def scene_params(frame, up: np.ndarray, near: float, far: float) -> dict:
    """The page's camera and light for a capture frame, in the glb's world (the export's node turns z up to y up:
    ``up`` (3, 3)); the camera-to-world in OpenGL axes as three.js's Camera wants it."""
    from texstream.capture.conventions import w2c_cv_to_c2w_gl

    k = frame.intrinsics
    u4 = np.eye(4)
    u4[:3, :3] = up
    c2w = u4 @ w2c_cv_to_c2w_gl(frame.R, frame.t)
    inten = np.asarray(frame.light.intensity, np.float64)
    peak = float(inten.max())
    return {"width": int(k.width), "height": int(k.height),
            "camera_to_world": c2w.T.reshape(-1).tolist(),
            "projection": projection(k.fx, k.fy, k.cx, k.cy, k.width, k.height, near, far).tolist(),
            "light_position": (up @ np.asarray(frame.light.position, np.float64)).tolist(),
            "light_intensity": peak, "light_color": (inten / peak).tolist(), "near": near, "far": far,
            "shadow_bias": 1e-3}


class _Server(http.server.ThreadingHTTPServer):
    files: dict
    result: dict | None = None
    done: threading.Event


class _Handler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):  # quiet
        pass

    def do_GET(self):
        body = self.server.files.get(self.path.split("?")[0].lstrip("/"))
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self):
        data = self.rfile.read(int(self.headers["Content-Length"]))
        self.send_response(200)
        self.end_headers()
        self.server.result = json.loads(data)
        self.server.done.set()


def render_in_chromium(glb: Path, params: dict, chromium: str = "chromium", timeout_s: float = 120.0) -> dict:
    """Render the glb in headless Chromium with three.js r111; returns the page's result with the image (H, W, 3)
    (``image``: linear floats from a render target, or the canvas's 8-bit values over 255 as written, encoded)
    and the viewer's coverage (``alpha`` > 0)."""
    files = {"three.js": (THREE / "three.js").read_bytes(),
             "GLTFLoader.js": (THREE / "examples/js/loaders/GLTFLoader.js").read_bytes(),
             "model.glb": Path(glb).read_bytes(), "page.html": PAGE.encode(),
             "params.json": json.dumps(params).encode()}
    srv = _Server(("127.0.0.1", 0), _Handler)
    srv.files, srv.done = files, threading.Event()
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{srv.server_address[1]}/page.html"
    with tempfile.TemporaryDirectory(prefix="gltf_check_") as prof:
        proc = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
                                 "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", f"--user-data-dir={prof}",
                                 "--remote-debugging-port=0", url],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ok = srv.done.wait(timeout_s)
        finally:
            proc.terminate()  # the one process this function started, by its id
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            srv.shutdown()
    if not ok:
        raise RuntimeError(f"no result from Chromium within {timeout_s} s")
    res = srv.result
    if "error" in res:
        raise RuntimeError(f"page error: {res['error']}")
    w, h = params["width"], params["height"]
    raw = base64.b64decode(res.pop("pixels"))
    if res["float"]:
        img = np.frombuffer(raw, np.float32).reshape(h, w, 4)[::-1].astype(np.float64)
    else:
        img = np.frombuffer(raw, np.uint8).reshape(h, w, 4)[::-1].astype(np.float64) / 255.0
    res["image"], res["alpha"] = img[..., :3], img[..., 3]
    return res


def render_in_blender(python: str, params: dict, timeout_s: float = 600.0) -> np.ndarray:
    """Render with Blender's Cycles through ``python`` (an interpreter with PyPI's ``bpy``; params as
    :func:`blender_params`); returns the (H, W, 4) linear RGBA image."""
    from texstream.capture.imageio import read_image

    with tempfile.TemporaryDirectory(prefix="gltf_blender_") as t:
        script, args = Path(t) / "render.py", Path(t) / "params.json"
        script.write_text(BLENDER_SCRIPT)
        out = Path(t) / "render.exr"
        args.write_text(json.dumps({**params, "out": str(out)}))
        subprocess.run([python, str(script), str(args)], check=True, timeout=timeout_s,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        return read_image(out, channels=4).astype(np.float64)


def blender_params(frame, near: float, far: float, watts_per_candela: float, samples: int) -> dict:
    """Blender's camera (texstream world frame, the glb's node undone by the importer) and point light of a frame;
    the light's power in watts is its intensity times ``watts_per_candela`` (from :func:`blender_calibration`)."""
    from texstream.capture.conventions import w2c_cv_to_c2w_gl

    k = frame.intrinsics
    inten = np.asarray(frame.light.intensity, np.float64)
    peak = float(inten.max())
    return {"width": int(k.width), "height": int(k.height), "fx": k.fx, "cx": k.cx, "cy": k.cy,
            "camera_to_world": w2c_cv_to_c2w_gl(frame.R, frame.t).reshape(-1).tolist(), "near": near, "far": far,
            "light_position": [float(x) for x in frame.light.position], "light_watts": peak * watts_per_candela,
            "light_color": (inten / peak).tolist(), "samples": samples}


def blender_calibration(python: str) -> float:
    """Watts per candela of Blender's point light, measured (a check of the 4 pi the renders use: Cycles gives a
    point light's power in watts, radiant intensity = power / (4 pi)): a Lambertian plane of albedo 0.5 lit from
    2 m straight above by 1000 W, seen from above; radiance = 0.5 / pi * I / r^2 at the centre."""
    from texstream.capture.capture_json import Frame, Intrinsics, Light
    from texstream.render.pose import look_at_w2c

    r, t = look_at_w2c(np.array([0.0, 0.0, 2.0]), np.zeros(3), up=(0.0, 1.0, 0.0))
    fr = Frame("calibration", r, t, Intrinsics(32, 32, 64.0, 64.0, 16.0, 16.0), Light.point([0.0, 0.0, 2.0], [1.0] * 3))
    p = blender_params(fr, 0.1, 10.0, 1000.0, 64)
    img = render_in_blender(python, {**p, "scene": "calibration", "plane_size": 1.0})
    centre = float(img[15:17, 15:17, :3].mean())
    intensity = centre / (0.5 / math.pi / 4.0)  # radiance = albedo / pi * I / r^2, r = 2
    return 1000.0 / intensity


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = (a[mask] - b[mask]).astype(np.float64)
    return 10 * math.log10(1.0 / float(np.mean(d * d)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("glb")
    ap.add_argument("capture", help="the capture the model was fitted to (cameras, lights, photos, masks)")
    ap.add_argument("model", help="the model folder the glb was exported from (texstream's own render)")
    ap.add_argument("--frame", default="frame_00007", help="the photo whose camera and light are used (held out)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--up-axis", default="z", help="the export's up_axis (export_config.json)")
    ap.add_argument("--label", default="", help="what this glb is, for the JSON")
    ap.add_argument("--blender", default=None, help="a Python with PyPI's bpy: also render with Blender's Cycles, "
                    "whose glTF importer reads KHR_materials_specular (Principled BSDF's Specular Tint)")
    ap.add_argument("--blender-samples", type=int, default=256)
    ap.add_argument("--out", default=None, help="folder for <label or frame>.json and .png (default: print only)")
    a = ap.parse_args(argv)

    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image, read_mask, write_image
    from texstream.fit.models import registry
    from texstream.fit.stages.export import _up_rotation

    cap = read_capture(a.capture)
    frame = next((f for f in cap.frames if f.name == a.frame), None)
    if frame is None:
        raise SystemExit(f"{a.capture}: no frame named {a.frame}")
    photo = read_image(cap.image_path(frame), channels=3).astype(np.float64)
    t0 = time.perf_counter()
    model = registry.load_model_folder(a.model)
    ours, coverage = model.renderer("cpu")(frame)
    t_ours = time.perf_counter() - t0
    fg = coverage.astype(bool)
    if cap.mask_path(frame) is not None and cap.mask_path(frame).exists():
        fg &= read_mask(cap.mask_path(frame), fg.shape)
    verts = np.asarray(model.mesh.vertices)
    dist = np.linalg.norm(verts - frame.center, axis=1)
    near, far = max(0.5 * float(dist.min()), 1e-3), 2.0 * float(dist.max())
    params = scene_params(frame, _up_rotation(a.up_axis), near, far)
    out = {"glb": str(a.glb), "label": a.label, "capture": str(a.capture), "model": str(a.model),
           "frame": frame.file_path, "texstream_vs_photo_db": psnr(ours, photo, fg), "pixels": int(fg.sum()),
           "texstream_render_s": t_ours, "variants": {}, "machine": platform.node(), "python": sys.version.split()[0]}
    try:
        sys.path.insert(0, str(Path(__file__).parent))
        from gitinfo import commit
        out["commit"] = commit()
    except Exception:  # noqa: BLE001 - a copy outside the repository
        out["commit"] = None
    panels = [photo, ours]
    for v in a.variants.split(","):
        t0 = time.perf_counter()
        res = render_in_chromium(Path(a.glb), {**params, "variant": v})
        img, m = res.pop("image"), fg & (res.pop("alpha") > 0)
        decoded = {v: img}
        if v == "gamma22":
            decoded = {v: img ** 2.2, "gamma22_as_srgb": srgb_to_linear(img)}
        elif v == "r111_defaults":
            decoded = {v: srgb_to_linear(img)}
        for name, lin in decoded.items():
            row = out["variants"][name] = {
                "vs_photo_db": psnr(lin, photo, m), "vs_texstream_db": psnr(lin, ours, m),
                "mean_ratio_to_photo": float(lin[m].mean() / photo[m].mean()),
                "viewer_missed_pixels": int((fg & ~m).sum()), "seconds": time.perf_counter() - t0, **res}
            print(f"{name:16s} vs photo {row['vs_photo_db']:.2f} dB, vs texstream {row['vs_texstream_db']:.2f} dB, "
                  f"mean / photo's {row['mean_ratio_to_photo']:.3f}", flush=True)
            if name in ("linear", "gamma22", "r111_defaults"):
                panels.append(lin)
    if a.blender:
        t0 = time.perf_counter()
        wpc = 4 * math.pi  # Cycles' point light: intensity = power / (4 pi) per steradian
        out["blender_calibration_watts_per_candela"] = blender_calibration(a.blender)
        for dist in ("MULTI_GGX", "GGX"):
            img = render_in_blender(a.blender, {**blender_params(frame, near, far, wpc, a.blender_samples),
                                                "scene": "glb", "glb": str(Path(a.glb).resolve()),
                                                "distribution": dist})
            m = fg & (img[..., 3] > 0.5)
            name = f"blender_cycles_{dist.lower()}"
            row = out["variants"][name] = {
                "vs_photo_db": psnr(img[..., :3], photo, m), "vs_texstream_db": psnr(img[..., :3], ours, m),
                "mean_ratio_to_photo": float(img[..., :3][m].mean() / photo[m].mean()),
                "viewer_missed_pixels": int((fg & ~m).sum()),
                "samples": a.blender_samples, "seconds": time.perf_counter() - t0}
            print(f"{name:16s} vs photo {row['vs_photo_db']:.2f} dB, vs texstream {row['vs_texstream_db']:.2f} dB, "
                  f"mean / photo's {row['mean_ratio_to_photo']:.3f}", flush=True)
            if dist == "MULTI_GGX":
                panels.append(img[..., :3])
    print(f"texstream vs photo {out['texstream_vs_photo_db']:.2f} dB over {out['pixels']} pixels")
    if a.out:
        d = Path(a.out)
        d.mkdir(parents=True, exist_ok=True)
        stem = a.label or frame.name
        (d / f"{stem}.json").write_text(json.dumps(out, indent=1) + "\n")
        write_image(d / f"{stem}.png", np.clip(np.concatenate(panels, axis=1), 0, 1).astype(np.float32), bits=8)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
