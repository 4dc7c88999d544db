"""Mesh files to and from :class:`~texstream.render.mesh.SurfaceMesh`.

Reading
    * OBJ: texstream's own numpy parser. It keeps ``v``, ``vt`` and ``vn`` and unwelds each
      distinct (v, vt, vn) corner triple into its own vertex, so UV seams (and hard normal creases)
      become split vertices whose ``source_vertex`` is the OBJ ``v`` index. Polygons are fan
      triangulated; negative (relative) indices are resolved as the OBJ spec says.
    * PLY and STL: pymeshlab (imported inside). PLY per-vertex ``s, t`` / ``texture_u, texture_v``
      and per-face wedge UVs are kept (wedge UVs unweld like OBJ corners).
    * GLB / glTF 2.0: a small numpy reader (triangle primitives of the default scene, node
      transforms applied, ``POSITION``, ``NORMAL``, ``TEXCOORD_0``). glTF puts v = 0 at the top of
      the image; it is flipped to texstream's v-up convention (capture/conventions.py).

Writing (atomic: temporary file beside the target, then ``os.replace``)
    * OBJ with ``v``, ``vt``, ``vn`` and ``f v/vt/vn`` (one ``v`` per SurfaceMesh vertex, so the
      split vertices at seams are written as they are).
    * PLY (binary little endian) with x, y, z, nx, ny, nz, s, t.
    * GLB (one mesh, one primitive; v flipped back to glTF's convention).

Every bad input raises :class:`~texstream.core.errors.InputError` naming the file and the fix.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from texstream.core.errors import InputError
from texstream.core.outputs import write_atomic_with

from texstream.render.mesh import SurfaceMesh

READ_EXTENSIONS = (".obj", ".ply", ".stl", ".glb", ".gltf")
WRITE_EXTENSIONS = (".obj", ".ply", ".glb")


# ----------------------------------------------------------------------------------------------
# public API


def load_mesh(path: str | os.PathLike) -> SurfaceMesh:
    """Read a triangle mesh (OBJ, PLY, STL, GLB, glTF) into a validated :class:`SurfaceMesh`.

    Args:
        path: the mesh file.

    Returns:
        The mesh: vertices (V, 3) float64, faces (F, 3) int32, and when the file has them
        normals (V, 3), uvs (V, 2) in texstream's v-up convention, and ``source_vertex`` (V,)
        mapping split vertices back to the file's welded vertices.

    Raises:
        InputError: missing file, unsupported extension, unreadable file, no faces, non-finite
            vertices or face indices out of range.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("mesh file not found", p, "check the path")
    ext = p.suffix.lower()
    if ext not in READ_EXTENSIONS:
        raise InputError(f"unsupported mesh format {ext or '(no extension)'!r}", p,
                         f"convert it to one of {', '.join(READ_EXTENSIONS)}")
    if ext == ".obj":
        mesh = _read_obj(p)
    elif ext in (".glb", ".gltf"):
        mesh = _read_gltf(p)
    else:
        mesh = _read_meshlab(p)
    validate_mesh(mesh, p)
    return mesh


def save_mesh(path: str | os.PathLike, mesh: SurfaceMesh) -> None:
    """Write a mesh atomically as OBJ, PLY or GLB (chosen by the extension).

    Normals are written when ``mesh.normals`` is set (or, for OBJ/PLY/GLB always, the
    area-weighted vertex normals of :meth:`SurfaceMesh.vertex_normals`); UVs when ``mesh.uvs`` is set.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in WRITE_EXTENSIONS:
        raise InputError(f"cannot write mesh format {ext or '(no extension)'!r}", p,
                         f"use one of {', '.join(WRITE_EXTENSIONS)}")
    validate_mesh(mesh, p)
    writer = {".obj": _obj_bytes, ".ply": _ply_bytes, ".glb": _glb_bytes}[ext]
    _write_atomic(p, writer(mesh))


def validate_mesh(mesh: SurfaceMesh, path: str | os.PathLike | None = None) -> None:
    """Raise InputError unless the mesh has faces, finite vertices and in-range indices."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vertices must be (V, 3), got {v.shape}", path, "re-export the mesh")
    if f.size == 0:
        raise InputError("mesh has no faces (a point cloud or an empty file)", path,
                         "give a triangle mesh, or reconstruct a surface first (texstream mesh --from sfm)")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces must be (F, 3) triangles, got {f.shape}", path, "re-export the mesh")
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        raise InputError(f"{int(bad.sum())} vertices are not finite (first: vertex {int(np.argmax(bad))})",
                         path, "remove NaN/inf vertices (e.g. in MeshLab) and export again")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"face indices out of range [0, {len(v)}) (min {int(f.min())}, max {int(f.max())})",
                         path, "the file is corrupt or truncated; export it again")
    if mesh.uvs is not None:
        uv = np.asarray(mesh.uvs)
        if uv.shape != (len(v), 2) or not np.all(np.isfinite(uv)):
            raise InputError("texture coordinates are not (V, 2) finite values", path,
                             "re-export the mesh with valid UVs, or without UVs")


# ----------------------------------------------------------------------------------------------
# helpers


def _write_atomic(p: Path, data: bytes) -> None:
    write_atomic_with(p, lambda fh: fh.write(data))


def write_npz_atomic(path: str | os.PathLike, compress: bool = True, **arrays) -> None:
    """``np.savez_compressed(path, **arrays)`` (``np.savez`` without ``compress``: a scratch file written
    often, where zlib would cost more than the disk) written atomically (a temporary file, then a rename)."""
    write_atomic_with(Path(path), lambda fh: (np.savez_compressed if compress else np.savez)(fh, **arrays))


def _unweld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of (N, K) corner keys -> (unique keys (U, K), inverse (N,)), in first-use order.

    First-use order keeps vertex numbering stable and close to the file's.
    """
    uniq, first, inv = np.unique(corners, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return uniq[order], rank[inv.reshape(-1)]


def _mesh_from_corners(pos: np.ndarray, corner_v: np.ndarray, faces_n: int,
                       uvs: np.ndarray | None = None, corner_vt: np.ndarray | None = None,
                       nrm: np.ndarray | None = None, corner_vn: np.ndarray | None = None) -> SurfaceMesh:
    """Build a SurfaceMesh from per-corner indices (3F,) into position/uv/normal pools."""
    keys = [corner_v]
    if corner_vt is not None:
        keys.append(corner_vt)
    if corner_vn is not None:
        keys.append(corner_vn)
    uniq, inv = _unweld(np.stack(keys, axis=1))
    src = uniq[:, 0]
    k = 1
    out_uv = out_n = None
    if corner_vt is not None:
        out_uv = np.asarray(uvs, dtype=np.float64)[uniq[:, k]]
        k += 1
    if corner_vn is not None:
        out_n = np.asarray(nrm, dtype=np.float64)[uniq[:, k]]
        ln = np.linalg.norm(out_n, axis=1, keepdims=True)
        out_n = np.divide(out_n, ln, out=np.tile([0.0, 0.0, 1.0], (len(out_n), 1)), where=ln > 0)
    return SurfaceMesh(vertices=np.asarray(pos, dtype=np.float64)[src],
                       faces=inv.reshape(faces_n, 3).astype(np.int32),
                       normals=out_n, uvs=out_uv, source_vertex=src.astype(np.int32))


# ----------------------------------------------------------------------------------------------
# OBJ


def _read_obj(p: Path) -> SurfaceMesh:
    try:
        text = p.read_text(errors="replace")
    except OSError as e:
        raise InputError(f"cannot read mesh ({e.strerror})", p, "check the file's permissions") from None
    fast = _read_obj_plain(text)
    if fast is not None:
        pos, uv, nrm, cols = fast
        counts = np.full(len(cols) // 3, 3)
        face_base = np.zeros((len(counts), 3), np.int64)  # unused: every index is positive
        return _obj_mesh(p, pos, uv, nrm, cols, counts, face_base)
    # Records by kind; counts of v/vt/vn seen before each face resolve negative indices.
    lines = text.replace("\\\n", " ").splitlines()
    vs, vts, vns, face_tokens, face_counts, face_base = [], [], [], [], [], []
    nv = nvt = nvn = 0
    try:
        for line in lines:
            if not line or line[0] not in "vf":
                continue
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            if tag == "v":
                vs.append(parts[1:4])
                nv += 1
            elif tag == "vt":
                vts.append((parts[1:3] + ["0"])[:2])
                nvt += 1
            elif tag == "vn":
                vns.append(parts[1:4])
                nvn += 1
            elif tag == "f":
                toks = parts[1:]
                if len(toks) < 3:
                    raise InputError(f"face with {len(toks)} corners: {line.strip()!r}", p,
                                     "every face needs at least 3 vertices; repair the file")
                face_tokens.extend(toks)
                face_counts.append(len(toks))
                face_base.append((nv, nvt, nvn))
        pos = np.array(vs, dtype=np.float64).reshape(-1, 3)
        uv = np.array(vts, dtype=np.float64).reshape(-1, 2)
        nrm = np.array(vns, dtype=np.float64).reshape(-1, 3)
    except ValueError as e:
        raise InputError(f"not a valid OBJ file ({e})", p, "repair or re-export the mesh") from None
    if not face_counts:
        return SurfaceMesh(vertices=pos, faces=np.zeros((0, 3), np.int32))
    counts = np.array(face_counts)
    # Split "v/vt/vn" tokens into three integer columns (0 = absent; OBJ indices are never 0).
    split = [t.split("/") for t in face_tokens]
    cols = np.zeros((len(split), 3), dtype=np.int64)
    try:
        for j in range(3):
            cols[:, j] = [int(s[j]) if len(s) > j and s[j] else 0 for s in split]
    except ValueError as e:
        raise InputError(f"bad face index in OBJ ({e})", p, "repair or re-export the mesh") from None
    return _obj_mesh(p, pos, uv, nrm, cols, counts, face_base)


def _obj_mesh(p: Path, pos, uv, nrm, cols: np.ndarray, counts: np.ndarray, face_base) -> SurfaceMesh:
    """The mesh of an OBJ's records: ``cols`` (corners, 3) the v/vt/vn indices as written (0: absent),
    ``counts`` the corners of each face, ``face_base`` each face's counts of v/vt/vn before it."""
    base = np.repeat(np.array(face_base, dtype=np.int64), counts, axis=0)  # (corners, 3)
    has = cols != 0
    for j in range(3):
        if has[:, j].any() and not has[:, j].all():
            what = ("vertex", "texture", "normal")[j]
            raise InputError(f"some face corners have {what} indices and others do not", p,
                             "export the mesh with UVs/normals on every face, or on none")
    # 1-based -> 0-based; negative -> relative to the elements defined before this face.
    idx = np.where(cols > 0, cols - 1, base + cols)
    # Fan triangulation: corners (c0, ci, ci+1) of each polygon.
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = counts - 2
    tri_face = np.repeat(np.arange(len(counts)), n_tri)
    k = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    s0 = starts[tri_face]
    corner = np.stack([s0, s0 + k + 1, s0 + k + 2], axis=1).reshape(-1)
    c = idx[corner]
    n_faces = len(tri_face)
    limits = (len(pos), len(uv), len(nrm))
    for j, what in enumerate(("vertex", "texture coordinate", "normal")):
        if has[0, j] and (c[:, j].min() < 0 or c[:, j].max() >= limits[j]):
            raise InputError(f"face {what} indices out of range (file has {limits[j]})", p,
                             "the file is corrupt or truncated; export it again")
    if not has[0, 0]:
        raise InputError("faces have no vertex indices", p, "repair or re-export the mesh")
    return _mesh_from_corners(pos, c[:, 0], n_faces,
                              uv, c[:, 1] if has[0, 1] else None,
                              nrm, c[:, 2] if has[0, 2] else None)


_OBJ_PLAIN_TAGS = {b"v", b"vt", b"vn", b"f"}


def _read_obj_plain(text: str):
    """(positions, uvs, normals, face corner indices (3F, 3)) of an OBJ as texstream and most exporters write it,
    parsed by numpy in a few passes (the general parser splits every line in Python: 0.4-0.7 s for the temple's
    20,000 faces, read by every stage): only ``v x y z``, ``vt u v``, ``vn x y z`` and triangles ``f`` whose corners
    all have the same form (``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``) with positive indices, beside comments and
    ``o``/``g``/``s``/``usemtl``/``mtllib`` lines; None for anything else (the general parser reads it)."""
    if "\\" in text or "\t" in text:
        return None
    lines = text.splitlines()
    tag_of = [line[:2] for line in lines]
    v = [line[2:] for line, t in zip(lines, tag_of) if t == "v "]
    vt = [line[3:] for line, t in zip(lines, tag_of) if t == "vt"]
    vn = [line[3:] for line, t in zip(lines, tag_of) if t == "vn"]
    f = [line[2:] for line, t in zip(lines, tag_of) if t == "f "]
    other = len(lines) - len(v) - len(vt) - len(vn) - len(f)
    if not f or other and any(t and t[0] in "vf" for t in tag_of if t not in ("v ", "vt", "vn", "f ")):
        return None

    def numbers(rows: list[str], width: int, dtype) -> np.ndarray | None:
        values = np.array(" ".join(rows).split(), dtype=dtype) if rows else np.zeros(0, dtype)
        return values.reshape(-1, width) if values.size == width * len(rows) else None

    try:
        pos, uv, nrm = numbers(v, 3, np.float64), numbers(vt, 2, np.float64), numbers(vn, 3, np.float64)
        first = f[0].split()
        if len(first) != 3 or pos is None or uv is None or nrm is None:
            return None
        form = [bool(c) for c in first[0].split("/")] + [False] * 2  # which of v, vt, vn the corners give
        slashes = first[0].count("/")
        joined = " ".join(f)
        if joined.count("/") != 3 * slashes * len(f):
            return None
        flat = np.array(joined.replace("//", " ").replace("/", " ").split(), dtype=np.int64)
    except ValueError:
        return None
    present = [j for j in range(3) if form[j]]
    if flat.size != 3 * len(present) * len(f) or not present or present[0] != 0 or flat.min() <= 0:
        return None
    cols = np.zeros((3 * len(f), 3), np.int64)
    cols[:, present] = flat.reshape(-1, len(present))
    return pos, uv, nrm, cols


def _fmt_rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    row = prefix + " " + " ".join([fmt] * (a.shape[1] // fmt.count("%"))) + "\n"
    return (row * len(a)) % tuple(a.reshape(-1))


def _obj_bytes(mesh: SurfaceMesh) -> bytes:
    """OBJ text. With UVs and ``source_vertex`` the ``v`` records are the welded vertices and each
    split vertex is one ``vt``/``vn`` pair, so reading the file back restores the seams' welding."""
    n = np.asarray(mesh.vertex_normals(), np.float64)
    f = np.asarray(mesh.faces, np.int64)
    verts = np.asarray(mesh.vertices, np.float64)
    vidx = f
    if mesh.uvs is not None and mesh.source_vertex is not None:
        src = np.asarray(mesh.source_vertex, np.int64)
        uniq, first, inv = np.unique(src, return_index=True, return_inverse=True)
        verts = verts[first]
        vidx = inv.reshape(-1)[f]
    out = ["# texstream mesh: %d vertices, %d faces\n" % (mesh.n_vertices, mesh.n_faces),
           _fmt_rows(verts, "v", "%.9g")]
    if mesh.uvs is not None:
        out.append(_fmt_rows(np.asarray(mesh.uvs, np.float64), "vt", "%.9g"))
    out.append(_fmt_rows(n, "vn", "%.7g"))
    if mesh.uvs is not None:
        corners = np.stack([vidx + 1, f + 1, f + 1], axis=2).reshape(len(f), 9)
        out.append(_fmt_rows(corners, "f", "%d/%d/%d"))
    else:
        out.append(_fmt_rows(np.repeat(f + 1, 2, axis=1), "f", "%d//%d"))
    return "".join(out).encode()


# ----------------------------------------------------------------------------------------------
# PLY / STL (pymeshlab)


def _meshlab_reason(e: Exception) -> str:
    """pymeshlab's error text on one line: its "Error details" (e.g. "Header not found") without the lines
    around them that repeat the file name."""
    text = str(e).strip()
    details = [ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.strip().startswith("Error details:")]
    return details[0] if details and details[0] else " ".join(text.split()) or type(e).__name__


def _read_meshlab(p: Path) -> SurfaceMesh:
    import pymeshlab  # heavy; only for these formats

    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(p))
    except Exception as e:  # pymeshlab raises its own PyMeshLabException
        raise InputError(f"cannot read mesh ({_meshlab_reason(e)})", p,
                         "check that the file is a valid mesh, or re-export it") from None
    m = ms.current_mesh()
    v = np.asarray(m.vertex_matrix(), dtype=np.float64)
    f = np.asarray(m.face_matrix(), dtype=np.int64).reshape(-1, 3)
    if f.size == 0:
        return SurfaceMesh(vertices=v, faces=np.zeros((0, 3), np.int32))
    normals = None
    if p.suffix.lower() == ".ply" and _ply_has_property(p, "nx"):
        normals = np.asarray(m.vertex_normal_matrix(), dtype=np.float64)
    if m.has_wedge_tex_coord() and not m.has_vertex_tex_coord():
        wuv = np.asarray(m.wedge_tex_coord_matrix(), dtype=np.float64).reshape(-1, 2)
        return _mesh_from_corners(v, f.reshape(-1), len(f), wuv, np.arange(len(wuv)),
                                  normals, f.reshape(-1) if normals is not None else None)
    uvs = np.asarray(m.vertex_tex_coord_matrix(), dtype=np.float64) if m.has_vertex_tex_coord() else None
    return SurfaceMesh(vertices=v, faces=f.astype(np.int32), normals=normals, uvs=uvs,
                       source_vertex=_weld_positions(v))


def _ply_has_property(p: Path, name: str) -> bool:
    with open(p, "rb") as fh:
        head = fh.read(4096).split(b"end_header")[0].decode("ascii", errors="replace")
    return any(line.split()[-1:] == [name] for line in head.splitlines() if line.startswith("property"))


def _ply_bytes(mesh: SurfaceMesh) -> bytes:
    n = mesh.vertex_normals()
    has_uv = mesh.uvs is not None
    props = ["x", "y", "z", "nx", "ny", "nz"] + (["s", "t"] if has_uv else [])
    header = ["ply", "format binary_little_endian 1.0", "comment texstream mesh",
              f"element vertex {mesh.n_vertices}"]
    header += [f"property float {q}" for q in props]
    header += [f"element face {mesh.n_faces}", "property list uchar int vertex_indices", "end_header"]
    cols = [np.asarray(mesh.vertices), np.asarray(n)] + ([np.asarray(mesh.uvs)] if has_uv else [])
    vert = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    face = np.zeros(mesh.n_faces, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = mesh.faces
    return ("\n".join(header) + "\n").encode() + vert.tobytes() + face.tobytes()


# ----------------------------------------------------------------------------------------------
# glTF 2.0 (numpy)

_GLTF_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
                5126: np.float32}
_GLTF_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _read_gltf(p: Path) -> SurfaceMesh:
    fix = "re-export it as glTF 2.0 with triangle primitives, or as OBJ/PLY"
    raw = p.read_bytes()
    try:
        if p.suffix.lower() == ".glb":
            magic, version, _ = struct.unpack_from("<III", raw, 0)
            if magic != 0x46546C67 or version != 2:
                raise ValueError("not a glTF 2.0 binary (bad magic or version)")
            off, doc, bin_chunk = 12, None, b""
            while off + 8 <= len(raw):
                length, kind = struct.unpack_from("<II", raw, off)
                chunk = raw[off + 8: off + 8 + length]
                if kind == 0x4E4F534A:
                    doc = json.loads(chunk.decode())
                elif kind == 0x004E4942:
                    bin_chunk = chunk
                off += 8 + length
            if doc is None:
                raise ValueError("no JSON chunk")
        else:
            doc, bin_chunk = json.loads(raw.decode()), b""
        buffers = []
        for b in doc.get("buffers", []):
            if "uri" not in b:
                buffers.append(bin_chunk)
            elif b["uri"].startswith("data:"):
                import base64

                buffers.append(base64.b64decode(b["uri"].split(",", 1)[1]))
            else:
                buffers.append((p.parent / b["uri"]).read_bytes())

        def accessor(i: int) -> np.ndarray:
            acc = doc["accessors"][i]
            nc = _GLTF_NCOMP[acc["type"]]
            dt = np.dtype(_GLTF_DTYPES[acc["componentType"]])
            count = acc["count"]
            if "bufferView" not in acc:
                return np.zeros((count, nc), dt)
            bv = doc["bufferViews"][acc["bufferView"]]
            buf = buffers[bv["buffer"]]
            start = bv.get("byteOffset", 0) + acc.get("byteOffset", 0)
            stride = bv.get("byteStride", 0) or nc * dt.itemsize
            a = np.ndarray((count, nc), dtype=dt.newbyteorder("<"), buffer=buf, offset=start,
                           strides=(stride, dt.itemsize))
            a = np.array(a)
            if acc.get("normalized") and dt.kind in "iu":
                a = a.astype(np.float64) / np.iinfo(dt).max
            return a

        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]] = []

        def visit(node_i: int, parent: np.ndarray) -> None:
            node = doc["nodes"][node_i]
            m = parent @ _node_matrix(node)
            if "mesh" in node:
                for prim in doc["meshes"][node["mesh"]]["primitives"]:
                    if prim.get("mode", 4) != 4:
                        continue  # points / lines carry no surface
                    att = prim["attributes"]
                    pos = accessor(att["POSITION"]).astype(np.float64)
                    idx = (accessor(prim["indices"]).reshape(-1).astype(np.int64) if "indices" in prim
                           else np.arange(len(pos)))
                    nrm = accessor(att["NORMAL"]).astype(np.float64) if "NORMAL" in att else None
                    uv = accessor(att["TEXCOORD_0"]).astype(np.float64) if "TEXCOORD_0" in att else None
                    pos = pos @ m[:3, :3].T + m[:3, 3]
                    if nrm is not None:
                        nrm = nrm @ np.linalg.inv(m[:3, :3])  # inverse-transpose for normals
                    if uv is not None:
                        uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # glTF v down -> v up
                    parts.append((pos, idx.reshape(-1, 3), nrm, uv))
            for c in node.get("children", []):
                visit(c, m)

        scene = doc.get("scenes", [{"nodes": list(range(len(doc.get("nodes", []))))}])[doc.get("scene", 0)]
        for n in scene.get("nodes", []):
            visit(n, np.eye(4))
    except InputError:
        raise
    except (ValueError, KeyError, IndexError, TypeError, struct.error, OSError) as e:
        raise InputError(f"cannot read glTF ({type(e).__name__}: {e})", p, fix) from None
    if not parts:
        return SurfaceMesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int32))
    all_uv = all(q[3] is not None for q in parts)
    all_n = all(q[2] is not None for q in parts)
    offs = np.cumsum([0] + [len(q[0]) for q in parts])
    v = np.concatenate([q[0] for q in parts])
    f = np.concatenate([q[1] + o for q, o in zip(parts, offs[:-1])])
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError("glTF indices out of range", p, fix)
    nrm = np.concatenate([q[2] for q in parts]) if all_n else None
    if nrm is not None:
        ln = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.divide(nrm, ln, out=np.tile([0.0, 0.0, 1.0], (len(nrm), 1)), where=ln > 0)
    return SurfaceMesh(vertices=v, faces=f.astype(np.int32), normals=nrm,
                       uvs=np.concatenate([q[3] for q in parts]) if all_uv else None,
                       source_vertex=_weld_positions(v))


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m[:3, :3] = r * np.asarray(node.get("scale", [1.0, 1.0, 1.0]))[None, :]
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def _weld_positions(v: np.ndarray) -> np.ndarray:
    """PLY and glTF split vertices at seams without saying so: weld by exact position."""
    _, inv = _unweld(np.asarray(v, dtype=np.float64))
    return inv.astype(np.int32)


def _glb_bytes(mesh: SurfaceMesh) -> bytes:
    v = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    n = np.ascontiguousarray(mesh.vertex_normals(), dtype="<f4")
    f = np.ascontiguousarray(mesh.faces, dtype="<u4")
    blobs = [v.tobytes(), n.tobytes(), f.tobytes()]
    if mesh.uvs is not None:
        uv = np.asarray(mesh.uvs, dtype=np.float64)
        blobs.append(np.ascontiguousarray(np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1), dtype="<f4").tobytes())
    views, off = [], 0
    for b in blobs:
        views.append({"buffer": 0, "byteOffset": off, "byteLength": len(b)})
        off += (len(b) + 3) // 4 * 4
    binary = b"".join(b + b"\0" * ((4 - len(b) % 4) % 4) for b in blobs)
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
         "min": v.min(0).tolist(), "max": v.max(0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": len(v), "type": "VEC3"},
        {"bufferView": 2, "componentType": 5125, "count": int(f.size), "type": "SCALAR"},
    ]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if mesh.uvs is not None:
        accessors.append({"bufferView": 3, "componentType": 5126, "count": len(v), "type": "VEC2"})
        attributes["TEXCOORD_0"] = 3
    doc = {"asset": {"version": "2.0", "generator": "texstream"}, "scene": 0,
           "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": attributes, "indices": 2, "mode": 4}]}],
           "buffers": [{"byteLength": len(binary)}], "bufferViews": views, "accessors": accessors}
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * ((4 - len(js) % 4) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(binary), 0x004E4942) + binary)
