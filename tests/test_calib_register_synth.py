"""Registration of a textured synthetic capture (capture/synthetic/scenes/textured_sphere.json) against its known
poses, and alignment of the registered model to a given mesh frame."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from texstream.calib.register import RegisterConfig, register
from texstream.capture.capture_json import read_capture

from conftest import pose_errors


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    """24 sRGB photos (256 px, two rings at 5 and 35 degrees elevation) of a noise-textured sphere, and the
    calibrated intrinsics file ``register`` accepts (the renderer's exact pinhole K)."""
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("synth_reg")
    cap = root / "sphere"
    synthesize("textured_sphere", cap, SynthConfig(progress=False, preview=False))
    i = read_capture(cap).frames[0].intrinsics
    (root / "K.json").write_text(json.dumps({"w": i.width, "h": i.height, "fl_x": i.fx, "fl_y": i.fy,
                                             "cx": i.cx, "cy": i.cy}))
    return cap, root / "K.json"


def test_textured_synthetic_capture_recovers_known_poses(sphere_capture, tmp_path):
    cap, k_file = sphere_capture
    t0 = time.time()
    cfg = RegisterConfig(max_num_features=2000, intrinsics=str(k_file), align_to=str(cap / "capture.json"),
                         num_threads=2, photometric="off")
    res = register(cap, tmp_path / "posed", cfg)
    s = res.summary
    assert len(s["registered"]) == 24 and not s["unregistered"], s  # every view overlaps its ring neighbours
    got, truth = read_capture(tmp_path / "posed"), read_capture(cap)
    cen, rot = pose_errors(got, truth)
    # Done-when: after Sim3 alignment, centres within 2% of the ring diameter and rotations within 2 degrees.
    # (Measured: worst frame ~0.9% / ~1.3 deg, median ~0.1% / ~0.2 deg; the worst frames sit in a shallow
    # rotation-vs-translation valley of a convex object seen by a 45-degree lens, not a convention error:
    # the ground-truth poses reproject the same tracks to the same 0.15 px.)
    assert cen.max() < 0.02, cen
    assert rot.max() < 2.0, rot
    assert np.median(rot) < 0.5  # the typical frame is far tighter than the done-when bound
    assert s["mean_reprojection_error"] < 0.5  # exact renders, 8-bit quantisation only
    assert got.frames[0].intrinsics.fx == pytest.approx(truth.frames[0].intrinsics.fx)  # K fixed
    print(f"textured sphere: 24/24, centre max {cen.max():.4f} / median {np.median(cen):.4f} of diameter, "
          f"rotation max {rot.max():.3f} / median {np.median(rot):.3f} deg, register {time.time() - t0:.1f} s")


# ------------------------------------------------------------------------------ alignment to a mesh frame


def _lumpy_mesh():
    """An icosphere pushed into an asymmetric potato (no symmetry the PCA start could confuse)."""
    from texstream.capture.synthetic.procedural import icosphere
    from texstream.render.mesh import SurfaceMesh

    m = icosphere(1.0, 3)
    v = m.vertices
    v = v * np.array([1.6, 1.0, 0.7]) * (1 + 0.25 * v[:, :1] + 0.15 * v[:, 1:2] ** 2 - 0.2 * v[:, 2:3] ** 3)
    return SurfaceMesh(vertices=v, faces=m.faces)


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_mesh_frame_transform_brings_sfm_points_and_cameras_onto_the_mesh():
    from texstream.geometry.mesh_frame import mesh_frame_transform
    from texstream.geometry.align import sample_mesh

    mesh = _lumpy_mesh()
    diag = mesh.bbox_diagonal()
    rng = np.random.default_rng(4)
    # Ground-truth mesh -> SfM similarity (COLMAP's arbitrary gauge): scale 0.37, a random rotation, an offset.
    sg, rg, tg = 0.37, _rotation(7), np.array([2.0, -1.0, 0.5])
    to_sfm = lambda x: sg * x @ rg.T + tg  # noqa: E731
    pts = to_sfm(sample_mesh(mesh, 3000, seed=1) + rng.normal(0, 0.002 * diag, (3000, 3)))
    lo, hi = pts.min(0), pts.max(0)
    pts = np.vstack([pts, rng.uniform(lo, hi, (150, 3))])  # 5% SfM outliers
    centres = 3.0 * np.stack([np.cos(np.arange(12) * 0.5), np.sin(np.arange(12) * 0.5), np.full(12, 0.4)], 1)
    s, r, t, info = mesh_frame_transform(mesh, pts)
    back = s * to_sfm(centres) @ r.T + t
    v_back = s * to_sfm(mesh.vertices) @ r.T + t
    # Measured: vertices 0.2% of the diagonal, cameras 0.8% of the ring diameter, rotation 0.3 deg (the
    # trimmed ICP stops within a few tenths of a degree). Bounds: 1% of the diagonal for the surface,
    # the done-when's 2% of the ring diameter (6 units) for camera centres, 1 degree for the rotation.
    assert np.abs(v_back - mesh.vertices).max() < 0.01 * diag
    assert np.linalg.norm(back - centres, axis=1).max() < 0.02 * 6.0
    assert s * sg == pytest.approx(1.0, rel=0.005)  # scale from 3,000 points: 0.5%
    assert np.degrees(np.arccos(np.clip((np.trace(r @ rg) - 1) / 2, -1, 1))) < 1.0
    assert info["rms_fraction"] < 0.01  # measured 0.4%: the 0.2% noise plus the sampling of the mesh


def test_align_to_mesh_rejects_the_wrong_mesh():
    from texstream.geometry.mesh_frame import align_to_mesh
    from texstream.core.errors import StageError

    class _Pt:
        def __init__(self, xyz):
            self.xyz = xyz

    class _Rec:  # the two members align_to_mesh touches on a pycolmap.Reconstruction
        points3D = {i: _Pt(p) for i, p in enumerate(np.random.default_rng(0).uniform(-1, 1, (500, 3)) * [3, 3, 0.01])}

        def transform(self, sim):
            raise AssertionError("a rejected alignment must not move the model")

    with pytest.raises(StageError, match="do not fit the mesh") as e:
        # A flat sheet of points is not the potato: RMS 1.9% of the extent against 0.4% for a true fit.
        align_to_mesh(_Rec(), _lumpy_mesh(), 0.01)
    assert "\n" not in str(e.value)


def test_register_cli_aligns_the_capture_to_the_mesh_frame(sphere_capture, tmp_path, capsys):
    """``texstream register --align-mesh``: the synthetic sphere's own mesh fixes scale and centre (its
    rotational symmetry leaves the orientation free, so the check is what a sphere determines)."""
    import pycolmap

    from texstream.pipelines.cli import main

    cap, k_file = sphere_capture
    out = tmp_path / "posed"
    rc = main(["register", str(cap), "-o", str(out), "--intrinsics", str(k_file), "--align-mesh",
               str(cap / "ground_truth" / "mesh.obj"), "--num-threads", "2", "--max-num-features", "2000",
               "--photometric", "off"])
    assert rc == 0
    assert "aligned to the mesh frame" in capsys.readouterr().out
    got = read_capture(out)
    dist = np.array([np.linalg.norm(f.center) for f in got.frames])
    # Cameras were 3.2 units from the sphere's centre; 2% is the done-when's centre tolerance.
    assert np.abs(dist / 3.2 - 1).max() < 0.02, dist
    fwd = np.stack([f.R[2] for f in got.frames])  # optical axis in world (third row of world-to-camera R)
    to_centre = -np.stack([f.center for f in got.frames]) / dist[:, None]
    ang = np.degrees(np.arccos(np.clip((fwd * to_centre).sum(1), -1, 1)))
    assert ang.max() < 2.0, ang  # every camera looked at the sphere's centre: 2 degrees as for rotations
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    radii = np.linalg.norm(np.array([p.xyz for p in rec.points3D.values()]), axis=1)
    # Points on the unit sphere (a 96x48 polygon: chords sag by 0.05%); 2% allows SfM noise at 256 px.
    assert np.median(np.abs(radii - 1)) < 0.02
    assert json.loads((out / "capture.json").read_text())["registration"]["aligned_to"] == "mesh"


def test_register_alignment_bad_options(sphere_capture, tmp_path, capsys):
    from texstream.pipelines.cli import main

    cap, _ = sphere_capture
    rc = main(["register", str(cap), "-o", str(tmp_path / "o"), "--align-mesh", str(tmp_path / "nope.obj")])
    err = capsys.readouterr().err
    assert rc == 1 and "mesh file not found" in err and "nope.obj" in err and err.count("\n") == 1
    rc = main(["register", str(cap), "-o", str(tmp_path / "o"), "--align-mesh", str(cap / "ground_truth" / "mesh.obj"),
               "--align-to", str(cap / "capture.json")])
    err = capsys.readouterr().err
    assert rc == 1 and "not both" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------ intrinsics truthfulness


def test_principal_point_refinement_and_intrinsics_source(sphere_capture, tmp_path):
    """Photos cropped off centre (true principal point 10 px right of and 10 px below the image centre, as a
    real lens' is off by some pixels): with no intrinsics given, refinement recovers the principal point
    and removes the rotation bias that a principal point held at the centre leaves; capture.json says the
    intrinsics came from SfM."""
    from texstream.capture.capture_json import Frame, Capture, write_capture
    from texstream.capture.imageio import read_image, write_image

    cap, _ = sphere_capture
    truth = read_capture(cap)
    src = tmp_path / "photos"
    frames = []
    for f in truth.frames:
        img = read_image(truth.image_path(f), channels=3)
        write_image(src / f"{f.name}.png", img[:236, :236], bits=8)  # centre 118; true cx = cy = 128
        frames.append(Frame(file_path=f"{f.name}.png", R=f.R, t=f.t, intrinsics=f.intrinsics))
    write_capture(Capture(root=tmp_path, frames=frames), tmp_path / "truth")
    rot = {}
    for mode in ("off", "on"):
        cfg = RegisterConfig(max_num_features=2000, num_threads=2, photometric="off", camera_model="SIMPLE_PINHOLE",
                             refine_principal_point=mode, align_to=str(tmp_path / "truth" / "capture.json"))
        res = register(src, tmp_path / mode, cfg)
        got = read_capture(tmp_path / mode)
        assert got.extra["intrinsics_source"] == "sfm" and got.extra["intrinsics_prior"] == "guess"
        _, r = pose_errors(got, read_capture(tmp_path / "truth"))
        rot[mode] = float(np.median(r))
        pp = res.summary["principal_point"]
        i = got.frames[0].intrinsics
        if mode == "on":
            assert pp["refined"] and "principal_point" in got.extra["intrinsics_refined"]
            # Measured (127.95, 125.0): cy is the weaker axis here (two rings 30 degrees apart in elevation,
            # a sphere: a tilt about the camera's x axis nearly trades for a cy shift).
            assert abs(i.cx - 128) < 2.0 and abs(i.cy - 128) < 4.0, (i.cx, i.cy)
        else:
            assert not pp["refined"] and (i.cx, i.cy) == (118, 118)
    print(f"median rotation error: pp fixed at the centre {rot['off']:.3f} deg, refined {rot['on']:.3f} deg")
    assert rot["on"] < 0.5 * rot["off"], rot


def test_flash_intensity_does_not_depend_on_the_sfm_scale(sphere_capture, tmp_path):
    """An unaligned reconstruction has an arbitrary scale, and a point light's irradiance falls as 1/r^2
    in it: the flash intensity given is taken as the irradiance at the median camera-to-object distance,
    so the albedos a fit finds do not depend on the scale SfM picked."""
    cap, k_file = sphere_capture
    cfg = RegisterConfig(max_num_features=2000, intrinsics=str(k_file), num_threads=2, photometric="off",
                         colocated_light=2.0)
    res = register(cap, tmp_path / "posed", cfg)
    got = read_capture(tmp_path / "posed")
    rep = res.summary.get("colocated_light") or json.loads((tmp_path / "posed" / "registration_report.json")
                                                           .read_text())["colocated_light"]
    d = rep["median_object_distance"]
    centres = np.array([f.center for f in got.frames])
    assert d == pytest.approx(np.median(np.linalg.norm(centres - np.median(centres, axis=0), axis=1)), rel=0.2)
    for f in got.frames:
        assert f.light is not None and np.allclose(f.light.intensity, 2.0 * d * d)
        # irradiance at the object: the intensity over the distance squared is what was asked for
        assert np.allclose(np.asarray(f.light.intensity) / d**2, 2.0)


# ------------------------------------------------------------------------------ self-calibration model choice


def test_self_calibration_keeps_a_pinhole_when_distortion_does_not_help(sphere_capture, tmp_path):
    """No intrinsics given (the EXIF focal length as the prior, SIMPLE_RADIAL): the renderer's perfect pinhole
    comes out pinhole with the right focal length. Keeping the estimated distortion made it k = -0.12 and the focal
    length 8% long, at a 0.02% lower mean reprojection error: on an object in the middle of the frame the
    tracks do not tell a radial term from the focal length and the poses."""
    from texstream.calib.ingest import ingest
    from texstream.capture.synthetic.photos_only import write_photos_only

    cap, _ = sphere_capture
    truth = read_capture(cap)
    # as `texstream run PHOTOS` does: ingest (the EXIF focal length as the prior, masks), then register
    src = write_photos_only(cap, tmp_path / "photos")[0].parent
    ingested = read_capture(ingest(src, tmp_path / "capture").output)
    assert ingested.extra["intrinsics_source"] == "exif"
    cfg = RegisterConfig(max_num_features=2000, num_threads=2, photometric="off", align_to=str(cap / "capture.json"))
    res = register(tmp_path / "capture", tmp_path / "posed", cfg)
    got = read_capture(tmp_path / "posed")
    d = res.summary["distortion"]
    fx, fx_true = got.frames[0].intrinsics.fx, truth.frames[0].intrinsics.fx
    _, rot = pose_errors(got, truth)
    print(f"kept {d['kept']} (gain {100 * d['gain']:.3f}%, k {d['distortion']}), focal {fx / fx_true - 1:+.4f}, "
          f"rotation median {np.median(rot):.3f} deg")
    assert d["kept"] == "pinhole" and "distortion" not in got.extra["intrinsics_refined"]
    assert d["gain"] < 0.01  # measured -0.002%: the distortion term explains nothing
    assert got.frames[0].intrinsics.camera_model in ("PINHOLE", "SIMPLE_PINHOLE")
    assert not got.frames[0].intrinsics.distortion
    # the EXIF focal length (the focal plane's tags: the true one) is held: refining it lowers the error by
    # less than 1% (measured -0.02%, at 309.4 px against the true 309.0)
    hold = res.summary["focal_hold"]
    assert hold["held"] and hold["gain"] < 0.01 and "focal_length" not in got.extra["intrinsics_refined"]
    # 0.01%: the focal plane's tags hold the focal length to 4 significant digits (the 35 mm tag, 43 mm, only
    # checks them); refined it was +0.06% here, and 8% off with the kept distortion, which put the SfM mesh 3% of
    # the sphere's diameter off (benchmarks/photos_only_diagnose.py)
    assert abs(fx / fx_true - 1) < 1e-4, (fx, fx_true)
    assert np.median(rot) < 0.5  # measured 0.19 deg


def test_a_wrong_exif_focal_length_is_refined_not_held(sphere_capture, tmp_path):
    """An EXIF focal length 6% long (a stale tag no cross-check caught) costs more than 1% of the reprojection
    error when held (measured 8%): the photos free it, and bundle adjustment brings it back to the true one."""
    from texstream.calib.ingest import ingest
    from texstream.capture.synthetic.photos_only import write_photos_only

    cap, _ = sphere_capture
    fx_true = read_capture(cap).frames[0].intrinsics.fx
    src = write_photos_only(cap, tmp_path / "photos")[0].parent
    ingest(src, tmp_path / "capture")
    data = json.loads((tmp_path / "capture" / "capture.json").read_text())
    data["fl_x"], data["fl_y"] = 1.06 * data["fl_x"], 1.06 * data["fl_y"]
    (tmp_path / "capture" / "capture.json").write_text(json.dumps(data))
    res = register(tmp_path / "capture", tmp_path / "posed",
                   RegisterConfig(max_num_features=2000, num_threads=2, photometric="off"))
    got = read_capture(tmp_path / "posed")
    hold, fx = res.summary["focal_hold"], got.frames[0].intrinsics.fx
    print(f"prior 6% long: {hold['reason']}; focal {fx / fx_true - 1:+.4f}")
    assert not hold["held"] and hold["gain"] >= 0.01 and "focal_length" in got.extra["intrinsics_refined"]
    # measured +0.12% and +0.27% (COLMAP on two threads); 1%: a sixth of the prior's error
    assert abs(fx / fx_true - 1) < 0.01, (fx, fx_true)


# ------------------------------------------------------------------------------ SIFT on downscaled photos


def test_feature_size_rule_halves_large_photos_and_keeps_small_ones():
    from texstream.calib.register import FEATURE_SIDE, feature_image_size

    assert feature_image_size(3072, 2048, 0)[0] == FEATURE_SIDE  # 6 MP: halved would be 1536, below the floor
    assert feature_image_size(6000, 4000, 0)[0] == 3000  # 24 MP: halved
    size, line = feature_image_size(1200, 800, 0)
    assert size == 1200 and line.startswith("SIFT on the photos as they are, 1200x800")  # small photos as they are
    size, line = feature_image_size(3072, 2048, 1000)
    assert size == 1000 and "1000x667 of 3072x2048" in line and "max-image-size 1000" in line


def test_sift_on_downscaled_photos_keeps_the_cameras(sphere_capture, tmp_path):
    """COLMAP finds the features on the downscaled photos and scales the keypoints back: the cameras come out in
    the full-resolution photos' pixels, about as close to the truth as from full-size features."""
    cap, k_file = sphere_capture
    # one thread: COLMAP's mapping on several threads is not deterministic, and under CI's load the worst frame of
    # a two-thread run once came out at 2.1 degrees (the mapping now runs on one thread whatever num_threads says:
    # mapping_threads, test_mapping_and_bundle_adjustment_run_on_one_thread_whatever_the_matching_threads)
    cfg = RegisterConfig(max_num_features=2000, intrinsics=str(k_file), align_to=str(cap / "capture.json"),
                         num_threads=1, photometric="off", max_image_size=192)
    s = register(cap, tmp_path / "posed", cfg).summary
    assert "SIFT on 192x192 of 256x256" in s["resolution"], s["resolution"]
    assert len(s["registered"]) == 24 and not s["unregistered"], s
    got, truth = read_capture(tmp_path / "posed"), read_capture(cap)
    assert (got.frames[0].intrinsics.width, got.frames[0].intrinsics.height) == (256, 256)  # full-size cameras
    cen, rot = pose_errors(got, truth)
    # The full-size test above holds 2% / 2 degrees at its worst frame and 0.5 degrees median; keypoints found at
    # 3/4 size are a third more uncertain in full-size pixels: the same bounds with the median at 1 degree. (At half
    # size, 128 px, too few features survive on these small photos: 9 of 24 registered; the auto rule never goes
    # below 1600 px.) A keypoint left unscaled would sit up to 64 px off: the reprojection error would not be < 1.
    assert cen.max() < 0.02 and rot.max() < 2.0, (cen, rot)
    assert np.median(rot) < 1.0
    assert s["mean_reprojection_error"] < 1.0  # full-size test: < 0.5 px (8-bit quantisation only); 4/3 of it here


def test_mapping_and_bundle_adjustment_run_on_one_thread_whatever_the_matching_threads(sphere_capture, tmp_path,
                                                                                        monkeypatch):
    """``mapping_threads`` (1) reaches COLMAP's mapping and every bundle adjustment, ``num_threads`` only the
    matching: COLMAP's mapping on several threads starts from whichever initial pair one of them finds first, so
    its cameras depend on the machine's core count (the temple test in test_calib_register.py shows the draws);
    the matches are the same at any count. Intrinsics estimated, so self-calibration's adjustments run too."""
    import pycolmap

    cap, _ = sphere_capture
    threads: dict[str, list[int]] = {}

    def spy(name: str, options_of) -> None:
        call = getattr(pycolmap, name)

        def recorded(*args, **kwargs):
            threads.setdefault(name, []).append(options_of(args, kwargs).num_threads)
            return call(*args, **kwargs)
        monkeypatch.setattr(pycolmap, name, recorded)

    spy("match_exhaustive", lambda a, k: k["matching_options"])
    spy("incremental_mapping", lambda a, k: k["options"])
    spy("bundle_adjustment", lambda a, k: a[1].ceres.solver_options)
    s = register(cap, tmp_path / "posed", RegisterConfig(max_num_features=2000, num_threads=3, photometric="off",
                                                         max_image_size=192)).summary
    assert len(s["registered"]) >= 12, s  # a model, so the self-calibration's bundle adjustments ran
    assert threads["match_exhaustive"] == [3]
    assert set(threads["incremental_mapping"]) == {1} and set(threads["bundle_adjustment"]) == {1}, threads
