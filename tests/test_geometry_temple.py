"""Real photos: the Middlebury temple (16 ring views, known cameras, threshold masks) -> mesh.

The mesh stage's sparse path (``--dense off``; the dense one is tests/test_geometry_mvs.py) triangulates
SfM points from the known cameras (pycolmap), runs screened Poisson on them and intersects it with the
visual hull. One module-scoped run (about
30 s on the 2-core CPU dev box) serves every check.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import need_data
from texstream.geometry.clean import topology

# README.txt of templeSparseRing: the tight bounding box, metres
LO = np.array([-0.073568, 0.021728, -0.012445])
HI = np.array([0.028855, 0.181892, 0.062736])
DIAG = float(np.linalg.norm(HI - LO))

pytestmark = [pytest.mark.data, pytest.mark.slow]


@pytest.fixture(scope="module")
def temple(data_dir, tmp_path_factory):
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh
    from texstream.geometry.reconstruct import read_points
    from texstream.pipelines.cli import main

    src = need_data(data_dir, "middlebury_temple_sparse")
    tmp = tmp_path_factory.mktemp("temple")
    assert main(["import", "middlebury", str(src), "-o", str(tmp / "cap"), "--make-masks"]) == 0
    # the sparse path (dense stereo off; the dense one is tests/test_geometry_mvs.py)
    res = make_mesh(tmp / "cap", tmp / "mesh", MeshConfig(faces=20000, dense="off"))
    pts, nrm = read_points(tmp / "mesh" / "points3D.ply")
    return {"summary": res.summary, "mesh": load_mesh(tmp / "mesh" / "mesh.ply"), "points": pts, "normals": nrm,
            "capture": read_capture(tmp / "cap")}


def test_auto_is_poisson_with_hull_and_says_why(temple):
    s = temple["summary"]
    assert s["source"] == "sfm"
    assert "known cameras" in s["reason"] and "visual hull" in s["reason"]
    tri = s["triangulation"]
    # measured 4215 points (SIFT peak threshold 0.002, two-view tracks kept; 4200-4224 over RANSAC
    # seeds 0-7), median error 0.20 px; the Poisson minimum is 200
    assert tri["points"] > 2000 and tri["median_reprojection_error_px"] < 0.5


def test_triangulated_points_lie_in_the_readme_box_with_outward_normals(temple):
    p, n = temple["points"], temple["normals"]
    assert n is not None  # written with normals, read back as such
    inside = np.all((p > LO - 0.01 * DIAG) & (p < HI + 0.01 * DIAG), axis=1)
    # measured 99.98%: the mask, reprojection and isolation filters leave almost no background matches
    assert inside.mean() > 0.99
    # normals face the cameras that saw the points: towards the ring, away from the temple's axis
    axis_pt = 0.5 * (LO + HI)
    radial = p - axis_pt
    radial[:, 1] = 0  # y is the temple's vertical axis (the ring of cameras goes round it)
    # most points are on the outer walls and columns; recesses and the roof make the rest (measured
    # 0.818-0.820 over RANSAC seeds 0-7)
    assert np.mean(np.einsum("ij,ij->i", n, radial) > 0) > 0.7


def test_mesh_is_closed_inside_the_box_and_covers_the_points(temple):
    from texstream.geometry.reconstruct import point_surface_distance

    m = temple["mesh"]
    t = topology(m)
    assert t["watertight"] and t["signed_volume"] > 0
    mlo, mhi = m.bbox()
    # inside the README's tight box up to the hull's error: 16 ring views leave the base under-
    # constrained (measured 1 cm of 20 cm below the box, as for the hull alone)
    assert np.all(mlo > LO - 0.06 * DIAG) and np.all(mhi < HI + 0.06 * DIAG)
    # covering the object: spans at least 90% of each side of the box
    assert np.all((np.minimum(mhi, HI) - np.maximum(mlo, LO)) > 0.9 * (HI - LO))
    # and the SfM points lie on it: 1% of the diagonal is 2 mm (measured 96% after decimation to
    # 20k faces; the hull alone, which cannot enter the recesses, has 67%)
    d = point_surface_distance(temple["points"], m)
    assert np.mean(d < 0.01 * DIAG) > 0.9


def test_density_atlas_gives_every_face_texels_and_evens_texel_size(temple, device):
    from texstream.geometry.atlas import AtlasConfig, build_atlas
    from texstream.geometry.density import density_face_weights, texel_size_spread
    from texstream.geometry.visibility import depth_maps

    m, frames = temple["mesh"], temple["capture"].frames
    depths = depth_maps(m, frames, device)
    w = density_face_weights(m, frames, device, depths)
    uni_mesh, uni = build_atlas(m, AtlasConfig())
    den_mesh, den = build_atlas(m, AtlasConfig(), face_weights=w)
    s_uni = texel_size_spread(uni_mesh, uni.width, uni.height, frames, device)
    s_den = texel_size_spread(den_mesh, den.width, den.height, frames, device)
    print(f"temple atlas, uniform: {uni.n_charts} charts, {uni.n_covered} texels, {s_uni}\n"
          f" density: {den.n_charts} charts, {den.n_covered} texels, {s_den}")
    # The Poisson mesh in metres has faces below float32 epsilon and UV vertices closer than xatlas'
    # weld distance, and the 16 ring views give noisy per-face weights (1% below 1/30 of the median):
    # before, 105 faces (uniform) and 405 (density) had no texel; now none.
    assert uni.faces_without_texels == 0 and den.faces_without_texels == 0
    # 16 views on one ring: faces seen from above or obliquely get few pixels, so a uniform atlas's
    # texel size varies widely; the density atlas evens it. The mesh is reproducible (one SIFT
    # extraction thread, triangulate.py): uniform p90/p10 2.16, log2 std 0.69 octave; density 1.25,
    # 0.38. Figures vary with the mesh, so the bounds hold for each of 12 equally valid meshes (RANSAC
    # seeds 0-7, and 6 runs of the former multi-threaded extraction, which gave 4 distinct meshes):
    # uniform p90/p10 2.16-2.30, density 1.23-1.28, their ratio 0.55-0.58.
    assert s_uni["p90_over_p10"] > 1.8
    assert s_den["p90_over_p10"] < 1.45 and s_den["p90_over_p10"] < 0.7 * s_uni["p90_over_p10"]
    # The log2 std is not a quantile: 0.8-1.9% of the area is seen only at grazing angles (clipped to
    # the lowest density weight, 1/64, yet 2-7.5 octaves below the median texel size in either atlas),
    # and how much of it a mesh has moves the std of both: density over uniform measured 0.36-0.71
    # over the same 12 meshes (0.54 for the reproducible one; 0.71 on seed 3, whose grazing area is
    # 1.9% against 0.8% on seed 0). It still has to be clearly below the uniform atlas's.
    assert s_den["log2_std"] < 0.85 * s_uni["log2_std"]


def test_mesh_faces_the_cameras_with_few_handles(temple):
    """Camera rays hit front faces; mask holes and voxel-scale tunnels are closed (geometry/scene.py, hull.py)."""
    from texstream.geometry.scene import camera_facing, cameras_enclosed, genus_by_component

    s, m, frames = temple["summary"], temple["mesh"], temple["capture"].frames
    assert s["capture_kind"]["kind"] == "object" and s["capture_kind"]["cameras_in_box"] == 0.0
    assert s["cameras_enclosed"] == 0 and not cameras_enclosed(m, np.array([f.center for f in frames])).any()
    fac = camera_facing(m, frames, "cpu", 64)
    print(f"temple: {fac.to_json()}, genus {genus_by_component(m)}, hull {s['hull']}")
    # a closed outward surface seen from outside: measured 0 back hits of 10,900 (64 rays per image
    # side); up to 1% allowed for faces that decimation folds over (tests/test_geometry_scene.py)
    assert fac.hits > 5000 and fac.back_fraction < 0.01
    assert s["facing"]["flipped_components"] == 0
    # genus 133 before the hull filled mask holes under 1% of the silhouette (threshold-mask noise,
    # 11,635 px in 16 views); measured 10 after filling. Closing the carved field by one cell
    # (--closing 1) gives 3, stable at closing 2 and at fill 2% (the real gaps between the columns),
    # but is off by default: with it this file's density-atlas test fails (p90/p10 1.71 > 1.45)
    # the hull fill (geometry/hull_fill.py) adds hull samples where no SfM point is near and fewer than two
    # cameras see the surface well; on the temple's sparse points that leaves one closed piece of ~700 faces
    # (3.6% of the main one's; measured) beside the body: allowed, as long as the body stays one piece
    g = genus_by_component(m)
    assert g["components"] <= 2 and g["per_component"][0] <= 14
