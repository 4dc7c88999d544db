"""Synthetic captures written as Agisoft Metashape and RealityCapture exports, with their ground truth.

The camera imports (:mod:`texstream.calib.metashape`, :mod:`texstream.calib.realitycapture`) are tested and
benchmarked against these: a synthetic scene is rendered through cameras with known lenses (two sensors with
different focal lengths, principal points and Brown distortion), and written as a real export would be:

- :func:`write_metashape`: ``cameras.xml`` (two sensors whose calibration is at ``calib_factor`` (4) times the
  photos' resolution, a chunk transform with rotation, translation and scale, one disabled and one unaligned
  camera), ``photos/*.JPG`` at the photos' resolution with the full sensor's stale EXIF (a raw converter's
  quarter-size export, :mod:`.exif`), and ``mesh_chunk.obj``: the true mesh in chunk coordinates (Metashape's
  default mesh export).
- :func:`write_realitycapture`: ``xmp/NAME.xmp`` sidecars (Brown3 with tangential terms; one without a pose)
  and ``photos/*.jpg``.
- :func:`write_truth`: the same views as a plain capture folder (pinhole PNGs, true cameras, lights) and the
  true mesh in world coordinates: the run the imports are compared with.

How the photos get their distortion: each view is rendered by the pinhole renderer (the lens's fx, fy, cx, cy,
no distortion); every pixel of the distorted photo is then traced back through the exact inverse of the lens
model (fixed-point iteration to 1e-12 of the normalized coordinates) to the pinhole render, and sampled there
bicubically (cv2.remap). So the photos are distorted exactly as the written coefficients say, up to the
resampling (bilinear sampling here and in the import cost a noise-textured view about 4 dB more than bicubic);
pixels whose ray leaves the render are black (the background).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from texstream.calib.posed_import import LensCamera
from texstream.capture.capture_json import Capture, Frame, write_capture
from texstream.capture.imageio import linear_to_srgb, write_image
from texstream.capture.synthetic.exif import CameraBody, exif_for, write_jpeg
from texstream.capture.synthetic.synth import (SynthConfig, camera_poses, frame_light, iter_renders, load_scene,
                                               prepare_scene)
from texstream.core.outputs import write_json_atomic
from texstream.geometry.mesh_io import save_mesh
from texstream.render.mesh import SurfaceMesh

# Two sensors' lenses relative to a photo of width w, height h and focal length f0 (from the scene's fov):
# focal factor, affinity b1 / f0 (Metashape only), principal point offsets / (w, h), k1 k2 k3 k4, OpenCV p1 p2.
# The distortion is strong for a 35 degree lens (about 1.5 pixels at the corners of a 64 x 48 photo), so that
# a photo read without it is measurably off.
SENSORS = (
    {"label": "Canon EOS 5D Mark III, 24 mm", "focal": 1.0, "b1": 0.002, "pp": (0.012, -0.009),
     "k": (-0.3, 0.12, -0.02, 0.0), "p": (0.004, -0.003)},
    {"label": "Canon EOS 5D Mark III, 28 mm", "focal": 1.08, "b1": 0.0, "pp": (-0.010, 0.011),
     "k": (0.25, -0.06, 0.01, 0.0), "p": (-0.003, 0.002)},
)


@dataclasses.dataclass
class ExportSet:
    """A rendered synthetic capture with distorted photos.

    Attributes:
        labels: camera labels (``IMG_0001`` ...), in order.
        frames: the true frames (pinhole intrinsics of each lens, world-to-camera poses, lights).
        lenses: the true lens of each photo (at the photos' resolution).
        sensor_of: the sensor index of each photo.
        pinhole: the renders (linear float), one per frame.
        photos: the distorted photos (linear float), one per frame.
        mesh: the true mesh (world coordinates).
    """

    labels: list[str]
    frames: list[Frame]
    lenses: list[LensCamera]
    sensor_of: list[int]
    pinhole: list[np.ndarray]
    photos: list[np.ndarray]
    mesh: SurfaceMesh


def sensor_lens(spec: dict, width: int, height: int, fov_deg: float, skew_free: bool = False) -> LensCamera:
    """A sensor of :data:`SENSORS` on a ``width`` x ``height`` photo (``skew_free``: no affinity, for formats
    that have none)."""
    f0 = (width / 2) / math.tan(math.radians(fov_deg) / 2) * spec["focal"]
    b1 = 0.0 if skew_free else spec["b1"] * f0
    return LensCamera(width=width, height=height, fx=f0 + b1, fy=f0, cx=width * (0.5 + spec["pp"][0]),
                      cy=height * (0.5 + spec["pp"][1]), k1=spec["k"][0], k2=spec["k"][1], k3=spec["k"][2],
                      k4=spec["k"][3], p1=spec["p"][0], p2=spec["p"][1])


def undistort_normalized(lens: LensCamera, xd: np.ndarray, yd: np.ndarray, iters: int = 60) -> tuple:
    """The inverse of :meth:`LensCamera.distort` by fixed-point iteration (converges for the mild lenses here)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        g = 1.0 + r2 * (lens.k1 + r2 * (lens.k2 + r2 * (lens.k3 + r2 * lens.k4)))
        dx = 2.0 * lens.p1 * x * y + lens.p2 * (r2 + 2.0 * x * x)
        dy = lens.p1 * (r2 + 2.0 * y * y) + 2.0 * lens.p2 * x * y
        x, y = (xd - dx) / g, (yd - dy) / g
    return x, y


def distort_image(render: np.ndarray, lens: LensCamera) -> np.ndarray:
    """The photo ``lens`` takes of a view whose pinhole render (same fx, fy, cx, cy) is ``render``."""
    import cv2

    v, u = np.mgrid[0:lens.height, 0:lens.width] + 0.5
    yd = (v - lens.cy) / lens.fy
    xd = (u - lens.cx - lens.skew * yd) / lens.fx
    x, y = undistort_normalized(lens, xd, yd)
    map_x = (lens.fx * x + lens.cx - 0.5).astype(np.float32)
    map_y = (lens.fy * y + lens.cy - 0.5).astype(np.float32)
    return cv2.remap(np.ascontiguousarray(render, dtype=np.float32), map_x, map_y, cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def render_export_set(scene, photos: int, width: int, height: int, *, skew_free: bool = False,
                      device: str = "cpu") -> ExportSet:
    """Render ``scene`` (name, path or dict) through the two :data:`SENSORS` (alternating) on ``photos`` photos of
    ``width`` x ``height`` (the scene's cameras and light; its photo settings but for the size)."""
    sc = load_scene(scene)
    sc["cameras"] = {**sc["cameras"], "width": int(width), "height": int(height), "count": int(photos)}
    config = SynthConfig(scale=1.0, photos=int(photos), device=device, progress=False, preview=False)
    sc, mesh, _, layout, params, _, _, _ = prepare_scene(sc, config)
    sc["cameras"].update(width=int(width), height=int(height))
    cams = sc["cameras"]
    target = np.asarray(cams.get("target", [0.0, 0.0, 0.0]), dtype=np.float64)
    lenses = [sensor_lens(s, width, height, float(cams["fov_deg"]), skew_free) for s in SENSORS]
    frames, sensor_of, labels = [], [], []
    for i, (r, t) in enumerate(camera_poses(cams, photos)):
        k = i % len(SENSORS)
        labels.append(f"IMG_{i + 1:04d}")
        sensor_of.append(k)
        frames.append(Frame(file_path=f"images/{labels[-1]}.png", R=r, t=t, intrinsics=lenses[k].pinhole(),
                            light=frame_light(sc["light"], r, t, i, photos, target), saturation=1.0))
    pinhole, distorted = [], []
    for _, f, photo, _, _ in iter_renders(sc, mesh, params, layout, frames, config):
        img = np.clip(np.asarray(photo, dtype=np.float32), 0.0, 1.0)
        pinhole.append(img)
        distorted.append(np.clip(distort_image(img, lenses[sensor_of[len(distorted)]]), 0.0, 1.0))
    return ExportSet(labels=labels, frames=frames, lenses=[lenses[k] for k in sensor_of], sensor_of=sensor_of,
                     pinhole=pinhole, photos=distorted, mesh=mesh)


def _write_photos(es: ExportSet, folder: Path, calib_factor: int, ext: str) -> None:
    """The distorted photos as 8-bit sRGB JPEGs with the full sensor's stale EXIF (sensor = photo x factor)."""
    for label, lens, img in zip(es.labels, es.lenses, es.photos):
        body = CameraBody(sensor_px=(lens.width * calib_factor, lens.height * calib_factor))
        focal_mm = lens.fy * body.sensor_width_mm / lens.width
        write_jpeg(folder / f"{label}{ext}", linear_to_srgb(img),
                   exif_for(body, focal_mm, (lens.width, lens.height), stale=True))


def _transformed(mesh: SurfaceMesh, m: np.ndarray) -> SurfaceMesh:
    """``mesh`` taken through the 4x4 similarity ``m``."""
    a = m[:3, :3]
    rot = a / np.cbrt(np.linalg.det(a))
    normals = None if mesh.normals is None else mesh.normals @ rot.T
    return dataclasses.replace(mesh, vertices=mesh.vertices @ a.T + m[:3, 3], normals=normals)


def default_chunk_transform() -> np.ndarray:
    """A chunk -> world similarity with a generic rotation, a translation and scale 2.5."""
    ax = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    ang = 0.7
    k = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    rot = np.eye(3) + math.sin(ang) * k + (1 - math.cos(ang)) * k @ k
    m = np.eye(4)
    m[:3, :3] = 2.5 * rot
    m[:3, 3] = [12.0, -3.5, 0.75]
    return m


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in np.asarray(v, dtype=np.float64).reshape(-1))


def _sensor_xml(k: int, lens: LensCamera, label: str) -> str:
    """A <sensor> of Metashape's XML for ``lens`` at the calibration resolution (inverse of calib.metashape)."""
    w, h = lens.width, lens.height
    tags = {"f": lens.fy, "cx": lens.cx - w / 2, "cy": lens.cy - h / 2, "b1": lens.fx - lens.fy, "b2": lens.skew,
            "k1": lens.k1, "k2": lens.k2, "k3": lens.k3, "k4": lens.k4,
            "p1": lens.p2, "p2": lens.p1}  # Metashape P1 = OpenCV p2, P2 = OpenCV p1
    cal = "".join(f"\n          <{t}>{v!r}</{t}>" for t, v in tags.items())
    return (f'\n      <sensor id="{k}" label="{label}" type="frame">\n        <resolution width="{w}" height="{h}"/>'
            f'\n        <property name="pixel_width" value="{36.0 / w!r}"/>\n        <property name="pixel_height" '
            f'value="{36.0 / w!r}"/>\n        <calibration type="frame" class="adjusted">\n          '
            f'<resolution width="{w}" height="{h}"/>{cal}\n        </calibration>\n      </sensor>')


def write_metashape(es: ExportSet, out: str | Path, *, calib_factor: int = 4, chunk: np.ndarray | None = None,
                    disabled: tuple[int, ...] = (1,), unaligned: tuple[int, ...] = (2,),
                    components: bool = False) -> dict:
    """``out/cameras.xml``, ``out/photos/*.JPG`` and ``out/mesh_chunk.obj`` (module doc). ``components``: the
    chunk transform is split into a chunk part and a component part (Metashape 2.x), cameras carry
    ``component_id``. Returns what was written (the indices of the skipped cameras, the chunk transform)."""
    out = Path(out)
    (out / "photos").mkdir(parents=True, exist_ok=True)
    chunk = default_chunk_transform() if chunk is None else np.asarray(chunk, dtype=np.float64)
    s = float(np.cbrt(np.linalg.det(chunk[:3, :3])))
    parts = [(chunk, "")]
    if components:  # world = chunk @ component: the component takes the rotation, the chunk scale and translation
        c1 = np.eye(4)
        c1[:3, :3], c1[:3, 3] = s * np.eye(3), chunk[:3, 3]
        c2 = np.eye(4)
        c2[:3, :3] = chunk[:3, :3] / s
        parts = [(c1, ""), (c2, ' component_id="0"')]
    chunk_inv = np.linalg.inv(chunk)
    sensors = ""
    for k in sorted(set(es.sensor_of)):
        lens = es.lenses[es.sensor_of.index(k)]
        sensors += _sensor_xml(k, lens.scaled(lens.width * calib_factor, lens.height * calib_factor),
                               SENSORS[k]["label"])
    cams = []
    for i, (label, f) in enumerate(zip(es.labels, es.frames)):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = f.R.T, -f.R.T @ f.t
        attrs = f'id="{i}" sensor_id="{es.sensor_of[i]}"{parts[-1][1]} label="{label}"'
        if i in disabled:
            attrs += ' enabled="false"'
        body = "" if i in unaligned else f"\n        <transform>{_fmt(chunk_inv @ c2w)}</transform>"
        cams.append(f"\n      <camera {attrs}>{body}\n      </camera>")

    def transform_xml(m: np.ndarray, indent: str) -> str:
        sc = float(np.cbrt(np.linalg.det(m[:3, :3])))
        return (f"{indent}<transform>\n{indent}  <rotation locked=\"false\">{_fmt(m[:3, :3] / sc)}</rotation>\n"
                f"{indent}  <translation locked=\"false\">{_fmt(m[:3, 3])}</translation>\n"
                f"{indent}  <scale locked=\"false\">{sc!r}</scale>\n{indent}</transform>\n")

    comp = ""
    if components:
        comp = ('    <components next_id="1" active_id="0">\n      <component id="0" label="Component 1">\n'
                + transform_xml(parts[1][0], "        ") + "      </component>\n    </components>\n")
    xml = ('<?xml version="1.0" encoding="UTF-8"?>\n<document version="2.0.0">\n  <chunk label="Chunk 1" '
           f'enabled="true">\n    <sensors next_id="{len(SENSORS)}">{sensors}\n    </sensors>\n{comp}'
           f'    <cameras next_id="{len(cams)}" next_group_id="0">{"".join(cams)}\n    </cameras>\n'
           + transform_xml(parts[0][0], "    ") + "  </chunk>\n</document>\n")
    (out / "cameras.xml").write_text(xml)
    _write_photos(es, out / "photos", calib_factor, ".JPG")
    save_mesh(out / "mesh_chunk.obj", _transformed(es.mesh, chunk_inv))
    return {"disabled": list(disabled), "unaligned": list(unaligned), "chunk_transform": chunk.tolist(),
            "chunk_scale": s}


def write_realitycapture(es: ExportSet, out: str | Path, *, unposed: tuple[int, ...] = (2,)) -> dict:
    """``out/xmp/NAME.xmp`` (Brown3 with tangential terms) and ``out/photos/NAME.jpg`` (module doc); the cameras
    in ``unposed`` get a calibration-only XMP."""
    out = Path(out)
    (out / "xmp").mkdir(parents=True, exist_ok=True)
    (out / "photos").mkdir(parents=True, exist_ok=True)
    for i, (label, f, lens) in enumerate(zip(es.labels, es.frames, es.lenses)):
        if lens.fx != lens.fy or lens.skew != 0.0:
            raise ValueError("RealityCapture XMPs hold square pixels without skew: render with skew_free=True")
        side = max(lens.width, lens.height)
        coeffs = _fmt([lens.k1, lens.k2, lens.k3, lens.k4, lens.p2, lens.p1])  # t1 = OpenCV p2, t2 = p1
        pose = "" if i in unposed else (f"\n      <xcr:Rotation>{_fmt(f.R)}</xcr:Rotation>"
                                        f"\n      <xcr:Position>{_fmt(-f.R.T @ f.t)}</xcr:Position>")
        xmp = ('<x:xmpmeta xmlns:x="adobe:ns:meta/">\n  <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-'
               'ns#">\n    <rdf:Description xcr:Version="3" xcr:PosePrior="locked" xcr:Coordinates="absolute"\n'
               f'       xcr:DistortionModel="brown3t2" xcr:FocalLength35mm="{lens.fx / side * 36.0!r}"\n'
               f'       xcr:Skew="0" xcr:AspectRatio="1" xcr:PrincipalPointU="{(lens.cx - lens.width / 2) / side!r}"\n'
               f'       xcr:PrincipalPointV="{(lens.cy - lens.height / 2) / side!r}" xcr:CalibrationPrior="exact"\n'
               f'       xcr:CalibrationGroup="{es.sensor_of[i]}" xcr:DistortionGroup="{es.sensor_of[i]}"\n'
               '       xmlns:xcr="http://www.capturingreality.com/ns/xcr/1.1#">'
               f'{pose}\n      <xcr:DistortionCoeficients>{coeffs}</xcr:DistortionCoeficients>\n'
               '    </rdf:Description>\n  </rdf:RDF>\n</x:xmpmeta>\n')
        (out / "xmp" / f"{label}.xmp").write_text(xmp)
    _write_photos(es, out / "photos", 1, ".jpg")
    return {"unposed": list(unposed)}


def write_truth(es: ExportSet, out: str | Path, skip: tuple[int, ...] = ()) -> Path:
    """The views but ``skip`` as a capture folder of pinhole 8-bit PNGs with the true cameras and lights, and
    ``mesh.obj`` (world coordinates): the baseline the imports are compared with."""
    out = Path(out)
    frames = []
    for i, (f, img) in enumerate(zip(es.frames, es.pinhole)):
        if i in skip:
            continue
        write_image(out / f.file_path, img, bits=8)
        frames.append(f)
    write_capture(Capture(root=out, frames=frames, extra={"source": "synthetic truth of camera_exports"}), out)
    save_mesh(out / "mesh.obj", es.mesh)
    write_json_atomic(out / "lenses.json", {lab: dataclasses.asdict(le) for lab, le in zip(es.labels, es.lenses)})
    return out
