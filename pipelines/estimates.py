"""What a command will write, estimated before its work so a full disk fails at once (issue 41).

Each estimate is an upper bound by construction, not a measurement: files counted uncompressed (the
stages write zip-compressed EXR, PNG and npz, which are smaller), every candidate model of an automatic
choice counted whole, and a fixed allowance for the small files (configs, reports, traces, previews).

- **per texel** (:data:`MODEL_BYTES_PER_TEXEL`): the largest per-texel model's float32 maps (two specular
  lobes: 3 + 2 x 6 = 15 channels), its uncertainty map (3), the 8-bit seen / lobes / materials PNGs (9
  bytes) and the copy of the texel bake (:data:`BAKE_BYTES_PER_TEXEL`): 4 x 18 + 9 + 64 = 145 bytes,
  rounded up to 256 for a view-dependent model's extra terms;
- **per photo pixel** of a render beside a fit: photo, render and difference as 8-bit RGB (9 bytes);
- **a mesh**: its input file counted 4 times (an OBJ with UVs and normals of a binary PLY is about that);
- **automatic model choice** with held-out photos: :data:`AUTO_CANDIDATES` fitted folders (each kept until
  the best is chosen).

So a fit at the default ``--texture-size 256`` asks for 32 MiB free, at 1024 (``texstream run``'s default
atlas) 272 MiB, with the automatic choice's candidates 1.0 GiB.
"""

from __future__ import annotations

import json
from pathlib import Path

BAKE_BYTES_PER_TEXEL = 64
"""bake.npz uncompressed: surface point and normal (float32 x 3 each), face index, barycentrics, tangent
frame and coverage: about 60 bytes"""
MODEL_BYTES_PER_TEXEL = 256
"""see the module doc: 145 bytes for the largest per-texel model, rounded up"""
RENDER_BYTES_PER_PIXEL = 9
AUTO_CANDIDATES = 4
"""the most model folders an automatic choice writes (base, its candidates, light field mapping)"""
SMALL_FILES_BYTES = 16 << 20
"""configs, reports, traces, plots and previews"""
MESH_FILE_FACTOR = 4


def _folder_bytes(folder: Path) -> int:
    if not folder.is_dir():
        return folder.stat().st_size if folder.is_file() else 0
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def atlas_texels(geometry: str | Path | None, texture_size: int) -> int:
    """Texels of the fit's atlas: an atlas folder's ``atlas_info.json`` size, else ``texture_size`` squared
    (0, the automatic size: the largest the automatic choice gives, 4096)."""
    if geometry is not None:
        info = Path(geometry) / "atlas_info.json"
        try:
            data = json.loads(info.read_text())
            return int(data["width"]) * int(data["height"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
    side = texture_size or 4096
    return side * side


def photo_pixels(capture: str | Path) -> int:
    """The largest photo's pixels in a capture.json (0 when it cannot be read: then renders are not counted)."""
    try:
        data = json.loads((Path(capture) / "capture.json").read_text())
        sizes = [(f.get("w") or data.get("w") or 0) * (f.get("h") or data.get("h") or 0) for f in data["frames"]]
        return int(max(sizes, default=0))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return 0


def mesh_bytes(mesh: str | Path | None) -> int:
    """An upper bound of a mesh's copies: the input file (or an atlas folder's mesh) times MESH_FILE_FACTOR."""
    if mesh is None:
        return 0
    p = Path(mesh)
    if p.is_dir():
        p = next((p / n for n in ("mesh.obj", "mesh.ply") if (p / n).is_file()), p)
    return MESH_FILE_FACTOR * (p.stat().st_size if p.is_file() else 0)


def fit_bytes(capture: str | Path, geometry: str | Path | None, texture_size: int, renders: int,
              auto: bool) -> int:
    """A model folder (or, with the automatic choice, all its candidates)."""
    one = (atlas_texels(geometry, texture_size) * MODEL_BYTES_PER_TEXEL
           + renders * photo_pixels(capture) * RENDER_BYTES_PER_PIXEL + mesh_bytes(geometry))
    return (AUTO_CANDIDATES if auto else 1) * one + SMALL_FILES_BYTES


def atlas_bytes(mesh: str | Path | None, resolution: int) -> int:
    """An atlas folder: the bake at the largest atlas side, the mesh with UVs, the preview."""
    return resolution * resolution * (BAKE_BYTES_PER_TEXEL + 3) + mesh_bytes(mesh) + SMALL_FILES_BYTES


def mesh_stage_bytes(mesh: str | Path | None, faces: int) -> int:
    """The mesh folder: a binary PLY of at most ``faces`` faces (0: the input's, or a million) at 100 bytes a
    face (vertices, normals and colours included), or the given mesh's copies."""
    return max(mesh_bytes(mesh), (faces or 1_000_000) * 100) + SMALL_FILES_BYTES


def refine_bytes(capture: str | Path, atlas: str | Path) -> int:
    """A refined capture.json and a re-baked copy of the atlas folder."""
    return 2 * _folder_bytes(Path(atlas)) + 4 * _folder_bytes(Path(capture) / "capture.json") + SMALL_FILES_BYTES


def export_bytes(model: str | Path) -> int:
    """glTF binary and OBJ + PNG textures with the EXR maps beside them: three times the model folder."""
    return 3 * _folder_bytes(Path(model)) + SMALL_FILES_BYTES


def run_bytes(photos: str | Path | None, atlas_resolution: int, mesh_faces: int) -> int:
    """``texstream run``: the photos copied (ingest, its masks) and undistorted (registration) twice over,
    the mesh and atlas, an automatic fit with its candidates at the atlas size, and the export."""
    photo_bytes = _folder_bytes(Path(photos)) if photos is not None else 0
    fit = fit_bytes(photos or Path("."), None, atlas_resolution, 4, auto=True)
    return (3 * photo_bytes + mesh_stage_bytes(None, mesh_faces) + atlas_bytes(None, atlas_resolution)
            + fit + 3 * fit // AUTO_CANDIDATES)
