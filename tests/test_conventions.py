"""Camera conventions: nerfstudio <-> OpenCV round trips and a projection check."""

import numpy as np

from texstream.capture.conventions import (c2w_gl_to_w2c_cv, camera_center, look_at_w2c, look_at_w2c_batch, project,
                                           texel_center_uv, uv_to_texel, w2c_cv_to_c2w_gl)


def test_c2w_round_trip():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    t = rng.normal(size=3)
    c2w = w2c_cv_to_c2w_gl(q, t)
    r2, t2 = c2w_gl_to_w2c_cv(c2w)
    # 1e-12: pure orthogonal algebra in float64
    np.testing.assert_allclose(r2, q, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_look_at_projects_target_to_principal_point():
    r, t = look_at_w2c([3.0, -2.0, 1.5], [0.1, 0.2, 0.3])
    uv, z = project(np.array([[0.1, 0.2, 0.3]]), r, t, 500.0, 500.0, 320.0, 240.0)
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
    assert z[0] > 0
    np.testing.assert_allclose(camera_center(r, t), [3.0, -2.0, 1.5], atol=1e-12)
    # OpenGL c2w: the camera looks down its -z axis
    c2w = w2c_cv_to_c2w_gl(r, t)
    fwd = -c2w[:3, 2]
    np.testing.assert_allclose(fwd, (np.array([0.1, 0.2, 0.3]) - [3.0, -2.0, 1.5]) / np.linalg.norm(np.array([0.1, 0.2, 0.3]) - [3.0, -2.0, 1.5]), atol=1e-12)


def test_up_in_world_is_up_in_image():
    r, t = look_at_w2c([5.0, 0.0, 0.0], [0.0, 0.0, 0.0], up=[0, 0, 1])
    uv, _ = project(np.array([[0.0, 0.0, 1.0]]), r, t, 100.0, 100.0, 50.0, 50.0)
    assert uv[0, 1] < 50.0  # +z world (up) lands above the centre (smaller row)


def test_texel_uv_round_trip():
    x, y = np.meshgrid(np.arange(7), np.arange(5))
    u, v = texel_center_uv(x, y, 7, 5)
    x2, y2 = uv_to_texel(u, v, 7, 5)
    np.testing.assert_allclose(x2, x, atol=1e-12)
    np.testing.assert_allclose(y2, y, atol=1e-12)
    assert v[0, 0] > v[-1, 0]  # row 0 is the top of the texture (largest v)


def test_look_at_batch_matches_one_at_a_time():
    rng = np.random.default_rng(3)
    eyes = rng.normal(size=(40, 3)) * 4
    eyes[0] = [0.0, 0.0, 5.0]   # looking straight down the up vector: the fallback up
    eyes[1] = [0.0, 0.1, -5.0]
    target = np.array([0.1, -0.2, 0.3])
    rot, trans = look_at_w2c_batch(eyes, target)
    for k, eye in enumerate(eyes):
        r, t = look_at_w2c(eye, target)
        # the same construction row by row; reductions over axes may round differently in the last bit
        np.testing.assert_allclose(rot[k], r, atol=1e-14)
        np.testing.assert_allclose(trans[k], t, atol=1e-13)
