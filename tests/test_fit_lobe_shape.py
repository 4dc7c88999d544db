"""The lobe-shape choice (fit/models.py "Lobe shape", fit/fitter.py ``choose_lobe_shape``).

A light riding beside the camera shows every highlight at one half-angle, where the lobe's height
rho_s (sin^2 + c_z cos^2)^n is all the photos fix: "auto" must hold c_z at 1 there and fit it when
the light moves independently of the camera. Pure numpy: the cameras and lights are built here.
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.fit.optim.fitter import FitConfig, choose_lobe_shape, light_view_angles
from texstream.render.layout import ModelLayout
from texstream.render.camera import PhotoFrame
from texstream.core.errors import ConfigError


def look_at(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t), OpenCV axes (z forward, y down)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return r, -r @ eye


def orbit_frames(light_for, n: int = 24, kind: str = "point") -> list[PhotoFrame]:
    frames = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = 5.0 * np.array([np.cos(a), np.sin(a), 0.3])
        r, t = look_at(eye, np.zeros(3))
        frames.append(PhotoFrame(r, t, 100.0, 100.0, 64.0, 64.0, 128, 128, kind, light_for(k, eye, r),
                                 np.array([10.0, 10.0, 10.0])))
    return frames


def test_a_light_beside_the_camera_holds_c_z():
    # the synthetic scenes' "camera" mode: a fixed offset in the camera frame (15 degrees off the view)
    frames = orbit_frames(lambda k, eye, r: eye + r.T @ np.array([1.2, -0.9, 0.0]))
    angles = light_view_angles(frames, np.zeros(3))
    assert np.ptp(angles) < 1e-6 and abs(angles[0] - np.degrees(np.arctan2(1.5, 5.0 * np.sqrt(1.09)))) < 1e-6
    assert choose_lobe_shape(frames, np.zeros(3), 10.0) == "phong"
    lay = FitConfig().layout(frames, np.zeros(3))
    assert lay.lobe_shape == "phong"
    cz = lay.index("lobe0.c_z")
    assert lay.frozen()[cz] and lay.lower()[cz] == lay.upper()[cz] == 1.0


def test_a_light_moving_around_the_object_fits_c_z():
    # the light orbits at another rate than the cameras: light-view angles from 0 to 180 degrees
    frames = orbit_frames(lambda k, eye, r: 4.0 * np.array([np.cos(-3.7 * k), np.sin(-3.7 * k), 0.5]))
    assert np.ptp(light_view_angles(frames, np.zeros(3))) > 90.0
    lay = FitConfig().layout(frames, np.zeros(3))
    assert lay.lobe_shape == "free" and not lay.frozen()[lay.index("lobe0.c_z")]


def test_directional_lights_point_the_way_light_travels():
    # a directional light from behind the camera, travelling towards the object: angle 0
    frames = orbit_frames(lambda k, eye, r: -eye / np.linalg.norm(eye), n=4, kind="directional")
    assert np.allclose(light_view_angles(frames, np.zeros(3)), 0.0, atol=1e-5)


def test_explicit_shapes_and_model_json():
    frames = orbit_frames(lambda k, eye, r: eye + r.T @ np.array([1.2, -0.9, 0.0]))
    assert FitConfig(lobe_shape="free").layout(frames, np.zeros(3)).lobe_shape == "free"
    assert FitConfig(lobe_shape="phong").layout().lobe_shape == "phong"
    with pytest.raises(ConfigError):
        FitConfig().layout()  # auto without photos to decide from
    assert FitConfig(model="diffuse").layout().lobe_shape == "free"  # no lobe, nothing to decide
    with pytest.raises(ConfigError):
        ModelLayout(lobe_shape="round")
    lay = ModelLayout(n_lobes=2, anisotropic=True, lobe_shape="phong")
    assert ModelLayout.from_json(lay.to_json()) == lay
    # model folders written before lobe_shape existed fitted c_z freely
    old = {k: v for k, v in lay.to_json().items() if k != "lobe_shape"}
    assert ModelLayout.from_json(old).lobe_shape == "free"
