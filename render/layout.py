"""Appearance models: named plugins with a documented parameter table.

A model's per-texel parameters are one flat vector; the fit state is a (n_texels, n_params)
array whose columns follow the layout below. Names follow STYLE.md lesson 7
("lafortune.rho_d.r", "lafortune.lobe0.n"), so optimizers, checkpoints, logs and freezing all
use one mapping.

Lafortune (seed Eq. 2.12, ch. 8), per texel: diffuse rho_d (RGB) plus K lobes; each lobe has a
specular albedo rho_s (RGB), coefficients C and an exponent n shared by the three channels.
- isotropic (the seed's choice): lobe columns [rho_s.r, rho_s.g, rho_s.b, c_xy, c_z, n]
- anisotropic ("general"):       lobe columns [rho_s.r, rho_s.g, rho_s.b, c_x, c_y, c_z, n]
K = 0 is the diffuse-only model.

Scale gauge. Scaling every C of a lobe by k and rho_s by k^-n changes nothing, so the lobe has
one redundant degree of freedom. texstream fixes it by normalisation: c_xy (or c_x) is held at
-1 (frozen: lower bound == upper bound), which keeps the lobe forward-reflective (seed 8.1) and
makes s = -(u_x v_x + u_y v_y) + c_z u_z v_z; with c_z = 1 this is the Phong cosine between the
mirrored light and the view. c_z then controls the off-specular shape and rho_s the lobe's
height, both identifiable. Freeing c_xy requires a penalty (see fit/stream/penalties.py).

Lobe shape (``ModelLayout.lobe_shape``). c_z is identifiable only when the photos see highlights at
several incidence angles: at the mirror direction s = sin^2(theta_h) + c_z cos^2(theta_h), so photos
whose light rides beside the camera (one half-angle theta_h for every highlight) fix the lobe's
height rho_s s^n there but not rho_s and c_z apart (n = 200: a 0.4% drift of c_z scales rho_s 2.2x).
"free" fits c_z in [0, 1]; "phong" holds it at 1 (the Phong lobe about the mirror direction), which
makes rho_s that height. The fit chooses per capture (fit/optim/fitter.py ``choose_lobe_shape``).

Units: rho_d, rho_s are BRDF values (1/sr; see capture/conventions.py), C and n are unitless.

Radiance (kind "radiance"): a view-independent exitant radiance L (RGB) per texel, for photos
under one fixed, unknown lighting (capture.json frames without a ``light``). A sample predicts
``exposure * L``: no light, no cosine, no shadow test (fit/kernels/accumulate.py compiles the light-free
path per layout). It shares the diffuse model's kernels (no lobes, m_c = p_c); only the weight
W = exposure replaces exposure * E * cos(theta_i). L is in photo value / exposure units.

View-dependent radiance (kind "view_radiance"): the radiance of a texel as a biquadratic polynomial
of the local view direction v (tangent frame of the atlas: x along dp/du, z the shading normal),
a polynomial texture map over view directions (Malzbender et al. 2001, there over light directions):
    L_c(v) = L_c + sum_k a_k,c phi_k(v),  phi = (v_x, v_y, v_x^2, v_x v_y, v_y^2)
so L_c is the radiance seen along the normal. It keeps what a fixed lighting and an approximate
mesh make view-dependent (a sheen, the parallax of geometry the mesh misses) which a single radiance
per texel averages away. The a_k are pulled towards 0 by a ridge prior (``FitConfig.view_prior``):
a texel seen from few directions falls back to the view-independent L. Linear in its parameters, so
Gauss-Newton is exact; same light-free weight W = exposure as "radiance".

Ambient (``ModelLayout.ambient``, reflectance kinds whose traits allow it): a per-texel radiance A (RGB) that
the room's own light adds to the flash-lit reflectance, seen the same from every view and under every light
position. A sample predicts ``exposure * (f_r E cos(theta_i) + A)``; its columns ``<kind>.ambient.{r,g,b}``
come last, in photo value / exposure units like the radiance model's L, with a lower bound 0.

Room light (``ModelLayout.room``, the physically right alternative to the free ambient): the room's light is one
global environment L_room in order-2 SH (render/sh.py), which lights the same diffuse albedo as the flash. A
sample predicts ``exposure * (f_r E cos(theta_i) + rho_d S)`` with S_c = pi T_t . L_room,c the texel's room
irradiance factor (T_t its visibility transfer, geometry/sh_transfer.py), so the room's radiance is pi rho_d T.L.
S is not fitted per texel: its columns ``<kind>.room.{r,g,b}`` (last, where the ambient's would be) carry each
texel's S, set from the global light between the fit's rounds (fit/models/per_texel/room_light.py) and frozen in
the per-texel fit (``frozen``), which then sees a known extra diffuse irradiance.
"""

from __future__ import annotations

import dataclasses
import importlib

import numpy as np

from texstream.core.errors import ConfigError

VIEW_TERMS = ("vx", "vy", "vxx", "vxy", "vyy")  # phi_k(v) of the view-dependent radiance, in this order


@dataclasses.dataclass(frozen=True)
class LayoutTraits:
    """What a per-texel model kind's name means for its parameter table and kernels; each model plugin
    registers its kind's traits (fit/models/<kind>/__init__.py), so nothing here knows a kind by name.

    Attributes:
        lit: samples are weighted by a known light (exposure * E * cos theta_i: reflectance); False: a
            light-free radiance model (W = exposure; the kernels skip the light).
        lobes: the kind carries specular lobes (n_lobes > 0 allowed); False forces n_lobes = 0.
        view_terms: view-direction terms phi_k per channel (the first ``view_terms`` of VIEW_TERMS).
        robust_loss: the fit's robust loss under ``robust_loss auto`` (fit/optim/fitter.py).
        ambient: the kind may carry a per-texel ambient radiance beside the lit reflectance (``ModelLayout.ambient``,
            the fit's ``ambient`` option); a light-free kind never does (its radiance is all the light there is).
    """

    lit: bool = True
    lobes: bool = True
    view_terms: int = 0
    robust_loss: str = "none"
    ambient: bool = False


_KIND_TRAITS: dict[str, LayoutTraits] = {}


def register_layout_kind(kind: str, traits: LayoutTraits) -> None:
    """Declare a per-texel model kind (a model plugin does, when it is registered)."""
    _KIND_TRAITS[kind] = traits


def layout_traits(kind: str) -> LayoutTraits:
    """The traits of a per-texel kind; a ConfigError naming the known kinds otherwise.

    The model plugins live above this module, so an unknown kind first has the plugin folders imported by
    name (fit/models/registry.py ``load_plugins``, the package's one import by name) and is looked up again."""
    if kind not in _KIND_TRAITS:
        importlib.import_module("texstream.fit.models.registry").load_plugins()
    if kind not in _KIND_TRAITS:
        raise ConfigError(f"unknown per-texel model kind {kind!r}", fix=f"use one of {sorted(_KIND_TRAITS)}")
    return _KIND_TRAITS[kind]


class _KnownKinds:
    """The registered per-texel kinds, as a live collection (``"radiance" in MODEL_KINDS``)."""

    def _kinds(self) -> list[str]:
        importlib.import_module("texstream.fit.models.registry").load_plugins()
        return sorted(_KIND_TRAITS)

    def __contains__(self, kind) -> bool:
        return kind in self._kinds()

    def __iter__(self):
        return iter(self._kinds())

    def __repr__(self) -> str:
        return repr(tuple(self._kinds()))


MODEL_KINDS = _KnownKinds()
LOBE_SHAPES = ("free", "phong")
MAX_LOBES = 2  # per-texel vectors are sized to the layout (at most 3 + 2*7 = 17 parameters)


def energy_bound_numpy(params: np.ndarray, layout: "ModelLayout", albedo_max: float) -> np.ndarray:
    """Cap each lobe's rho_s,c at ``albedo_max * (n + 2) / (2 pi)``.

    A normalised Phong lobe max(s, 0)^n with s the cosine to the mirror direction reflects
    2 pi / (n + 2) of the light at normal incidence, so rho_s above (n + 2) / (2 pi) creates
    energy. With sparse photos a texel can otherwise explain one highlight sample with a
    broad, enormously bright lobe that ruins unseen views; the cap rules that out while leaving
    every physical material (rho_s <= 1 albedo) reachable. ``albedo_max`` <= 0 disables it.
    (The kernels apply the same rule in ``optim_kernels.energy_bound``.)
    """
    out = np.array(params, dtype=np.float64, copy=True)
    if albedo_max <= 0:
        return out
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        cap = albedo_max * (out[..., o + layout.lobe_stride - 1] + 2.0) / (2.0 * np.pi)
        out[..., o:o + 3] = np.minimum(out[..., o:o + 3], cap[..., None])
    return out


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """One column of the parameter table."""

    name: str
    unit: str
    lower: float
    upper: float
    default: float
    doc: str


@dataclasses.dataclass(frozen=True)
class ModelLayout:
    """Parameter layout of a per-texel reflectance model.

    Attributes:
        kind: a per-texel model kind registered with :func:`register_layout_kind` (its plugin's name; the
            kinds texstream ships are described in the module doc).
        n_lobes: number of specular lobes K (0..MAX_LOBES).
        anisotropic: general C_x, C_y, C_z instead of the isotropic C_xy, C_z.
        lobe_shape: "free" (c_z fitted) or "phong" (c_z held at 1; see the module doc).
        ambient: a per-texel ambient radiance A (RGB) in the last three columns (see the module doc); kinds whose
            traits do not allow it (``LayoutTraits.ambient``) have none.
        room: the room's light as a global SH environment: each texel's known room irradiance factor S (RGB) in the
            last three columns, frozen (module doc); exclusive with ``ambient``; same traits.
    """

    kind: str = "lafortune"
    n_lobes: int = 1
    anisotropic: bool = False
    lobe_shape: str = "free"
    ambient: bool = False
    room: bool = False

    def __post_init__(self) -> None:
        traits = layout_traits(self.kind)
        if not traits.lobes and self.n_lobes != 0:
            object.__setattr__(self, "n_lobes", 0)
        if self.ambient and not (traits.ambient and traits.lit):
            object.__setattr__(self, "ambient", False)
        if self.room and not (traits.ambient and traits.lit):
            object.__setattr__(self, "room", False)
        if self.room and self.ambient:
            raise ConfigError("a layout has either the free ambient or the room light", fix="use one of them")
        if not traits.lit:  # no lobes: nothing anisotropic, no lobe shape
            object.__setattr__(self, "anisotropic", False)
            object.__setattr__(self, "lobe_shape", "free")
        if not 0 <= self.n_lobes <= MAX_LOBES:
            raise ConfigError(f"n_lobes={self.n_lobes} out of range", fix=f"use 0..{MAX_LOBES}")
        if self.lobe_shape not in LOBE_SHAPES:
            raise ConfigError(f"unknown lobe shape {self.lobe_shape!r}", fix=f"use one of {LOBE_SHAPES}")

    @property
    def is_radiance(self) -> bool:
        """A light-free radiance model (kernels skip the light, W = exposure)."""
        return not layout_traits(self.kind).lit

    @property
    def view_terms(self) -> int:
        """Number of view-direction terms phi_k per channel (5 for "view_radiance", else 0)."""
        return layout_traits(self.kind).view_terms

    def view_offset(self, k: int) -> int:
        """First column (channel r) of view term k; channel c is at ``view_offset(k) + c``."""
        return 3 + 3 * k

    @property
    def lobe_stride(self) -> int:
        return 7 if self.anisotropic else 6

    @property
    def n_params(self) -> int:
        return 3 + self.n_lobes * self.lobe_stride + 3 * self.view_terms + 3 * int(self.ambient or self.room)

    @property
    def ambient_offset(self) -> int:
        """First column (channel r) of the ambient radiance; -1 without one."""
        return self.n_params - 3 if self.ambient else -1

    @property
    def room_offset(self) -> int:
        """First column (channel r) of the room irradiance factor S; -1 without the room light."""
        return self.n_params - 3 if self.room else -1

    @property
    def extra_term(self) -> int:
        """The kernels' switch for the last three columns: 0 none, 1 the free ambient A, 2 the room's S."""
        return 2 if self.room else int(self.ambient)

    def rendered(self, params: np.ndarray) -> tuple["ModelLayout", np.ndarray]:
        """(layout, params) the renderer draws: a room light's columns become the ambient radiance they make,
        rho_d S (the room's light lights the same albedo, module doc); any other layout as it is."""
        if not self.room:
            return self, params
        out = np.array(params, copy=True)
        o = self.room_offset
        out[..., o:o + 3] = out[..., 0:3] * out[..., o:o + 3]
        return dataclasses.replace(self, room=False, ambient=True), out

    def lobe_offset(self, j: int) -> int:
        return 3 + j * self.lobe_stride

    def specs(self) -> list[ParamSpec]:
        if self.is_radiance:
            out = [ParamSpec(f"{self.kind}.L.{c}", "photo value / exposure", 0.0, 1000.0, 0.5,
                             "exitant radiance (seen along the normal for view_radiance); a sample "
                             "predicts exposure * L") for c in "rgb"]
            for k in VIEW_TERMS[:self.view_terms]:
                out += [ParamSpec(f"{self.kind}.view.{k}.{c}", "photo value / exposure", -1000.0, 1000.0, 0.0,
                                  f"coefficient of the view term {k} (local view direction components)")
                        for c in "rgb"]
            return out
        out = [ParamSpec(f"{self.kind}.rho_d.{c}", "1/sr", 0.0, 10.0, 0.1,
                         "diffuse BRDF value (albedo / pi); seed bounds reflectance samples to [0, 10]")
               for c in "rgb"]
        for j in range(self.n_lobes):
            p = f"{self.kind}.lobe{j}"
            out += [ParamSpec(f"{p}.rho_s.{c}", "1/sr", 0.0, 1.0e5, 1.0,
                              "specular albedo; large for sharp lobes, since max(s,0)^n peaks at 1")
                    for c in "rgb"]
            if self.anisotropic:
                out += [ParamSpec(f"{p}.c_x", "", -1.0, -1.0, -1.0, "scale gauge: held at -1 (frozen)"),
                        ParamSpec(f"{p}.c_y", "", -10.0, 0.0, -1.0, "tangent-y coefficient (<= 0: forward)")]
            else:
                out += [ParamSpec(f"{p}.c_xy", "", -1.0, -1.0, -1.0, "scale gauge: held at -1 (frozen)")]
            if self.lobe_shape == "phong":
                out += [ParamSpec(f"{p}.c_z", "", 1.0, 1.0, 1.0, "held at 1 (Phong lobe): the capture does not tell c_z from rho_s")]
            else:
                out += [ParamSpec(f"{p}.c_z", "", 0.0, 1.0, 1.0, "normal coefficient in [0, 1]: keeps s <= 1, so the lobe peaks at rho_s and cannot blow up in unobserved directions")]
            out += [ParamSpec(f"{p}.n", "", 1.0, 1.0e4, 10.0, "exponent; >= 1 keeps the objective C1")]
        if self.ambient:
            out += [ParamSpec(f"{self.kind}.ambient.{c}", "photo value / exposure", 0.0, 1000.0, 0.0,
                              "ambient radiance: what the room's light adds, the same from every view and under "
                              "every light; a sample predicts exposure * (f_r E cos + A)") for c in "rgb"]
        if self.room:
            out += [ParamSpec(f"{self.kind}.room.{c}", "photo value / exposure", 0.0, 1.0e6, 0.0,
                              "room irradiance factor S = pi T.L_room (known, set from the global room light, "
                              "frozen in the per-texel fit); a sample predicts exposure * (f_r E cos + rho_d S)")
                    for c in "rgb"]
        return out

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.specs()]

    def lower(self) -> np.ndarray:
        return np.array([s.lower for s in self.specs()], dtype=np.float64)

    def upper(self) -> np.ndarray:
        return np.array([s.upper for s in self.specs()], dtype=np.float64)

    def defaults(self) -> np.ndarray:
        return np.array([s.default for s in self.specs()], dtype=np.float64)

    def frozen(self) -> np.ndarray:
        """Columns that never move in the per-texel fit (lower == upper; the room's S, set from the global light)."""
        out = self.lower() == self.upper()
        if self.room:
            out[self.room_offset:self.room_offset + 3] = True
        return out

    def index(self, name: str) -> int:
        """Column of a named parameter; the kind prefix may be omitted ("lobe0.n")."""
        names = self.names
        for i, n in enumerate(names):
            if n == name or n.split(".", 1)[1] == name:
                return i
        raise ConfigError(f"model has no parameter {name!r}", fix=f"use one of {names}")

    def pack(self, rho_d, lobes=()) -> np.ndarray:
        """Parameter vector(s) from rho_d (..., 3) and per lobe dicts {rho_s, c (2 or 3), n}."""
        rho_d = np.asarray(rho_d, dtype=np.float64)
        lead = rho_d.shape[:-1]
        out = np.zeros((*lead, self.n_params))
        out[..., 0:3] = rho_d
        for j, lobe in enumerate(lobes):
            o = self.lobe_offset(j)
            out[..., o:o + 3] = np.asarray(lobe["rho_s"], dtype=np.float64)
            c = np.asarray(lobe.get("c", (-1.0, 1.0) if not self.anisotropic else (-1.0, -1.0, 1.0)), dtype=np.float64)
            nc = 3 if self.anisotropic else 2
            out[..., o + 3:o + 3 + nc] = c
            out[..., o + 3 + nc] = np.asarray(lobe["n"], dtype=np.float64)
        return out

    def to_json(self) -> dict:
        return {"kind": self.kind, "n_lobes": self.n_lobes, "anisotropic": self.anisotropic, "lobe_shape": self.lobe_shape,
                "n_params": self.n_params, "names": self.names,
                "units": [s.unit for s in self.specs()],
                "lower": self.lower().tolist(), "upper": self.upper().tolist(),
                **({"ambient": True} if self.ambient else {}),  # absent: none (the manifests written before it)
                **({"room": True} if self.room else {})}

    @staticmethod
    def from_json(d: dict) -> "ModelLayout":
        # model folders written before lobe_shape existed fitted c_z freely; before ambient, had none
        return ModelLayout(kind=d["kind"], n_lobes=int(d["n_lobes"]), anisotropic=bool(d["anisotropic"]),
                           lobe_shape=d.get("lobe_shape", "free"), ambient=bool(d.get("ambient", False)),
                           room=bool(d.get("room", False)))
