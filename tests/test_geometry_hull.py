"""Visual hull (Warp carving + marching cubes) of synthetic captures against the true surface.

Masks come from ray-cast depth maps of the known mesh (a mask only needs coverage).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from texstream.geometry.clean import CleanConfig, clean_mesh, hausdorff_distance
from texstream.geometry.hull import HullConfig, orbit_frames, visual_hull
from texstream.geometry.visibility import depth_maps
from texstream.core.errors import StageError
from conftest import need_data
from test_geometry_clean import icosphere, load_obj


def _masks(mesh, frames, device):
    return [np.isfinite(d) for d in depth_maps(mesh, frames, device)]


def test_sphere_hull_within_1pct(device):
    sphere = icosphere(4)
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=8, elevations_deg=(-35, 0, 35), width=160, height=160)
    hull = visual_hull(frames, _masks(sphere, frames, device), HullConfig(), device)
    h = hausdorff_distance(hull, sphere)
    # the bound: mean distance within 1% of the bbox diagonal (measured ~0.08%: 26 views leave
    # small cone facets; the grid step is 1.2% of the diagonal, marching cubes interpolates below it)
    assert h["mean_fraction"] < 0.01
    # The visual hull contains the object: no hull vertex is well inside the sphere.
    r = np.linalg.norm(hull.vertices, axis=1)
    assert r.min() > 1 - 0.01


@pytest.mark.slow
def test_bunny_hull_within_1pct(data_dir):
    bunny = load_obj(need_data(data_dir, "stanford_bunny") / "stanford-bunny.obj")
    bunny, _ = clean_mesh(bunny, CleanConfig(target_faces=20000, hausdorff=False, max_hole_edges=1000))
    lo, hi = bunny.bbox()
    frames = orbit_frames((lo + hi) / 2, 1.6 * bunny.bbox_diagonal(), n_azimuth=8, elevations_deg=(-35, 0, 35),
                          width=160, height=160, up=(0, 1, 0))
    t0 = time.perf_counter()
    hull = visual_hull(frames, _masks(bunny, frames, "cpu"), HullConfig(), "cpu")
    h = hausdorff_distance(hull, bunny)
    print(f"bunny hull {time.perf_counter() - t0:.2f} s, mean {100 * h['mean_fraction']:.3f}% of diagonal")
    # issue bound 1% (measured ~0.4%: concavities between the ears and under the body stay filled)
    assert h["mean_fraction"] < 0.01


def test_misaligned_masks_say_what_to_do(device):
    sphere = icosphere(2)
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=4, elevations_deg=(0,), width=64, height=64, poles=False)
    masks = _masks(sphere, frames, device)
    masks = [np.roll(m, 30 * (i % 2) - 15, axis=1) for i, m in enumerate(masks)]  # silhouettes shifted apart
    masks[0][:] = False
    with pytest.raises(StageError, match="--from sfm"):
        visual_hull(frames, masks, HullConfig(resolution=32), device)


@pytest.mark.slow
def test_temple_hull_fills_the_readme_bbox(data_dir, tmp_path):
    """Real photos: Middlebury temple imported with threshold masks, hull via the mesh stage."""
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh
    from texstream.pipelines.cli import main

    src = need_data(data_dir, "middlebury_temple_sparse")
    assert main(["import", "middlebury", str(src), "-o", str(tmp_path / "cap"), "--make-masks"]) == 0
    res = make_mesh(tmp_path / "cap", tmp_path / "mesh", MeshConfig(source="hull", faces=20000))
    assert res.summary["source"] == "hull"
    m = load_mesh(tmp_path / "mesh" / "mesh.ply")
    lo, hi = np.array([-0.073568, 0.021728, -0.012445]), np.array([0.028855, 0.181892, 0.062736])
    diag = np.linalg.norm(hi - lo)
    mlo, mhi = m.bbox()
    # inside the README's tight box up to the hull's margin of error (16 ring views leave the base
    # under-constrained: measured 1 cm of 20 cm below the box) and covering at least 90% of each side
    assert np.all(mlo > lo - 0.06 * diag) and np.all(mhi < hi + 0.06 * diag)
    assert np.all((np.minimum(mhi, hi) - np.maximum(mlo, lo)) > 0.9 * (hi - lo))


def test_mask_fields_are_computed_once_per_mask():
    """The mesh stage carves the same masks three times: the filled masks and signed distances are remembered
    by the masks' bytes (the same arrays come back), and equal a fresh computation."""
    from texstream.geometry.hull import fill_small_holes, mask_fields, mask_sdf

    rng = np.random.default_rng(0)
    masks = [rng.random((40, 50)) < 0.7, np.pad(np.ones((20, 20), bool), 10)]
    filled, sdfs = mask_fields(masks, 0.01)
    for m, f, s in zip(masks, filled, sdfs):
        assert np.array_equal(f, fill_small_holes(m, 0.01)) and np.array_equal(s, mask_sdf(f))
    again = mask_fields([m.copy() for m in masks], 0.01)
    assert all(a is b for a, b in zip(again[1], sdfs))
    assert mask_fields(masks, 0.0)[1][0] is not sdfs[0]  # another fill: another entry


def test_mask_fields_past_the_budget_keep_the_first_masks_on_every_pass(monkeypatch):
    """A set of masks larger than the budget keeps those that fit (each later pass finds them; forgetting the
    oldest made every pass of the 6 MP run's 11 masks miss), and another capture's masks are forgotten first."""
    import texstream.geometry.hull as hull

    monkeypatch.setattr(hull, "_FIELDS_CACHE", type(hull._FIELDS_CACHE)())
    one = 30 * 40 * (1 + 4)  # a 30x40 mask's filled bools and float32 distances
    monkeypatch.setattr(hull, "_FIELDS_CACHE_BYTES", 3 * one)
    rng = np.random.default_rng(1)
    masks = [rng.random((30, 40)) < 0.6 for _ in range(5)]
    first = hull.mask_fields(masks, 0.0)[1]
    second = hull.mask_fields(masks, 0.0)[1]
    assert [a is b for a, b in zip(first, second)] == [True, True, True, False, False]
    other = [rng.random((30, 40)) < 0.6 for _ in range(2)]
    hull.mask_fields(other, 0.0)
    assert len(hull._FIELDS_CACHE) == 3  # two of the first set's forgotten for the other set's two
    assert hull.mask_fields(other, 0.0)[1][1] is hull.mask_fields(other, 0.0)[1][1]
