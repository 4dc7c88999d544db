"""Agisoft Metashape cameras (File > Export > Export Cameras, Agisoft XML) -> a capture folder.

``texstream import metashape CAMERAS.xml PHOTOS -o OUT [--mesh FILE]``.

The conventions, from the Metashape manual's "Camera models" appendix (frame cameras; the same in the 1.x and
2.x manuals):

    x = X / Z, y = Y / Z   (camera axes: x right, y down, z forward, as OpenCV)
    r2 = x^2 + y^2
    x' = x (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P1 (r2 + 2 x^2) + 2 P2 x y
    y' = y (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P2 (r2 + 2 y^2) + 2 P1 x y
    u = w / 2 + cx + x' f + x' B1 + y' B2
    v = h / 2 + cy + y' f

in pixels of the calibration's ``<resolution>`` with the centre of the top-left pixel at (0.5, 0.5), texstream's
own pixel convention. So (:class:`~texstream.calib.posed_import.LensCamera` names):

- ``fx = f + B1`` (the affinity term stretches x), ``fy = f``, ``skew = B2``;
- ``cx = w / 2 + cx``, ``cy = h / 2 + cy`` (Metashape's are offsets from the image centre);
- ``k1..k4 = K1..K4``; **OpenCV's p1 is Metashape's P2 and OpenCV's p2 is Metashape's P1**: OpenCV puts p2 on
  x's (r2 + 2 x^2) term and p1 on its 2 x y term, Metashape the other way round.

Sources: the tangential order as the Metashape 2.3 manual states it is quoted in nerfstudio's issue #3714 and
pull request #3779 (Metashape's P1 on x's (r2 + 2 x^2) term, so nerfstudio swaps P1 and P2 into OpenCV's); the
manual's own appendix pages could not be read here beyond their tables of contents, so the projection above
(in particular B1 on x and B2 as skew, and cx, cy centre-relative, as nerfstudio's reader also takes them) is
written from the manual as we know it; the import was not checked against a file Metashape wrote, only against
that formula (tests/test_camera_imports.py) and synthetic exports of it.

Poses: a camera's ``<transform>`` (16 numbers, row-major) is camera-to-chunk; a camera of a component
(``component_id``, Metashape 2.x) is first taken through the component's ``<transform>``; the chunk's
``<transform>`` (``<rotation>`` 3x3 row-major, ``<translation>``, ``<scale>``) takes chunk to world:
``world = s R x + t``. The capture is written in that world frame (its units: the chunk's, metres for a
referenced chunk). Cameras that are disabled (``enabled="false"`` or ``"0"``) or not aligned (no
``<transform>``) are skipped with a printed line. Each camera's photo is found in PHOTOS by its label (the file
name without extension, case-insensitive); a photo smaller or larger than the calibration's resolution (a
raw converter's export at a quarter of the sensor) gets the calibration scaled by the size ratio.

A mesh Metashape exported (``--mesh``, OBJ or PLY; in chunk coordinates unless ``--mesh-frame world``) is
taken into the same world frame and written beside capture.json; ``texstream run`` then uses it as the mesh
as it is, with no registration or alignment (capture.json's ``mesh``).
"""

from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from texstream.capture.imageio import image_size
from texstream.core.config import option, save_config
from texstream.core.errors import InputError
from texstream.core.outputs import StageResult, atomic_output_dir

from .no_flash import NO_FLASH_HELP
from .posed_import import (LensCamera, MeshWriter, PosedPhoto, check_photos_out, find_photo, photo_index,
                           photo_scale, pose_from_camera_to_world, similarity_matrix, summary_lines,
                           write_posed_capture)

FIX_EXPORT = "export the cameras from Metashape with File > Export > Export Cameras (Agisoft XML)"


@dataclasses.dataclass
class MetashapeImportConfig:
    """Options of ``texstream import metashape``."""

    undistort: bool = option(True, help="resample the photos onto pinhole cameras through Metashape's exact lens "
                                        "model (the fit renders pinhole cameras); off: copy them and keep the "
                                        "distortion in capture.json (OpenCV k1 k2 p1 p2 k3)")
    copy_mode: str = option("copy", help="how photos that need no resampling reach the capture folder",
                            choices=("copy", "hardlink", "symlink"))
    colocated_light: float | None = option(None, help="photos lit by a flash at the camera: its intensity (a point "
                                                      "light at each camera centre, in the chunk's world units)",
                                                      min=1e-12)
    no_flash: str | None = option(None, help=NO_FLASH_HELP + " (calib/no_flash.py); those photos' flash gets "
                                  "intensity 0")
    mesh: str | None = option(None, help="a mesh Metashape exported (OBJ/PLY): written into the capture, and "
                                         "'texstream run' uses it as the mesh")
    mesh_frame: str = option("chunk", help="the frame the mesh is in: chunk (Metashape's default export) or world "
                                           "(exported with the chunk's coordinate system)", choices=("chunk", "world"))
    overwrite: bool = option(True, help="replace an existing output folder")


@dataclasses.dataclass
class Sensor:
    """A frame sensor's calibration: the lens at its calibration resolution, and where it came from."""

    label: str
    lens: LensCamera
    calibration_class: str


@dataclasses.dataclass
class MetashapeCamera:
    label: str
    sensor_id: str
    component_id: str | None
    enabled: bool
    transform: np.ndarray | None


@dataclasses.dataclass
class MetashapeChunk:
    """What an Agisoft XML holds for the import."""

    sensors: dict[str, Sensor]
    cameras: list[MetashapeCamera]
    chunk_transform: np.ndarray
    components: dict[str, np.ndarray]

    def camera_to_world(self, cam: MetashapeCamera) -> np.ndarray:
        comp = self.components.get(cam.component_id or "", np.eye(4))
        return self.chunk_transform @ comp @ cam.transform


def _numbers(el: ET.Element | None, n: int, what: str, path: Path) -> np.ndarray | None:
    if el is None or el.text is None:
        return None
    try:
        v = np.array([float(x) for x in el.text.split()], dtype=np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.size != n or not np.all(np.isfinite(v)):
        raise InputError(f"{what} is not {n} finite numbers", path, FIX_EXPORT)
    return v


def _transform(el: ET.Element | None, what: str, path: Path) -> np.ndarray:
    """A chunk's or component's <transform> (rotation, translation, scale; each optional) as a 4x4 similarity."""
    if el is None:
        return np.eye(4)
    rot = _numbers(el.find("rotation"), 9, f"{what} rotation", path)
    tr = _numbers(el.find("translation"), 3, f"{what} translation", path)
    sc = _numbers(el.find("scale"), 1, f"{what} scale", path)
    r = np.eye(3) if rot is None else rot.reshape(3, 3)
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-5 or np.linalg.det(r) <= 0:
        raise InputError(f"{what} rotation is not a rotation", path, FIX_EXPORT)
    s = 1.0 if sc is None else float(sc[0])
    if not s > 0:
        raise InputError(f"{what} scale {s} is not positive", path, FIX_EXPORT)
    return similarity_matrix(r, np.zeros(3) if tr is None else tr, s)


def _calibration(sensor: ET.Element, label: str, path: Path) -> tuple[ET.Element, str]:
    cals = sensor.findall("calibration")
    if not cals:
        raise InputError(f"sensor {label!r} has no calibration", path, "align the photos in Metashape, then export the cameras again")
    by_class = {c.get("class", ""): c for c in cals}
    for cls in ("adjusted", "initial", ""):
        if cls in by_class:
            return by_class[cls], cls or "unnamed"
    return cals[0], cals[0].get("class", "unnamed")


def _sensor(el: ET.Element, path: Path) -> Sensor:
    """A <sensor> as a :class:`Sensor` (module doc: the mapping of f, cx, cy, B1, B2, K1..K4, P1, P2)."""
    label = el.get("label") or el.get("id", "?")
    kind = el.get("type", "frame")
    if kind != "frame":
        raise InputError(f"sensor {label!r} is a {kind} camera; only frame (pinhole) cameras are supported", path,
                         "use photos from a frame camera, or convert them to frame images first")
    cal, cls = _calibration(el, label, path)
    res = cal.find("resolution")
    if res is None:
        res = el.find("resolution")
    try:
        w, h = int(res.get("width")), int(res.get("height"))  # type: ignore[union-attr]
    except (AttributeError, TypeError, ValueError):
        raise InputError(f"sensor {label!r} has no calibration resolution", path, FIX_EXPORT) from None

    def val(tag: str) -> float:
        v = _numbers(cal.find(tag), 1, f"sensor {label!r} {tag}", path)
        return 0.0 if v is None else float(v[0])

    f = val("f")
    if not f > 0:
        raise InputError(f"sensor {label!r} has no positive focal length f", path, FIX_EXPORT)
    lens = LensCamera(width=w, height=h, fx=f + val("b1"), fy=f, cx=w / 2 + val("cx"), cy=h / 2 + val("cy"),
                      skew=val("b2"), k1=val("k1"), k2=val("k2"), k3=val("k3"), k4=val("k4"),
                      p1=val("p2"), p2=val("p1"))  # OpenCV p1 = Metashape P2, p2 = P1 (module doc)
    return Sensor(label=label, lens=lens, calibration_class=cls)


def read_metashape(path: str | os.PathLike) -> MetashapeChunk:
    """Parse an Agisoft cameras XML (its first chunk with cameras).

    Raises:
        InputError: not XML, not a Metashape cameras file, a malformed number or transform.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("Metashape cameras file not found", path, "pass the XML Metashape exported")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(f"not a readable XML file ({e})", path, FIX_EXPORT) from None
    chunks = [root] if root.tag == "chunk" else root.findall("chunk") if root.tag == "document" else []
    chunk = next((c for c in chunks if c.find("cameras") is not None), None)
    if chunk is None:
        raise InputError(f"not a Metashape cameras file (root <{root.tag}>, no <chunk> with <cameras>)", path,
                         FIX_EXPORT)
    sensors_el = chunk.find("sensors")
    sensors = {s.get("id", ""): _sensor(s, path) for s in (sensors_el if sensors_el is not None else [])
               if s.tag == "sensor"}
    components = {}
    comps_el = chunk.find("components")
    for comp in (comps_el if comps_el is not None else []):
        components[comp.get("id", "")] = _transform(comp.find("transform"), f"component {comp.get('id')}", path)
    cameras = []
    for cam in chunk.find("cameras").iter("camera"):  # cameras may sit in <group>s
        label = cam.get("label") or cam.get("id", "?")
        m = _numbers(cam.find("transform"), 16, f"camera {label!r} transform", path)
        cameras.append(MetashapeCamera(label=label, sensor_id=cam.get("sensor_id", ""),
                                       component_id=cam.get("component_id"),
                                       enabled=cam.get("enabled", "true").lower() not in ("false", "0"),
                                       transform=None if m is None else m.reshape(4, 4)))
    for cam in cameras:
        if cam.component_id is not None and cam.component_id not in components:
            raise InputError(f"camera {cam.label!r} names component {cam.component_id!r}, which the file lacks",
                             path, FIX_EXPORT)
        if cam.sensor_id not in sensors:
            raise InputError(f"camera {cam.label!r} names sensor {cam.sensor_id!r}, which the file lacks", path,
                             FIX_EXPORT)
    return MetashapeChunk(sensors=sensors, cameras=cameras,
                          chunk_transform=_transform(chunk.find("transform"), "chunk", path), components=components)


def _chunk_scale(m: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(m[:3, :3])))


def import_metashape(cameras_xml: str | os.PathLike, photos: str | os.PathLike, out: str | os.PathLike,
                     config: MetashapeImportConfig | None = None, mesh_writer: MeshWriter | None = None,
                     log=print) -> StageResult:
    """Metashape cameras and their photos -> a capture folder (module doc for the conventions).

    Args:
        cameras_xml: the Agisoft XML (File > Export > Export Cameras).
        photos: the folder holding the photos (any extension, matched to the cameras' labels).
        out: the capture folder to write (atomically): capture.json, images/, optional mesh file,
            import_config.json.
        config: options.
        mesh_writer: writes ``config.mesh`` transformed into the world frame (needed when ``config.mesh``).
        log: where the notes on skipped cameras and the sensors go.

    Returns:
        StageResult; its summary names the sensors, the cameras used and skipped and the chunk's scale.
    """
    cfg = config or MetashapeImportConfig()
    xml_path, photo_dir, out = Path(cameras_xml), Path(photos), Path(out)
    chunk = read_metashape(xml_path)
    check_photos_out(out, photo_dir)
    index = photo_index(photo_dir)
    skipped: dict[str, list[str]] = {"disabled": [], "unaligned": []}
    posed, sensors_used = [], {}
    for cam in chunk.cameras:
        if not cam.enabled:
            skipped["disabled"].append(cam.label)
            continue
        if cam.transform is None:
            skipped["unaligned"].append(cam.label)
            continue
        photo = find_photo(index, cam.label, photo_dir, xml_path.name)
        sensor = chunk.sensors[cam.sensor_id]
        w, h, _ = image_size(photo)
        calib = (sensor.lens.width, sensor.lens.height)
        sx, _ = photo_scale(calib, (w, h), photo)
        r, t = pose_from_camera_to_world(chunk.camera_to_world(cam), f"camera {cam.label!r}", xml_path)
        posed.append(PosedPhoto(label=cam.label, photo=photo, r=r, t=t, lens=sensor.lens.scaled(w, h),
                                sensor=sensor.label))
        s = sensors_used.setdefault(sensor.label, {"cameras": 0, "calibration": f"{calib[0]}x{calib[1]} "
                                                   f"({sensor.calibration_class})", "photos": f"{w}x{h}", "scale": sx})
        s["cameras"] += 1
        if s["photos"] != f"{w}x{h}":
            s["photos"] = "several sizes"
    for kind, labels in skipped.items():
        for label in labels:
            log(f"metashape: camera {label} skipped ({'disabled' if kind == 'disabled' else 'not aligned'})")
    if not posed:
        raise InputError("no enabled, aligned camera in the file", xml_path, "align the photos in Metashape first")
    if cfg.mesh and mesh_writer is None:
        raise InputError("a mesh was given but this caller cannot write meshes", cfg.mesh,
                         "use 'texstream import metashape ... --mesh FILE'")
    if cfg.mesh and not Path(cfg.mesh).is_file():
        raise InputError("mesh file not found", cfg.mesh, "pass the OBJ/PLY Metashape exported")
    scale = _chunk_scale(chunk.chunk_transform)
    extra = {"source": {"format": "metashape", "cameras": str(xml_path.resolve()), "photos": str(photo_dir.resolve())},
             "chunk_transform": chunk.chunk_transform.tolist(), "chunk_scale": scale,
             "intrinsics_source": "metashape", "undistorted": bool(cfg.undistort)}
    with atomic_output_dir(out, overwrite=cfg.overwrite) as tmp:
        if cfg.mesh:
            mesh_rel = "mesh" + Path(cfg.mesh).suffix.lower()
            mesh_writer(Path(cfg.mesh), tmp / mesh_rel,
                        chunk.chunk_transform if cfg.mesh_frame == "chunk" else np.eye(4))
            extra["mesh"] = mesh_rel
            extra["mesh_source"] = {"file": str(Path(cfg.mesh).resolve()), "frame": cfg.mesh_frame}
        write_posed_capture(tmp, posed, undistort=cfg.undistort, copy_mode=cfg.copy_mode,
                            colocated=cfg.colocated_light, extra=extra, no_flash=cfg.no_flash)
        save_config(cfg, tmp / "import_config.json")
    log(summary_lines(sensors_used, len(posed), skipped) + f"\nchunk scale {scale:.6g} (chunk -> world)")
    return StageResult(output=out, summary={"cameras": len(posed), "disabled": len(skipped["disabled"]),
                                            "unaligned": len(skipped["unaligned"]), "chunk_scale": scale,
                                            "sensors": sensors_used, "skipped": skipped,
                                            "mesh": extra.get("mesh"), "undistorted": bool(cfg.undistort)})
