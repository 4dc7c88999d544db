"""SfM-point meshes of scenes and objects: bounded by the points, facing the cameras, few handles.

A synthetic outdoor-like scene (a ground plane with four boxes; eight cameras stand inside it and
look out at the boxes) gives SfM-like points: ray-cast pixels of the cameras, with noise and
outliers, no normals. Screened Poisson closes that into a balloon around the cameras whose faces
turn away from them (what broke on real photos); the mesh stage must detect a scene, crop to the
points' robust extent and face the cameras. A turntable object (cameras on rings outside it) with
noisy masks gives a hull that faces outwards, is watertight and has genus 0.
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.capture_json import Capture, Frame, Intrinsics, write_capture
from texstream.capture.conventions import look_at_w2c
from texstream.core.errors import StageError
from texstream.render.mesh import SurfaceMesh
from texstream.geometry.scene import (camera_facing, cameras_enclosed, check_facing, classify_capture,
                                      genus_by_component, orient_to_cameras, robust_box)
from texstream.geometry.visibility import depth_maps


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # corner index = 4 * ix + 2 * iy + iz; two triangles per side, counter-clockwise from outside
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = lo, x = hi
                  [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = lo, y = hi
                  [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])  # z = lo, z = hi
    return v, f


def _ground(half: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(-half, half, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i, i + (n + 1), i + (n + 1) + 1, i + 1
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f  # counter-clockwise seen from +z


def outdoor_scene() -> tuple[SurfaceMesh, list]:
    """Ground plane [-6, 6]^2 (z up), four 1 x 1 x 1.5 boxes at radius 3.5, eight cameras at radius 1.5,
    1 m high, looking outwards (four at the boxes, four between them)."""
    parts = [_ground(6.0, 24)]
    for a in np.radians([0, 90, 180, 270]):
        c = 3.5 * np.array([np.cos(a), np.sin(a)])
        parts.append(_box([c[0] - 0.5, c[1] - 0.5, 0.0], [c[0] + 0.5, c[1] + 0.5, 1.5]))
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    mesh = SurfaceMesh(np.concatenate(vs), np.concatenate(fs).astype(np.int32))
    intr = Intrinsics(width=80, height=60, fx=50.0, fy=50.0, cx=40.0, cy=30.0)  # 77 deg horizontal field
    frames = []
    for i, a in enumerate(np.radians(np.arange(0, 360, 45))):
        d = np.array([np.cos(a), np.sin(a), 0.0])
        r, t = look_at_w2c(1.5 * d + [0, 0, 1.0], 3.5 * d + [0, 0, 0.4])
        frames.append(Frame(file_path=f"images/{i:04d}.png", R=r, t=t, intrinsics=intr))
    return mesh, frames


def sfm_like_points(mesh: SurfaceMesh, frames, n: int = 6000, noise: float = 0.01, outliers: float = 0.02,
                    seed: int = 0) -> np.ndarray:
    """Surface points seen by the cameras (ray-cast pixels), Gaussian noise of ``noise`` units, and a
    fraction ``outliers`` of points uniform in a box three times the scene's (some far off)."""
    rng = np.random.default_rng(seed)
    pts = []
    for fr, d in zip(frames, depth_maps(mesh, frames, "cpu")):
        j, i = np.nonzero(np.isfinite(d))
        k = fr.intrinsics
        cam = np.stack([(i + 0.5 - k.cx) / k.fx, (j + 0.5 - k.cy) / k.fy, np.ones(len(i))], 1) * d[j, i][:, None]
        pts.append((cam - np.asarray(fr.t).reshape(1, 3)) @ np.asarray(fr.R))
    p = np.concatenate(pts)
    p = p[rng.choice(len(p), size=min(n, len(p)), replace=False)] + rng.normal(0, noise, (min(n, len(p)), 3))
    lo, hi = mesh.bbox()
    mid, ext = 0.5 * (lo + hi), hi - lo
    out = mid + (rng.random((int(outliers * len(p)), 3)) - 0.5) * 3 * ext
    return np.concatenate([p, out])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh
    from texstream.geometry.triangulate import write_points

    truth, frames = outdoor_scene()
    pts = sfm_like_points(truth, frames)
    root = tmp_path_factory.mktemp("scene") / "cap"
    root.mkdir()
    write_capture(Capture(root=root, frames=frames))
    write_points(root / "points3D.ply", pts)  # no normals, as from SfM
    out = root.parent / "mesh"
    res = make_mesh(root, out, MeshConfig(faces=8000, poisson_depth=7))
    return {"summary": res.summary, "mesh": load_mesh(out / "mesh.ply"), "points": pts, "frames": frames,
            "truth": truth}


def test_scene_is_detected_with_its_reason(scene):
    ck = scene["summary"]["capture_kind"]
    assert ck["kind"] == "scene" and ck["cameras_in_box"] == 1.0
    assert "inside the SfM points' robust bounding box" in ck["reason"]


def test_scene_mesh_is_bounded_by_the_points(scene):
    m, pts = scene["mesh"], scene["points"]
    lo, hi = robust_box(pts, 2.0, 0.0)
    pad = 0.05 * np.linalg.norm(hi - lo) + 1e-3 * np.linalg.norm(hi - lo)  # + decimation's vertex moves
    mlo, mhi = m.bbox()
    # inside the points' robust box (percentiles 2-98) grown by its 5% margin, whatever the outliers
    assert np.all(mlo >= lo - pad) and np.all(mhi <= hi + pad), (mlo, mhi, lo, hi)
    # so within a small factor of the points' extent (measured 1.04 of the robust box's diagonal; the
    # balloon Poisson makes round the cameras is 2x the full extent of the points, outliers included)
    ratio = np.linalg.norm(mhi - mlo) / np.linalg.norm(hi - lo)
    print(f"scene mesh bbox diagonal / points' robust diagonal: {ratio:.3f}")
    assert ratio < 1.15
    assert not cameras_enclosed(m, np.array([f.center for f in scene["frames"]])).any()
    # and it covers the scene: the ground under the cameras and the boxes are there
    from texstream.geometry.reconstruct import point_surface_distance

    inl = pts[:6000]  # the inliers (sfm_like_points puts the outliers last)
    d = point_surface_distance(inl, m)
    inner = np.linalg.norm(inl[:, :2], axis=1) < 5.0
    print(f"scene inliers within 0.1 of the mesh: {np.mean(d < 0.1):.3f}, inside radius 5: {np.mean(d[inner] < 0.1):.3f}")
    # 0.1 is 10 noise sigmas and one Poisson cell (1.1 * 12 / 128). Inside radius 5 every point is
    # covered (measured 1.000); the sparse far ground out to 6 lies partly beyond the points' 98th
    # percentile and is cropped by design (measured 0.955 of all inliers covered)
    assert np.mean(d[inner] < 0.1) > 0.99 and np.mean(d < 0.1) > 0.9


def test_scene_mesh_faces_the_cameras(scene):
    f = scene["summary"]["facing"]["after"]
    # every camera ray first hits a face from its front on a surface that faces the cameras; what
    # remains are grazing rays along crop borders and the boxes' rounded edges (measured in the report)
    assert f["hits"] > 1000 and f["back_fraction"] < 0.02, f
    again = camera_facing(scene["mesh"], scene["frames"], "cpu", 48)
    assert again.back_fraction < 0.02
    assert scene["summary"]["cameras_enclosed"] == 0


def test_raw_poisson_balloon_is_caught(scene):
    """What broke: the uncropped Poisson surface encloses the cameras and faces away from them."""
    from texstream.geometry.reconstruct import PoissonConfig, poisson_reconstruct

    frames = scene["frames"]
    centres = np.array([f.center for f in frames])
    raw = poisson_reconstruct(scene["points"], None, centres, PoissonConfig(depth=7, density_quantile=0.0))
    assert cameras_enclosed(raw, centres).all()
    lo, hi = robust_box(scene["points"], 2.0, 0.0)
    rlo, rhi = raw.bbox()
    assert np.any(rhi - rlo > 1.5 * (hi - lo))  # the balloon
    fac = camera_facing(raw, frames, "cpu", 32)
    assert fac.back_fraction > 0.5
    with pytest.raises(StageError, match="back of a face"):
        check_facing(fac, 0.05)
    # per-component orientation turns it towards the cameras (it still encloses them: the stage crops)
    fixed, rep = orient_to_cameras(raw, frames, "cpu", 32)
    assert rep["flipped_components"] >= 1 and rep["after"]["back_fraction"] < 0.5


def test_object_capture_is_detected():
    from texstream.geometry.hull import orbit_frames
    from test_geometry_clean import icosphere
    from test_geometry_poisson import sample_surface

    pts, _ = sample_surface(icosphere(3), 2000)
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=8, elevations_deg=(-30, 0, 30))
    ck = classify_capture(pts, np.array([f.center for f in frames]))
    assert ck.kind == "object" and ck.cameras_in_box == 0.0 and "outside" in ck.reason
    # a flat cloud (a ground patch) with cameras above it is a scene, seen from above
    rng = np.random.default_rng(0)
    flat = np.c_[rng.uniform(-5, 5, (2000, 2)), rng.normal(0, 0.05, 2000)]
    cams = np.c_[rng.uniform(-3, 3, (10, 2)), np.full(10, 4.0)]
    ck = classify_capture(flat, cams)
    assert ck.kind == "scene" and "from above" in ck.reason


def _turntable_object() -> SurfaceMesh:
    """A genus-0 object with a concavity: an L of two boxes welded into one closed surface by pymeshlab."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    for lo, hi in (([-1, -1, -1], [1, 1, 0]), ([-1, -1, 0], [0, 1, 1])):
        v, f = _box(lo, hi)
        ms.add_mesh(ml.Mesh(vertex_matrix=v, face_matrix=f))
    ms.generate_boolean_union(first_mesh=0, second_mesh=1)
    m = ms.current_mesh()
    return SurfaceMesh(np.asarray(m.vertex_matrix(), float), np.asarray(m.face_matrix(), np.int32))


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    from texstream.capture.imageio import write_image
    from texstream.geometry.hull import orbit_frames
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh

    obj = _turntable_object()
    frames = orbit_frames([0, 0, 0], 5.0, n_azimuth=8, elevations_deg=(-30, 0, 30), width=96, height=96)
    rng = np.random.default_rng(1)
    root = tmp_path_factory.mktemp("turntable") / "cap"
    (root / "masks").mkdir(parents=True)
    masks = []
    for f, d in zip(frames, depth_maps(obj, frames, "cpu")):
        m = np.isfinite(d)
        # threshold-mask noise: a few 2 x 2 pixel holes inside the silhouette (as on the temple)
        j, i = np.nonzero(m)
        for k in rng.choice(len(j), size=4, replace=False):
            m[j[k]:j[k] + 2, i[k]:i[k] + 2] = False
        masks.append(m)
        f.mask_path = f"masks/{f.name}.png"
        write_image(root / f.mask_path, m.astype(np.uint8)[:, :, None] * np.uint8(255))
    write_capture(Capture(root=root, frames=frames))
    res = make_mesh(root, root.parent / "mesh", MeshConfig(faces=4000, hull_resolution=64))
    return {"summary": res.summary, "mesh": load_mesh(root.parent / "mesh" / "mesh.ply"), "frames": frames,
            "masks": masks, "object": obj}


def test_turntable_hull_faces_out_is_watertight_genus_0(turntable):
    from texstream.geometry.clean import topology

    s = turntable["summary"]
    assert s["source"] == "hull"
    t = topology(turntable["mesh"])
    assert t["watertight"] and t["signed_volume"] > 0
    assert t["genus"] == 0 and s["genus"]["total"] == 0 and s["hull"]["genus"] == 0
    # a closed outward surface seen from outside: no first hit is a back face, but for the few faces that
    # quadric decimation folds over (measured 0.15-0.3% of the hits at 4000 faces, 0 undecimated;
    # brute-force ray casting agrees, so it is the mesh and not the ray test)
    assert s["facing"]["after"]["back_fraction"] < 0.01 and s["facing"]["flipped_components"] == 0
    assert s["cameras_enclosed"] == 0


def test_mask_holes_make_tunnels_that_filling_and_closing_remove(turntable):
    from texstream.geometry.hull import HullConfig, visual_hull

    frames, masks = turntable["frames"], turntable["masks"]
    rep_raw: dict = {}
    raw = visual_hull(frames, masks, HullConfig(resolution=64, fill_holes=0.0, closing=0), report=rep_raw)
    g_raw = genus_by_component(raw)["total"]
    # each mask hole carves a tunnel through the hull along its view
    assert g_raw > 0
    rep: dict = {}
    fixed = visual_hull(frames, masks, HullConfig(resolution=64), report=rep)
    assert genus_by_component(fixed)["total"] == 0 and rep["mask_pixels_filled"] > 0
    # without filling, closing the carved field by one cell closes the 2-pixel tunnels too
    closed = visual_hull(frames, masks, HullConfig(resolution=64, fill_holes=0.0, closing=1))
    print(f"turntable hull genus: raw {g_raw}, filled {genus_by_component(fixed)['total']}, "
          f"closed {genus_by_component(closed)['total']}")
    assert genus_by_component(closed)["total"] < g_raw


def test_genus_by_component_counts_handles_and_boundaries():
    from test_geometry_clean import icosphere

    sphere = icosphere(2)
    assert genus_by_component(sphere)["total"] == 0
    # a sphere with a cap cut off: genus 0, one boundary loop
    keep = sphere.vertices[sphere.faces].mean(axis=1)[:, 2] < 0.8
    cut = SurfaceMesh(sphere.vertices, sphere.faces[keep])
    g = genus_by_component(cut)
    assert g["total"] == 0 and g["boundary_loops"] == 1
    # a torus: genus 1
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.linspace(0, 2 * np.pi, 12, endpoint=False),
                       indexing="ij")
    verts = np.stack([(2 + np.cos(v)) * np.cos(u), (2 + np.cos(v)) * np.sin(u), np.sin(v)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(24), np.arange(12), indexing="ij")
    a, b = i * 12 + j, ((i + 1) % 24) * 12 + j
    c, d = ((i + 1) % 24) * 12 + (j + 1) % 12, i * 12 + (j + 1) % 12
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    assert genus_by_component(SurfaceMesh(verts, faces.astype(np.int32)))["total"] == 1


def test_a_shell_inside_the_body_is_removed():
    """Poisson can close a pocket inside an object's body: a closed component every vertex of which lies
    inside another component is seen by no camera and is dropped; a separate piece outside stays."""
    from texstream.capture.synthetic import procedural
    from texstream.geometry.scene import drop_enclosed_components

    outer = procedural.uv_sphere(1.0, n_segments=24, n_rings=12)
    inner = procedural.uv_sphere(0.3, n_segments=12, n_rings=6)
    beside = procedural.uv_sphere(0.3, n_segments=12, n_rings=6)

    def join(*meshes):
        vs, fs, off = [], [], 0
        for m, shift in meshes:
            vs.append(m.vertices + shift)
            fs.append(m.faces + off)
            off += len(m.vertices)
        return SurfaceMesh(np.concatenate(vs), np.concatenate(fs))

    both = join((outer, 0.0), (inner, 0.0), (beside, np.array([3.0, 0.0, 0.0])))
    kept, removed = drop_enclosed_components(both)
    assert removed == 1 and kept.n_faces == outer.n_faces + beside.n_faces
    assert drop_enclosed_components(join((outer, 0.0)))[1] == 0
