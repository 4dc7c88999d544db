"""A synthetic outdoor scene: a building front with relief and the ground before it, photographed from one side.

The capture a street-level photographer makes of a facade: ``photos`` cameras on an arc of
``arc_deg`` degrees at ``distance`` metres from the wall, 1.6 m above the ground, all looking at the
middle of the front; a fixed sun; per-photo exposure spread evenly over ``exposure_stops`` stops (an
auto-exposing camera), shuffled so neighbouring photos differ; cameras only (no masks, no SfM
points): what :mod:`texstream.geometry.make_mesh` must mesh from dense stereo without masks.

The front (:func:`facade_mesh`, metres, world +z up, the wall in the plane y = 0 facing -y) is 12 m
wide and 8 m high: a plinth, four pillars, a cornice and a frieze standing out of it, four window
recesses on two storeys with sills, a door recess at the ground; the ground (z = 0) reaches 8 m in
front of it and 3 m past each side. Every cell of the relief is an axis-aligned box face, so the
true surface is exact; vertices are shared only between faces of one plane, so the renderer's vertex
normals stay the faces' own (no shading smeared over a corner).

Brick-like walls, plaster-like cornice and paving-like ground are value-noise albedos of
:mod:`texstream.capture.synthetic.synth`'s ``materials`` over an xatlas atlas, with a faint glossy
lobe. The ground truth (``ground_truth/``: ``mesh.obj`` with its UVs, parameter maps, ``bake.npz``,
``manifest.json``) is written as :func:`~texstream.capture.synthetic.synth.synthesize` writes it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import Capture, Frame, Intrinsics, Light, write_capture
from texstream.capture.conventions import look_at_w2c
from texstream.capture.imageio import write_image
from texstream.capture.synthetic.param_maps import write_param_maps
from texstream.capture.synthetic.synth import GROUND_TRUTH, SynthConfig, iter_renders, prepare_scene
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.geometry.mesh_io import save_mesh
from texstream.render.mesh import SurfaceMesh

WIDTH, HEIGHT, GROUND_DEPTH, SIDE_GROUND = 12.0, 8.0, 8.0, 3.0

# (x0, x1, z0, z1, offset): boxes of relief, later ones over earlier ones; offset > 0 stands out of the
# wall towards the street (-y), < 0 is a recess
RELIEF = [
    (-6.0, 6.0, 0.0, 0.5, 0.15),                                        # plinth
    *[(x, x + 0.6, 0.0, 7.0, 0.35) for x in (-5.6, -2.1, 1.5, 5.0)],    # pillars
    *[(c - 0.7, c + 0.7, z, z + 1.6, -0.3) for c in (-3.55, 3.55) for z in (1.2, 4.2)],  # windows
    (-0.7, 0.7, 4.2, 5.8, -0.3),                                        # upper middle window
    *[(c - 0.9, c + 0.9, z - 0.12, z, 0.12) for c in (-3.55, 3.55) for z in (1.2, 4.2)],  # sills
    (-0.9, 0.9, 4.08, 4.2, 0.12),
    (-0.8, 0.8, 0.0, 2.6, -0.4),                                        # door
    (-6.0, 6.0, 7.0, 7.6, 0.5),                                         # cornice
    (-6.0, 6.0, 7.6, 8.0, 0.2),                                         # frieze
]


class _Builder:
    """Quads into a triangle mesh, vertices shared only among faces of one plane (exact vertex normals)."""

    def __init__(self):
        self.index: dict = {}
        self.vertices: list = []
        self.faces: list = []

    def _vertex(self, p, normal) -> int:
        key = (tuple(np.round(p, 6)), tuple(np.round(normal, 3)))
        if key not in self.index:
            self.index[key] = len(self.vertices)
            self.vertices.append(p)
        return self.index[key]

    def quad(self, corners, normal) -> None:
        """A planar quad (corners in order round it) facing ``normal``."""
        c = [np.asarray(p, np.float64) for p in corners]
        if np.dot(np.cross(c[1] - c[0], c[2] - c[0]), normal) < 0:
            c = c[::-1]
        i = [self._vertex(p, normal) for p in c]
        self.faces += [[i[0], i[1], i[2]], [i[0], i[2], i[3]]]

    def mesh(self) -> SurfaceMesh:
        return SurfaceMesh(np.asarray(self.vertices, np.float64), np.asarray(self.faces, np.int32))


def _relief_grid():
    xs = sorted({-WIDTH / 2, WIDTH / 2, *[r[0] for r in RELIEF], *[r[1] for r in RELIEF]})
    zs = sorted({0.0, HEIGHT, *[r[2] for r in RELIEF], *[r[3] for r in RELIEF]})
    off = np.zeros((len(xs) - 1, len(zs) - 1))
    for i in range(len(xs) - 1):
        for j in range(len(zs) - 1):
            cx, cz = 0.5 * (xs[i] + xs[i + 1]), 0.5 * (zs[j] + zs[j + 1])
            for x0, x1, z0, z1, o in RELIEF:
                if x0 < cx < x1 and z0 < cz < z1:
                    off[i, j] = o
    return xs, zs, off


def facade_mesh() -> SurfaceMesh:
    """The facade and the ground (module doc): the wall's relief as a grid of cells at their offsets, the steps
    between neighbouring cells, caps at the front's sides and top, and the ground up to the front's foot."""
    xs, zs, off = _relief_grid()
    b = _Builder()
    nx, nz = off.shape
    for i in range(nx):
        for j in range(nz):
            y = -off[i, j]
            b.quad([(xs[i], y, zs[j]), (xs[i + 1], y, zs[j]), (xs[i + 1], y, zs[j + 1]), (xs[i], y, zs[j + 1])],
                   (0, -1, 0))
            # steps to the right and above (to nothing, i.e. the bare wall's plane, past the front's edges)
            right = off[i + 1, j] if i + 1 < nx else 0.0
            if right != off[i, j] and (i + 1 < nx or off[i, j] > 0):
                yr = -right
                b.quad([(xs[i + 1], y, zs[j]), (xs[i + 1], yr, zs[j]), (xs[i + 1], yr, zs[j + 1]),
                        (xs[i + 1], y, zs[j + 1])], (np.sign(off[i, j] - right), 0, 0))
            if i == 0 and off[i, j] > 0:
                b.quad([(xs[0], y, zs[j]), (xs[0], 0.0, zs[j]), (xs[0], 0.0, zs[j + 1]), (xs[0], y, zs[j + 1])],
                       (-1, 0, 0))
            above = off[i, j + 1] if j + 1 < nz else 0.0
            if above != off[i, j] and (j + 1 < nz or off[i, j] > 0):
                ya = -above
                b.quad([(xs[i], y, zs[j + 1]), (xs[i + 1], y, zs[j + 1]), (xs[i + 1], ya, zs[j + 1]),
                        (xs[i], ya, zs[j + 1])], (0, 0, np.sign(off[i, j] - above)))
        # the ground up to the front's foot (into the door recess, round the pillars' feet)
        foot = -off[i, 0]
        b.quad([(xs[i], -GROUND_DEPTH, 0.0), (xs[i + 1], -GROUND_DEPTH, 0.0), (xs[i + 1], foot, 0.0),
                (xs[i], foot, 0.0)], (0, 0, 1))
    for x0, x1 in ((-WIDTH / 2 - SIDE_GROUND, -WIDTH / 2), (WIDTH / 2, WIDTH / 2 + SIDE_GROUND)):
        b.quad([(x0, -GROUND_DEPTH, 0.0), (x1, -GROUND_DEPTH, 0.0), (x1, 0.0, 0.0), (x0, 0.0, 0.0)], (0, 0, 1))
    return b.mesh()


def facade_scene(mesh_file: str | os.PathLike, atlas_resolution: int = 1024) -> dict:
    """The scene JSON of :mod:`texstream.capture.synthetic.synth` for the facade mesh written at ``mesh_file``."""
    cells = [atlas_resolution // 5] * 2  # blotches of about 5 texels: a few pixels in the photos
    return {
        "name": "facade",
        "description": "A building front with relief and the ground before it (capture/synthetic/facade.py).",
        "mesh": {"file": str(mesh_file), "faces": 0},
        "texture": {"resolution": atlas_resolution, "padding": 2},
        "model": {"kind": "lafortune", "n_lobes": 1, "anisotropic": False},
        "materials": {
            "paving": {"rho_d": [0.12, 0.115, 0.11], "lobes": [{"rho_s": [0.03] * 3, "c_z": 1.0, "n": 20}],
                       "noise": {"amount": 0.7, "cells": cells, "octaves": 2, "seed": 5, "sharpness": 2.0}},
            "brick": {"rho_d": [0.17, 0.09, 0.06], "lobes": [{"rho_s": [0.04] * 3, "c_z": 1.0, "n": 30}],
                      "noise": {"amount": 0.8, "cells": cells, "octaves": 2, "seed": 6, "sharpness": 3.0}},
            "plaster": {"rho_d": [0.21, 0.2, 0.17], "lobes": [{"rho_s": [0.05] * 3, "c_z": 1.0, "n": 40}],
                        "noise": {"amount": 0.5, "cells": cells, "octaves": 2, "seed": 7, "sharpness": 1.5}},
        },
        # fractions of the bounding box's height: the ground, the wall up to the cornice, the cornice and frieze
        "assignment": {"rule": "bands", "axis": "z",
                       "bands": [[0.002, "paving"], [7.0 / HEIGHT, "brick"], [1.0, "plaster"]]},
        "cameras": {"layout": "ring", "count": 1, "distance": 1.0, "fov_deg": 60.0, "width": 640, "height": 480},
        "light": {"type": "directional", "mode": "fixed", "direction": [0.15, 0.85, -0.5], "intensity": 2.6},
        "photo": {"exposure": 1.0, "noise_sigma": 0.002, "bits": 8, "saturation": None},
    }


@dataclasses.dataclass
class FacadeConfig:
    """Options of the synthetic facade capture (module doc)."""

    photos: int = option(11, help="photos on the arc", min=2)
    width: int = option(640, help="photo width in pixels", min=32)
    height: int = option(480, help="photo height in pixels", min=32)
    fov_deg: float = option(60.0, help="horizontal field of view, degrees", min=5.0, max=150.0)
    arc_deg: float = option(70.0, help="the arc the cameras stand on, degrees (centred on the front's normal)",
                            min=0.0, max=170.0)
    distance: float = option(13.0, help="distance of the cameras from the front's middle, metres", min=1.0)
    exposure_stops: float = option(2.0, help="per-photo exposures spread evenly over this many stops", min=0.0)
    atlas_resolution: int = option(1024, help="the true texture atlas' larger side in texels", min=64)
    seed: int = option(0, help="noise and exposure order seed")
    device: str = option("cpu", help="Warp device for baking and rendering")


def facade_frames(cfg: FacadeConfig, light: dict) -> list[Frame]:
    """The arc of cameras (module doc) with exposures 2^-s/2 .. 2^s/2 in a seeded order."""
    fx = (cfg.width / 2) / math.tan(math.radians(cfg.fov_deg) / 2)
    intr = Intrinsics(width=cfg.width, height=cfg.height, fx=fx, fy=fx, cx=cfg.width / 2, cy=cfg.height / 2)
    target = np.array([0.0, 0.0, 3.2])
    exps = 2.0 ** np.linspace(-cfg.exposure_stops / 2, cfg.exposure_stops / 2, cfg.photos)
    exps = exps[np.random.default_rng([cfg.seed, 11]).permutation(cfg.photos)]
    frames = []
    for k, a in enumerate(np.radians(np.linspace(-cfg.arc_deg / 2, cfg.arc_deg / 2, cfg.photos))):
        eye = np.array([cfg.distance * math.sin(a), -cfg.distance * math.cos(a), 1.6])
        r, t = look_at_w2c(eye, target, up=(0.0, 0.0, 1.0))
        name = f"frame_{k:05d}"
        frames.append(Frame(file_path=f"images/{name}.png", R=r, t=t, intrinsics=intr,
                            light=Light.directional(light["direction"], np.repeat(float(light["intensity"]), 3)),
                            exposure=float(exps[k]), saturation=1.0))
    return frames


def synthesize_facade(out_dir: str | os.PathLike, config: FacadeConfig | None = None) -> StageResult:
    """Render the facade capture into ``out_dir`` (atomically): ``images/`` (8-bit sRGB PNG), ``capture.json``
    (cameras, exposures and the sun; no masks, no points) and ``ground_truth/``."""
    cfg = config or FacadeConfig()
    scfg = SynthConfig(device=cfg.device, seed=cfg.seed, progress=False, preview=False)
    with tempfile.TemporaryDirectory(prefix="texstream_facade_") as tmpdir:
        mesh_file = Path(tmpdir) / "facade.obj"
        save_mesh(mesh_file, facade_mesh())
        sc, mesh, bake, layout, params, mid, names, info = prepare_scene(
            facade_scene(mesh_file, cfg.atlas_resolution), scfg)
    frames = facade_frames(cfg, sc["light"])
    out_dir = Path(out_dir)
    with atomic_output_dir(out_dir) as tmp:
        gt = tmp / GROUND_TRUTH
        gt.mkdir(parents=True)
        for _, f, photo, _, _ in iter_renders(sc, mesh, params, layout, frames, scfg):
            write_image(tmp / f.file_path, photo, bits=8)
        write_capture(Capture(root=tmp, frames=frames, extra={"texstream_synthetic": "facade"}), tmp)
        save_mesh(gt / "mesh.obj", mesh)
        files = write_param_maps(gt, params, layout)
        bake.save(gt / "bake.npz")
        write_image(gt / "material_id.png", (mid + 1).astype(np.uint8), bits=8)
        counts = {"photos": len(frames), "image_width": cfg.width, "image_height": cfg.height,
                  "triangles": mesh.n_faces, "texture_width": bake.width, "texture_height": bake.height,
                  "exposures": [f.exposure for f in frames]}
        write_json_atomic(gt / "manifest.json", {
            "kind": "texstream synthetic ground truth", "layout": layout.to_json(), "scene": sc, "materials": names,
            "counts": counts, "mesh": "mesh.obj", "maps": files, "bake": "bake.npz", "mesh_info": info,
            "units": "metres; BRDF values in 1/sr; photos = exposure * radiance (capture/conventions.py)"})
        save_config(cfg, tmp / "facade_config.json")
    return StageResult(output=out_dir, summary=counts)
