"""The mesh stage / ``texstream mesh``: source choice with reasons, fallbacks and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texstream.capture.capture_json import Capture, write_capture
from texstream.capture.imageio import write_image
from texstream.geometry.hull import orbit_frames
from texstream.geometry.make_mesh import MeshConfig, make_mesh
from texstream.geometry.mesh_io import load_mesh, save_mesh
from texstream.geometry.visibility import depth_maps
from texstream.pipelines.cli import main
from texstream.core.config import load_config
from texstream.core.errors import InputError
from test_geometry_clean import icosphere
from test_geometry_poisson import sample_surface


def _capture(tmp_path, masks=True, n_points=0):
    """A ring capture of a unit sphere: masks from depth maps, optional SfM-like points (PLY, no normals)."""
    sphere = icosphere(4)
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=8, elevations_deg=(-35, 0, 35), width=96, height=96)
    root = tmp_path / "cap"
    (root / "masks").mkdir(parents=True)
    if masks:
        for f, d in zip(frames, depth_maps(sphere, frames, "cpu")):
            f.mask_path = f"masks/{f.name}.png"
            write_image(root / f.mask_path, np.isfinite(d).astype(np.uint8)[:, :, None] * np.uint8(255))
    write_capture(Capture(root=root, frames=frames))
    if n_points:
        import pymeshlab as ml

        pts, _ = sample_surface(sphere, n_points)
        ms = ml.MeshSet()
        ms.add_mesh(ml.Mesh(vertex_matrix=pts))
        ms.save_current_mesh(str(root / "points3D.ply"), save_vertex_normal=False)
    return root, sphere


def test_auto_picks_hull_when_only_masks(tmp_path):
    root, sphere = _capture(tmp_path)
    cfg = MeshConfig(faces=2000, hull_resolution=64)
    res = make_mesh(root, tmp_path / "out", cfg)
    assert res.summary["source"] == "hull" and "masks" in res.summary["reason"]
    mesh = load_mesh(tmp_path / "out" / "mesh.ply")
    # 64-node grid: step ~0.04 on a radius-1 sphere; the hull lies outside the sphere by < 3 steps
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(np.median(r) - 1) < 0.05 and mesh.n_faces <= 2000
    # the options that made it, the device resolved ("auto": cuda:0 where there is one, else cpu)
    saved = load_config(MeshConfig, tmp_path / "out" / "mesh_config.json")
    assert saved.device in ("cpu", "cuda:0") and dataclasses.replace(saved, device=cfg.device) == cfg


def test_too_few_points_fall_back_to_hull_and_say_so(tmp_path):
    root, _ = _capture(tmp_path, masks=True, n_points=50)
    res = make_mesh(root, tmp_path / "out", MeshConfig(faces=1000, hull_resolution=48))
    assert res.summary["source"] == "hull" and "too few SfM points" in res.summary["reason"]


def test_too_few_points_without_masks_names_fallback(tmp_path, capsys):
    root, _ = _capture(tmp_path, masks=False, n_points=50)
    assert main(["mesh", str(root), "-o", str(tmp_path / "out"), "--from", "sfm"]) == 1
    err = capsys.readouterr().err
    assert "only 50 points" in err and "--from hull" in err and "--from scan.obj" in err
    assert not (tmp_path / "out").exists()  # nothing half-written


def test_misaligned_scan_is_refused_with_fix(tmp_path):
    root, sphere = _capture(tmp_path, masks=False)
    far = type(sphere)(sphere.vertices + [100.0, 0, 0], sphere.faces)
    save_mesh(tmp_path / "far.obj", far)
    with pytest.raises(InputError, match="not where the cameras look.*--matrix"):
        make_mesh(root, tmp_path / "out", MeshConfig(mesh=str(tmp_path / "far.obj"), faces=500))
    # the same mesh with the matrix that brings it back is accepted
    m = np.eye(4)
    m[0, 3] = -100.0
    (tmp_path / "m.txt").write_text("\n".join(" ".join(map(str, r)) for r in m))
    res = make_mesh(root, tmp_path / "out", MeshConfig(mesh=str(tmp_path / "far.obj"), faces=500,
                                                       matrix=str(tmp_path / "m.txt")))
    assert res.summary["alignment"]["method"] == "matrix"


def test_inside_out_scan_is_fixed_and_reported(tmp_path):
    s = icosphere(3)
    save_mesh(tmp_path / "inv.ply", type(s)(s.vertices, s.faces[:, ::-1].copy()))
    assert main(["mesh", "-o", str(tmp_path / "out"), "--from", str(tmp_path / "inv.ply"), "--faces", "0"]) == 0
    from texstream.core.outputs import read_json

    rep = read_json(tmp_path / "out" / "mesh_report.json")
    assert rep["clean"]["flipped"] and rep["clean"]["after"]["signed_volume"] > 0


def test_empty_mesh_file_names_fallback(tmp_path, capsys):
    (tmp_path / "empty.obj").write_text("# nothing\n")
    assert main(["mesh", "-o", str(tmp_path / "out"), "--from", str(tmp_path / "empty.obj")]) == 1
    err = capsys.readouterr().err
    assert "empty.obj" in err and "--from sfm" in err
