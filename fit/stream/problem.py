"""Host side of the streaming fit: the evaluation passes over texels (fit/stream/texels.py) and photos
(fit/stream/photo_set.py), whose options are fit/stream/config.py's.

A :class:`StreamProblem` owns every device buffer the passes need, allocated once. Each pass
(:meth:`StreamProblem.evaluate` or :meth:`StreamProblem.evaluate_lm`) streams all photos through
:mod:`texstream.fit.kernels.accumulate` and leaves per-texel objective, gradient and curvature on the
device. Imports only numpy and warp (plus numpy-only spine modules).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError, InputError

from texstream.fit.kernels import accumulate
from texstream.fit.kernels import optim_kernels as K
from texstream.fit.kernels import stream
from texstream.fit.kernels.lafortune_grad import param_types
from texstream.render.layout import ModelLayout
from texstream.fit.stream.config import PRECISIONS, StreamConfig, resolve_accumulate
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.texels import TexelSet
from texstream.render.camera import PhotoFrame  # noqa: F401  (the problem's photos, imported with it by tests and benchmarks)


def no_light_error(n_unlit: int, n_total: int, kind: str) -> InputError:
    """The error for a reflectance model fitted to photos without a known light."""
    return InputError(f"{n_unlit} of {n_total} photos have no light, and the {kind} model needs a known light "
                      "per photo (capture.json frames' 'light')",
                      fix="use --model radiance (view-independent radiance under the photos' fixed lighting), "
                          "or add a point or directional 'light' to every frame of capture.json")




def _vec_types(acc: str, n_params: int):
    """(scalar, parameter vector, parameter matrix) types of the accumulate precision."""
    scalars = {"fp64": wp.float64, "fp32": wp.float32}
    if acc not in scalars:
        raise ConfigError(f"accumulate precision {acc!r} unknown", fix="use fp32 or fp64")
    return (scalars[acc], *param_types(n_params, scalars[acc]))


def _stream_of(device: str):
    """The device's current stream (None on the CPU, whose copies are synchronous)."""
    return None if device == "cpu" else wp.get_stream(device)


def exposure_mean_square(photos) -> float:
    """The photos' mean squared exposure (1 for none): the view prior's unit (:meth:`StreamProblem.set_view_prior`)."""
    exposures = np.asarray(getattr(photos, "exposures", [1.0]), np.float64)
    return float(np.mean(exposures ** 2)) if exposures.size else 1.0


class StreamProblem:
    """Per-texel objective/gradient/curvature passes over a PhotoSet (buffers allocated once)."""

    def __init__(self, texels: TexelSet, photos: PhotoSet, layout: ModelLayout,
                 config: StreamConfig | None = None, device: str = "cpu"):
        """``photos``: a :class:`PhotoSet`, or photos split over devices
        (:class:`~texstream.fit.multi.photo_split.DevicePhotos`, whose first part is on ``device``): the problem
        then streams its first part itself and the others through ``peers``."""
        self.cfg = cfg = config or StreamConfig()
        self.texels, self.photos, self.layout, self.device = texels, photos, layout, device
        parts = getattr(photos, "parts", None)
        self.own_photos = parts[0] if parts else photos
        """the photos this problem's own launches stream (the first part of split photos)"""
        if self.own_photos.device != device:
            raise ConfigError(f"the problem is on {device} and its photos on {self.own_photos.device}",
                              fix="list the fit's device first in stream.devices")
        kinds = list(getattr(photos, "light_kinds", []))
        unlit = sum(k == "none" for k in kinds)
        if unlit and not layout.is_radiance:
            raise no_light_error(unlit, len(kinds), layout.kind)
        # the light-free passes: 1 the radiance model, 2 the view-dependent one (accumulate.layout_funcs)
        self.radiance = 2 if layout.view_terms else int(layout.is_radiance)
        self.robust = accumulate.ROBUST_NONE
        self.robust_scale = 0.0
        self.view_prior = None  # the view terms' ridge prior (set_view_prior): (centre, weights), one row each
        self.material_centre = self.material_weights = None  # the shared materials' prior (set_material_prior)
        if cfg.storage not in PRECISIONS:
            raise ConfigError(f"storage precision {cfg.storage!r} unknown", fix="use fp16, fp32 or fp64")
        self.accumulate = resolve_accumulate(cfg.accumulate, photos.n)
        """the accumulate precision in use ("fp32" or "fp64"; ``cfg.accumulate`` "auto" resolved)"""
        self.scalar, self.vec, self.mat = _vec_types(self.accumulate, layout.n_params)
        self.storage_dtype = PRECISIONS[cfg.storage]
        n = texels.n
        self.n = n
        self.one = self.scalar(1.0)
        self.like = self.vec()
        self.like_m = self.mat()
        dev = device
        self.pos = wp.array(texels.position, dtype=wp.vec3, device=dev)
        self.nrm = wp.array(texels.normal, dtype=wp.vec3, device=dev)
        self.tan = wp.array(texels.tangent, dtype=wp.vec3, device=dev)
        self.bit = wp.array(texels.bitangent, dtype=wp.vec3, device=dev)
        face_nrm = texels.normal if texels.face_normal is None else texels.face_normal
        jac = np.zeros((n, 3, 3), np.float32) if texels.normal_jacobian is None else texels.normal_jacobian
        self.tex = stream.TexelFrames()
        self.tex.pos, self.tex.nrm, self.tex.tan, self.tex.bit = self.pos, self.nrm, self.tan, self.bit
        self.tex.face_nrm = wp.array(np.ascontiguousarray(face_nrm, np.float32), dtype=wp.vec3, device=dev)
        self.tex.dn_dp = wp.array(np.ascontiguousarray(jac, np.float32), dtype=wp.mat33, device=dev)
        self._init_lookup(texels, layout, cfg, dev)
        self._init_taps(self.own_photos, cfg, dev)
        self.neighbors = wp.array(texels.neighbors, dtype=wp.vec4i, device=dev)
        # the other parts of split photos: the same texels over those photos, in this precision
        peer_cfg = dataclasses.replace(cfg, accumulate=self.accumulate)
        self.peers = [StreamProblem(texels, part, layout, peer_cfg, part.device) for part in (parts or [])[1:]]
        """one problem per other part of split photos (photo_split.py): they launch into their own partial
        sums, which this problem adds to its own; empty for a PhotoSet"""
        self._mirrors = {}  # this problem's copies of the first problem's arrays, when it is a peer
        self.set_groups(cfg.groups)
        self.no_diag = wp.zeros((1, 1), dtype=self.vec, device=dev)
        self.all_active = wp.ones(n, dtype=wp.int32, device=dev)
        self.no_direction = wp.zeros((1, 1), dtype=self.storage_dtype, device=dev)
        self.opt = stream.SampleOptions()
        self.opt.cos_light_min = float(cfg.cos_light_min)
        self.opt.cos_view_min = float(cfg.cos_view_min)
        self.opt.depth_tol = float(cfg.depth_tol)
        self.opt.shadow_tol = float(cfg.shadow_tol)
        if cfg.residual_space not in ("radiance", "reflectance"):
            raise ConfigError(f"residual_space {cfg.residual_space!r} unknown", fix="use radiance or reflectance")
        self.opt.reflectance_space = 1 if cfg.residual_space == "reflectance" else 0
        modes = {"bilinear": 0, "point": 1, "filtered": 2}  # stream.SAMPLING_*
        if cfg.photo_sampling not in modes:
            raise ConfigError(f"photo_sampling {cfg.photo_sampling!r} unknown", fix="use filtered, point or bilinear")
        self.opt.sampling = modes[cfg.photo_sampling]
        self.opt.robust_scale = 0.0
        if cfg.cuda_max_registers not in (-1, 0) and not 24 <= cfg.cuda_max_registers <= 255:
            raise ConfigError(f"cuda_max_registers {cfg.cuda_max_registers} invalid",
                              fix="use -1 (automatic), 0 (no cap) or 24 to 255")
        self.max_registers = cfg.cuda_max_registers
        if self.max_registers < 0:
            self.max_registers = 168 if layout.n_params <= 9 else 0
        if cfg.cuda_block_dim < 32 or cfg.cuda_block_dim > 1024 or cfg.cuda_block_dim % 32:
            raise ConfigError(f"cuda_block_dim {cfg.cuda_block_dim} invalid", fix="use a multiple of 32 from 32 to 1024")
        self.block_dim = cfg.cuda_block_dim
        self.passes = 0

    def set_robust_loss(self, kind: str, scale: float = 1.0) -> None:
        """The data term's loss per channel residual r: "none" (r^2 / 2, least squares), "huber" or
        "cauchy" with scale ``scale`` > 0 in residual units (photo values in radiance space), applied
        in the passes as iteratively reweighted least squares (fit/kernels/accumulate.py
        ``accumulate_kernel``; each loss compiles its own passes). The fit sets it from
        ``FitConfig.robust_loss``; a new problem starts with "none"."""
        if kind not in accumulate.ROBUST_LOSSES:
            raise ConfigError(f"robust loss {kind!r} unknown", fix=f"use one of {sorted(accumulate.ROBUST_LOSSES)}")
        code = accumulate.ROBUST_LOSSES[kind]
        if code != accumulate.ROBUST_NONE and not (math.isfinite(scale) and scale > 0):
            raise ConfigError(f"robust loss scale {scale} invalid", fix="use a positive scale in residual units")
        self.robust = code
        self.robust_scale = float(scale) if code != accumulate.ROBUST_NONE else 0.0
        self.opt.robust_scale = self.robust_scale
        for peer in self.peers:
            peer.set_robust_loss(kind, scale)

    def set_view_prior(self, weight: float, mean_sq: float | None = None) -> None:
        """The view-dependent radiance's ridge prior: lam / 2 sum_k a_k^2 per texel over its view-term
        coefficients (render/layout.py), with lam = ``weight`` x the photos' mean squared exposure so that
        ``weight`` counts in samples of the radiance-space residual (a sample's residual scales with its
        exposure; ``mean_sq``: that mean when this problem's photos are part of the fit's, e.g. a tile's).
        Added to every pass's objective, gradient, d^T H d, Jacobi diagonal and J^T J (the centred prior's
        kernels with one row for every texel, centre 0). No-op for other models."""
        if not (math.isfinite(weight) and weight >= 0):
            raise ConfigError(f"view prior {weight} invalid", fix="use a weight >= 0")
        lay = self.layout
        if not lay.view_terms:
            return
        if mean_sq is None:
            mean_sq = exposure_mean_square(self.photos)
        lam = float(weight) * mean_sq
        if lam <= 0:
            self.view_prior = None
            return
        w = np.zeros((1, lay.n_params))
        w[0, lay.view_offset(0):] = lam
        self.view_prior = (self.new_vec(np.zeros((1, lay.n_params))), self.new_vec(w))

    def set_material_prior(self, centre: np.ndarray | None, weights: np.ndarray | None = None) -> None:
        """The shared materials' prior (fit/models/materials.py): 1/2 sum_k w_ik (p_ik - c_ik)^2 per texel, a
        quadratic pull of each texel's parameters towards a centre of its own (its material's lobe)
        with weights of its own (zero on the columns it leaves free), both (N, n_params), in objective
        units per squared parameter unit. Added to every pass's objective, gradient, d^T H d, Jacobi
        diagonal and J^T J, on the device. ``None`` removes it."""
        if centre is None:
            self.material_centre = self.material_weights = None
            return
        c = np.asarray(centre, np.float64)
        w = np.asarray(weights, np.float64)
        shape = (self.n, self.layout.n_params)
        if c.shape != shape or w.shape != shape:
            raise ConfigError(f"material prior centre {c.shape} and weights {w.shape} must both be {shape}")
        if not (np.isfinite(c).all() and np.isfinite(w).all() and (w >= 0).all()):
            raise ConfigError("material prior has non-finite centres or negative weights",
                              fix="report this with the command that made it")
        self.material_centre = self.new_vec(c)
        self.material_weights = self.new_vec(w)

    def _add_prior(self, params, f, g, act, direction=None, dhd=None, jtj=None, diag=None) -> None:
        want = direction is not None and dhd is not None
        priors = [(self.material_centre, self.material_weights)] if self.material_centre is not None else []
        if self.view_prior is not None:
            priors.append(self.view_prior)
        for centre, weights in priors:
            wp.launch(K.centred_prior_kernel, dim=self.n, device=self.device,
                      inputs=[params, direction if want else self.no_direction, centre, weights, act,
                              self.layout.n_params, int(want), int(diag is not None)],
                      outputs=[f, g, dhd if want else f, diag if diag is not None else g])
            if jtj is not None:
                wp.launch(K.centred_prior_diag_kernel, dim=self.n, device=self.device,
                          inputs=[weights, act, self.layout.n_params], outputs=[jtj])

    def _init_lookup(self, texels: TexelSet, layout: ModelLayout, cfg: StreamConfig, dev: str) -> None:
        """The renderer's texture lookup (``StreamConfig.model_lookup``): texel coordinates and
        their gradients, the atlas's read map and the held parameters (placeholders when off)."""
        if cfg.model_lookup not in ("texel", "bilinear"):
            raise ConfigError(f"model_lookup {cfg.model_lookup!r} unknown", fix="use texel or bilinear")
        self.lookup = cfg.model_lookup == "bilinear"
        tex, n = self.tex, texels.n
        tex.grid_width, tex.grid_height = int(texels.width), int(texels.height)
        tex.n_lobes, tex.anisotropic = int(layout.n_lobes), int(layout.anisotropic)
        if self.lookup and layout.view_terms:
            raise ConfigError("model_lookup bilinear does not blend the view-dependent radiance's view terms",
                              fix="set stream.model_lookup to texel")
        if not self.lookup:
            tex.centre_xy = wp.zeros(1, dtype=wp.vec2, device=dev)
            tex.dx_dp = tex.dy_dp = wp.zeros(1, dtype=wp.vec3, device=dev)
            tex.grid_source = wp.zeros(1, dtype=wp.int32, device=dev)
            tex.lookup_params = wp.zeros((1, layout.n_params), dtype=wp.float32, device=dev)
            return
        if cfg.photo_sampling != "filtered":
            raise ConfigError(f"model_lookup bilinear needs filtered photo sampling, not {cfg.photo_sampling!r}",
                              fix="set photo_sampling to filtered or model_lookup to texel")
        if texels.coordinate_gradients is None or texels.grid_source is None or min(texels.width, texels.height) < 2:
            raise ConfigError("model_lookup bilinear needs an atlas (texel coordinate gradients and padding "
                              "sources; single-view fits have none)", fix="set model_lookup to texel")
        ys, xs = np.divmod(np.asarray(texels.grid_index, np.int64), texels.width)
        tex.centre_xy = wp.array(np.stack([xs, ys], 1).astype(np.float32), dtype=wp.vec2, device=dev)
        grads = np.ascontiguousarray(texels.coordinate_gradients, np.float32)
        tex.dx_dp = wp.array(np.ascontiguousarray(grads[:, 0]), dtype=wp.vec3, device=dev)
        tex.dy_dp = wp.array(np.ascontiguousarray(grads[:, 1]), dtype=wp.vec3, device=dev)
        source = np.asarray(texels.grid_source, np.int64)
        tex.grid_source = wp.array(np.where(source >= 0, source, n).astype(np.int32), dtype=wp.int32, device=dev)
        held = np.tile(layout.defaults().astype(np.float32), (n + 1, 1))  # row n: the defaults
        tex.lookup_params = wp.array(held, dtype=wp.float32, device=dev)

    def _init_taps(self, photos: PhotoSet, cfg: StreamConfig, dev: str) -> None:
        """The filtered taps' geometry (``StreamConfig.tap_geometry``): the mesh they are traced to
        (placeholders for the face plane)."""
        if cfg.tap_geometry not in ("plane", "mesh"):
            raise ConfigError(f"tap_geometry {cfg.tap_geometry!r} unknown", fix="use plane or mesh")
        self.traced = cfg.tap_geometry == "mesh"
        tex = self.tex
        if not self.traced:
            tex.mesh = wp.uint64(0)
            tex.mesh_points = tex.mesh_normals = wp.zeros(1, dtype=wp.vec3, device=dev)
            tex.mesh_indices = wp.zeros(1, dtype=wp.int32, device=dev)
            tex.mesh_uvs = wp.zeros(1, dtype=wp.vec2, device=dev)
            tex.shadow_eps = 0.0
            tex.shadow_rays = 0
            return
        if cfg.photo_sampling != "filtered":
            raise ConfigError(f"tap_geometry mesh needs filtered photo sampling, not {cfg.photo_sampling!r}",
                              fix="set photo_sampling to filtered or tap_geometry to plane")
        if photos.mesh_normals is None or photos.mesh_uvs is None:
            raise ConfigError("tap_geometry mesh needs a mesh with normals and UVs (single-view fits have none)",
                              fix="set tap_geometry to plane")
        tex.mesh = photos.mesh.id
        tex.mesh_points, tex.mesh_indices = photos.mesh.points, photos.mesh.indices
        tex.mesh_normals, tex.mesh_uvs = photos.mesh_normals, photos.mesh_uvs
        tex.shadow_eps = float(photos.shadow_eps)
        tex.shadow_rays = int(cfg.shadow_map_size > 0)

    def refresh_lookup(self, params: wp.array, relaxation: float = 1.0) -> None:
        """Hold the neighbours of the renderer's lookup at ``params`` (N, n_params, storage
        precision) until the next call, or move the held values ``relaxation`` of the way there
        (``FitConfig.lookup_relaxation``); on the device, no host round trip. No-op when off."""
        if self.lookup:
            wp.launch(accumulate.hold_lookup_params_kernel, dim=(self.n, self.layout.n_params), device=self.device,
                      inputs=[params, float(relaxation)], outputs=[self.tex.lookup_params])
            # a buffer of its own on the peer: the passes' "params" buffer is rewritten every pass
            for peer, mirrored in zip(self.peers, self._to_peers(lookup_params=params)):
                peer.refresh_lookup(mirrored["lookup_params"], relaxation)

    def set_groups(self, groups: int) -> None:
        """Split each pass's photos into ``groups`` groups, one thread per (group, texel); 0 picks
        one group on the CPU and enough for ~262k GPU threads. Reallocates the per-group partials
        (with split photos, ``groups`` per device: the peers' rows follow this problem's own)."""
        n, dev = self.n, self.device
        window = self.own_photos.window
        if groups <= 0:
            groups = 1 if dev == "cpu" else max(1, min(window, math.ceil(262144 / max(n, 1))))
        self.groups = groups
        self.per_group = math.ceil(window / groups)
        self.rows = groups * (1 + len(self.peers))
        """partial-sum rows a pass reduces: this problem's groups, then each peer's"""
        self.pf = wp.zeros((self.rows, n), dtype=self.scalar, device=dev)
        self.pg = wp.zeros((self.rows, n), dtype=self.vec, device=dev)
        self.ph = wp.zeros((self.rows, n), dtype=self.scalar, device=dev)
        self.pst = wp.zeros((self.rows, n), dtype=wp.vec4d, device=dev)
        self.pm = None  # per-group J^T J (LM), allocated on first request
        self.pdiag = None  # per-group Gauss-Newton diagonals, allocated on first request
        for peer in self.peers:
            peer.set_groups(groups)

    def new_storage(self, values: np.ndarray | None = None) -> wp.array:
        """A (N, n_params) parameter array in the storage precision."""
        a = np.zeros((self.n, self.layout.n_params)) if values is None else np.asarray(values)
        return wp.array(np.ascontiguousarray(a), dtype=self.storage_dtype, device=self.device)

    def new_vec(self, values: np.ndarray | None = None) -> wp.array:
        """A (N,) array of n_params-long parameter vectors in the compute precision."""
        if values is None:
            return wp.zeros(self.n, dtype=self.vec, device=self.device)
        return wp.array(np.ascontiguousarray(values, dtype=np.float64), dtype=self.vec, device=self.device)

    def new_scalar(self, fill: float = 0.0) -> wp.array:
        a = wp.zeros(self.n, dtype=self.scalar, device=self.device)
        if fill:
            a.fill_(fill)
        return a

    def evaluate(self, params: wp.array, f: wp.array, g: wp.array, stats: wp.array, *,
                 direction: wp.array | None = None, dhd: wp.array | None = None,
                 active: wp.array | None = None, full_hessian: bool = False,
                 diag: wp.array | None = None) -> None:
        """One streaming pass: f, g (and d^T H d along ``direction`` into ``dhd``) per texel.

        ``params`` and ``direction`` are (N, n_params) arrays; texels whose ``active`` flag is 0
        are skipped (their outputs are zero). ``diag`` (an (N,) parameter-vector array, optional)
        receives the Gauss-Newton diagonal diag(J^T J) of the data term (Jacobi preconditioner).
        """
        lay = self.layout
        # arguments normalised so one pass kind maps to one cached (compiled) kernel
        kernel = accumulate.accumulate_kernel(lay.n_lobes, int(lay.anisotropic), bool(self.cfg.kahan), diag is not None,
                                          direction is not None, bool(full_hessian and direction is not None),
                                          self.max_registers, self.lookup, self.traced, self.radiance, self.robust,
                                          lay.extra_term)
        if direction is not None and direction.dtype != params.dtype:
            raise ConfigError("direction and parameters must share a dtype")
        h_out = dhd if dhd is not None else self.ph_scratch()

        def launch(pr: StreamProblem, inputs: dict, window) -> None:
            images, depth, shadow, infos, b, e = window
            if diag is not None and pr.pdiag is None:
                pr.pdiag = wp.zeros((pr.rows, pr.n), dtype=pr.vec, device=pr.device)
            dirn = inputs["direction"] if inputs["direction"] is not None else pr.no_direction
            act = inputs["active"] if inputs["active"] is not None else pr.all_active
            wp.launch(kernel, dim=(pr.groups, pr.n), device=pr.device, block_dim=pr.block_dim,
                      inputs=[pr.tex, inputs["params"], dirn, act, images, depth, shadow, infos, b, e,
                              math.ceil((e - b) / pr.groups), pr.opt, pr.like, pr.one],
                      outputs=[pr.pf, pr.pg, pr.ph, pr.pst, pr.pdiag if diag is not None else pr.no_diag])

        partials = ["pf", "pg", "ph", "pst"] + (["pdiag"] if diag is not None else [])
        first = True
        for rows in self._launch_passes(launch, partials, params=params, direction=direction, active=active):
            wp.launch(accumulate.reduce_partials_kernel, dim=self.n, device=self.device,
                      inputs=[self.pf, self.pg, self.ph, self.pst, rows, 0 if first else 1],
                      outputs=[f, g, h_out, stats])
            if diag is not None:
                wp.launch(accumulate.reduce_vec_partials_kernel, dim=self.n, device=self.device,
                          inputs=[self.pdiag, rows, 0 if first else 1], outputs=[diag])
            first = False
        act = self.all_active if active is None else active
        self._add_prior(params, f, g, act, direction, dhd, diag=diag)
        self.passes += 1

    def _launch_passes(self, launch, partials: list[str], **inputs):
        """Launch a pass's accumulation over every photo: per window of this problem's photos, yields the
        number of partial-sum rows to reduce after ``launch(problem, inputs, window)`` has filled them.
        With split photos (one window per device): every peer's launch on its device with ``inputs``
        copied there, this problem's own, then the peers' ``partials`` rows copied after its own."""
        if not self.peers:
            for window in self.own_photos.windows():
                launch(self, inputs, window)
                yield self.groups
            return
        for peer, mirrored in zip(self.peers, self._to_peers(**inputs)):
            launch(peer, mirrored, next(iter(peer.own_photos.windows())))
        launch(self, inputs, next(iter(self.own_photos.windows())))
        self._gather_from_peers(partials, self.groups * self.n)
        yield self.rows

    def _same_device(self, peer: "StreamProblem") -> bool:
        """Whether ``peer`` reads this problem's arrays where they are (its device is this one)."""
        return peer.device == self.device

    def _to_peers(self, **arrays) -> list[dict]:
        """Per peer, ``arrays`` (this device's; None passes through) as that peer reads them: the same arrays
        on the same device, else copies on its device. A copy runs on this (the source) device's stream,
        after the work that wrote the array, and this device is synchronised before the peers' launches
        read it (the tiles' halo exchange, fit/multi/tiles.py, orders its copies by host synchronisations too)."""
        out, copied = [], False
        for peer in self.peers:
            if self._same_device(peer):
                out.append(dict(arrays))
                continue
            mirrored = {}
            for name, a in arrays.items():
                if a is not None:
                    buf = peer._mirrors.get(name)
                    if buf is None or buf.shape != a.shape or buf.dtype != a.dtype:
                        buf = peer._mirrors[name] = wp.empty(a.shape, dtype=a.dtype, device=peer.device)
                        wp.synchronize_device(peer.device)  # allocated on the peer's stream: ready for another's
                    wp.copy(buf, a, stream=_stream_of(self.device))
                    copied = True
                    a = buf
                mirrored[name] = a
            out.append(mirrored)
        if copied:
            wp.synchronize_device(self.device)
        return out

    def _from_peer(self, peer: "StreamProblem", pairs, count: int, offset: int) -> None:
        """Copy ``count`` elements of each (peer's array, this problem's array) in ``pairs`` to this one's
        element ``offset``, ahead of this device's launches that read them: from another device on that
        device's stream (after its launches that wrote them), once this device's queued work is done (its
        arrays written), then that device synchronised."""
        if self._same_device(peer):
            for theirs, mine in pairs:
                wp.copy(mine, theirs, offset, 0, count)
            return
        wp.synchronize_device(self.device)
        for theirs, mine in pairs:
            wp.copy(mine, theirs, offset, 0, count, stream=_stream_of(peer.device))
        wp.synchronize_device(peer.device)

    def _gather_from_peers(self, names: list[str], count: int) -> None:
        """Each peer's first ``count`` elements of the partial arrays ``names`` after this problem's own (peer
        k's into rows k x groups on)."""
        for k, peer in enumerate(self.peers, 1):
            self._from_peer(peer, [(getattr(peer, name), getattr(self, name)) for name in names], count, k * count)

    def split_initial_guess(self, kernel, rank: int, low: wp.array, high: wp.array, count: wp.array) -> None:
        """fitter.initial_guess's pass over split photos: each device's 4 smallest samples per channel,
        largest and count, merged on this device (``low``, ``high``, ``count``: the one-pass values)."""
        parts, n = 1 + len(self.peers), self.n
        lists = wp.zeros((parts, n), dtype=wp.mat44, device=self.device)
        highs = wp.zeros((parts, n), dtype=wp.vec3, device=self.device)
        counts = wp.zeros((parts, n), dtype=wp.int32, device=self.device)
        for k, pr in enumerate([self, *self.peers]):
            images, depth, shadow, infos, b, e = next(iter(pr.own_photos.windows()))
            if pr is self:
                out = [low, highs[0], counts[0], lists[0]]
            else:
                out = [wp.zeros(n, dtype=wp.vec3, device=pr.device), wp.zeros(n, dtype=wp.vec3, device=pr.device),
                       wp.zeros(n, dtype=wp.int32, device=pr.device), wp.zeros(n, dtype=wp.mat44, device=pr.device)]
            wp.launch(kernel, dim=n, device=pr.device,
                      inputs=[pr.tex, images, depth, shadow, infos, b, e, pr.opt, rank, 1], outputs=out)
            if pr is not self:
                pr._part_guess = out  # kept until the next call: this device's copies read them after this returns
        for k, peer in enumerate(self.peers, 1):
            _, hi, cnt, sm = peer._part_guess
            self._from_peer(peer, [(sm, lists), (hi, highs), (cnt, counts)], n, k * n)
        wp.launch(stream.merge_smallest_kernel, dim=n, device=self.device,
                  inputs=[lists, highs, counts, parts, rank], outputs=[low, high, count])

    def ph_scratch(self) -> wp.array:
        if not hasattr(self, "_h_scratch"):
            self._h_scratch = self.new_scalar()
        return self._h_scratch

    def evaluate_lm(self, params: wp.array, f: wp.array, g: wp.array, jtj: wp.array, stats: wp.array, *,
                    active: wp.array | None = None) -> None:
        """One streaming pass accumulating f, J^T r and J^T J per texel (Gauss-Newton / LM)."""
        lay = self.layout
        kernel = accumulate.accumulate_lm_kernel(lay.n_lobes, int(lay.anisotropic), self.max_registers, self.lookup,
                                             self.traced, self.radiance, self.robust, lay.extra_term)

        def launch(pr: StreamProblem, inputs: dict, window) -> None:
            images, depth, shadow, infos, b, e = window
            if pr.pm is None:
                pr.pm = wp.zeros((pr.rows, pr.n), dtype=pr.mat, device=pr.device)
            act = inputs["active"] if inputs["active"] is not None else pr.all_active
            wp.launch(kernel, dim=(pr.groups, pr.n), device=pr.device, block_dim=pr.block_dim,
                      inputs=[pr.tex, inputs["params"], act, images, depth, shadow, infos, b, e,
                              math.ceil((e - b) / pr.groups), pr.opt, pr.like, pr.like_m, pr.one],
                      outputs=[pr.pf, pr.pg, pr.pm, pr.pst])

        first = True
        for rows in self._launch_passes(launch, ["pf", "pg", "pm", "pst"], params=params, active=active):
            wp.launch(accumulate.reduce_partials_kernel, dim=self.n, device=self.device,
                      inputs=[self.pf, self.pg, self.pm, self.pst, rows, 0 if first else 1],
                      outputs=[f, g, jtj, stats])
            first = False
        act = self.all_active if active is None else active
        self._add_prior(params, f, g, act, jtj=jtj)
        self.passes += 1
