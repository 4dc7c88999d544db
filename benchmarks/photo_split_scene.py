"""The scene of the photo-split profiles (benchmarks/photo_split_*_profile.py): the full ornament (1,760 photos of
430x430 rendered in memory) with its atlas baked at 4x the scene's texels, and photo sets of runs of its photos."""

from __future__ import annotations

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import PhotoFrame
from texstream.geometry.bake import bake_texels


class OrnamentAt4x:
    """``mesh``, ``frames``, ``images``, ``masks`` and ``bake`` of the ornament rendered on ``device``."""

    def __init__(self, device: str = "cuda:0"):
        sc = render_scene("ornament", SynthConfig(scale=1.0, device=device, progress=False))
        self.mesh, self.frames, self.images, self.masks = sc.mesh, sc.frames, sc.images, sc.masks
        self.bake = bake_texels(self.mesh, sc.bake.width * 2, sc.bake.height * 2, device=device)
        self.photo_frames = [PhotoFrame.from_capture_frame(f) for f in self.frames]
        self.normals = self.mesh.vertex_normals()

    def photoset(self, device: str, lo: int = 0, hi: int | None = None, **stream) -> PhotoSet:
        """Photos lo..hi-1 on ``device`` (half floats, on the device; ``stream``: other StreamConfig fields)."""
        hi = len(self.frames) if hi is None else hi
        cfg = StreamConfig(image_precision="fp16", photo_residency="device", **stream)
        return PhotoSet(self.photo_frames[lo:hi], self.images[lo:hi], self.mesh.vertices, self.mesh.faces,
                        masks=self.masks[lo:hi], config=cfg, device=device, mesh_normals=self.normals,
                        mesh_uvs=self.mesh.uvs)
