"""A capture with cameras and nothing else (no masks, no SfM points) still gets a dense mesh (issue 38).

Synthetic: the ``textured_sphere`` scene made glossy (one Lafortune lobe, rho_s 0.4, n 60) under a
flash beside each camera, 16 photos of 128 x 128 on two rings, its masks removed from capture.json
and the folder: the mesh stage triangulates points with the given cameras, takes each photo's depth
range and matched region from them, runs dense stereo without masks and meshes the dense points.
benchmarks/posed_mesh.py measures the same at 24 photos of 192 pixels and the facade scene.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import SCENE_DEVICE


def glossy_sphere_scene() -> dict:
    """textured_sphere with a specular lobe and the flash a little off the lens (highlights move with the view)."""
    from texstream.capture.synthetic.synth import load_scene

    sc = load_scene("textured_sphere")
    sc["model"] = {"kind": "lafortune", "n_lobes": 1, "anisotropic": False}
    sc["materials"]["noisy"]["lobes"] = [{"rho_s": [0.4, 0.4, 0.4], "c_z": 1.0, "n": 60}]
    sc["light"]["offset"] = [0.3, -0.2, 0.0]
    return sc


def strip_to_cameras(root) -> None:
    """Remove the masks (files and capture.json entries) and any SfM points: cameras and photos only."""
    cj = json.loads((root / "capture.json").read_text())
    for f in cj["frames"]:
        f.pop("mask_path", None)
    (root / "capture.json").write_text(json.dumps(cj, indent=1))
    shutil.rmtree(root / "masks", ignore_errors=True)
    (root / "points3D.ply").unlink(missing_ok=True)


@pytest.fixture(scope="module")
def cameras_only(tmp_path_factory):
    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh

    root = tmp_path_factory.mktemp("posed") / "cap"
    synthesize(glossy_sphere_scene(), root, SynthConfig(photos=16, image_size=128, progress=False, preview=False,
                                                        device=SCENE_DEVICE))
    strip_to_cameras(root)
    res = make_mesh(root, root.parent / "mesh", MeshConfig(faces=8000))
    return {"summary": res.summary, "mesh": load_mesh(root.parent / "mesh" / "mesh.ply"),
            "truth": load_mesh(root / "ground_truth" / "mesh.obj"), "out": root.parent / "mesh"}


def test_cameras_only_glossy_object_meshes_within_half_a_percent(cameras_only):
    """Median distance both ways under 0.5% of the true bounding-box diagonal (the issue's bound; measured
    0.12% mesh to truth and 0.16% truth to mesh at this size, 2-core CPU dev box; 0.06% and 0.07% at 24
    photos of 192 pixels in benchmarks/posed_mesh.py). The underside no camera sees (the lower ring is 5
    degrees up) is left open or guessed (90th percentiles 1.3% and 9%), so only the median is bounded."""
    from texstream.geometry.mesh_error import mesh_error

    err = mesh_error(cameras_only["mesh"], cameras_only["truth"], samples=20000)
    assert err["made_to_true"]["median"] < 0.005
    assert err["true_to_made"]["median"] < 0.005


def test_cameras_only_report_says_what_was_used(cameras_only):
    """The report names the triangulation with the given cameras and dense stereo without masks, with the
    depth range's source; both point sets are written beside the mesh."""
    s = cameras_only["summary"]
    assert s["source"] == "sfm" and "without masks" in s["reason"]
    assert s["triangulation"]["points"] >= 50
    d = s["dense"]
    assert d["used"] and d["masks"].startswith("none")
    assert "triangulated here with the given cameras" in d["depth_range_from"]
    assert all("depth_range_source" in v for v in d["views"])
    # the point sets the report counts, with their normals
    from texstream.geometry.reconstruct import read_points

    sparse, sparse_normals = read_points(cameras_only["out"] / "points3D.ply")
    dense, dense_normals = read_points(cameras_only["out"] / "dense_points.ply")
    assert len(sparse) == s["triangulation"]["points"] and sparse_normals is not None
    assert len(dense) == d["points"] and dense_normals is not None


def test_depth_ranges_hold_the_points_with_margin():
    """Each photo's range holds the 1st-99th percentile depths of the points it sees, widened by 15% of the span;
    a scene's by a further factor 2 each way; a photo that sees too few points gets the robust box's range."""
    from texstream.geometry.hull import orbit_frames
    from texstream.geometry.posed_dense import PosedDenseConfig, depth_ranges_from_points

    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.3, (2000, 3))
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=4, elevations_deg=(0.0,), width=64, height=64)
    ranges, rep = depth_ranges_from_points(frames, pts)
    for f, (near, far) in zip(frames, ranges):
        z = (pts @ np.asarray(f.R).T + np.asarray(f.t).reshape(1, 3))[:, 2]
        lo, hi = np.percentile(z, [1, 99])
        assert near == pytest.approx(lo - 0.15 * (hi - lo), rel=0.02) and far == pytest.approx(hi + 0.15 * (hi - lo),
                                                                                                rel=0.02)
    scene, _ = depth_ranges_from_points(frames, pts, scene=True)
    assert scene[0][0] == pytest.approx(ranges[0][0] / 2) and scene[0][1] == pytest.approx(ranges[0][1] * 2)
    few, rep = depth_ranges_from_points(frames, pts[:5], PosedDenseConfig(min_points=20))
    assert "robust box" in rep[0]["source"] and few[0][0] < few[0][1]
