"""A small synthetic capture under one fixed, unknown light with a view-dependent surface (the LFM
export, report and run tests): the glossy sphere scene on a coarse mesh, lit by one point light that
stays put while the cameras move, its lights removed from capture.json."""

from __future__ import annotations

import dataclasses
from pathlib import Path


def fixed_light_sphere_capture(root: Path, photos: int = 48, image_size: int = 32, segments: int = 8,
                               exponent: float = 3.0, device: str = "cpu") -> Path:
    """``root/cap`` with its ground-truth atlas: ``photos`` photos of ``image_size`` pixels of a sphere of
    ``segments`` x ``segments / 2`` quads (few vertices: the LFM's view maps are per vertex) with a broad
    highlight (lobe exponent ``exponent``) from a fixed point light; capture.json has no light."""
    from texstream.capture.capture_json import read_capture, write_capture
    from texstream.capture.synthetic.synth import SynthConfig, load_scene, synthesize

    scene = load_scene("sphere")
    scene["mesh"]["params"].update(n_segments=segments, n_rings=segments // 2)
    scene["texture"].update(width=64, height=32)
    scene["materials"]["plastic"]["lobes"][0]["n"] = exponent
    scene["light"] = {"type": "point", "mode": "fixed", "position": [1.8, -1.2, 2.1], "intensity": 5.0}
    cap_dir = root / "cap"
    synthesize(scene, cap_dir, SynthConfig(scale=1.0, photos=photos, image_size=image_size, progress=False,
                                           preview=False, device=device))
    cap = read_capture(cap_dir)
    unlit = [dataclasses.replace(f, light=None) for f in cap.frames]
    write_capture(dataclasses.replace(cap, frames=unlit), cap_dir)
    return cap_dir
