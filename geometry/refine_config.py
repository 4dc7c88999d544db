"""The options of the photometric refinement (``texstream refine``, the run's refine stage; geometry/refine.py)."""

from __future__ import annotations

import dataclasses
import math

from texstream.core.config import option
from texstream.core.errors import ConfigError


@dataclasses.dataclass
class RefineConfig:
    """Options of the photometric refinement of cameras and mesh (``texstream refine``)."""

    mode: str = option("auto", "when texstream run refines: auto (cameras it registered and a mesh it made, each "
                               "only then), on (cameras and mesh whatever their source), off", choices=("auto", "on", "off"))
    judge: str = option("auto", "under known lights, whether texstream run hands the refined cameras and mesh to the "
                                "fit: auto (only when the diffuse fit, with the fit's options, predicts a validation "
                                "split of the fitted photos better on them than on the registered ones: this stage's "
                                "shared texture has no lobe and no room light, so its own residual can fall while the "
                                "geometry gets worse for the fitted model; pipelines/refine_judge.py), off (the "
                                "residual alone, refinement_kept)", choices=("auto", "off"))
    cameras: bool = option(True, "refine each photo's pose (rotation and translation; intrinsics stay)")
    mesh: bool = option(True, "move the mesh's vertices along their normals (seams stay closed)")
    align_heldout: bool = option(True, "align the held-out photos' poses to the texture the fitted photos make "
                                       "(their pixels move no colour and no vertex)")
    holdout_every: int = option(8, "photos held out as the fit holds them out (every k-th; 0: none)", min=0)
    blur: str = option("2,1,0.5", "Gaussian blur (standard deviation in pixels) of the photos at each level, "
                                  "coarse to fine")
    detail: float = option(6.0, "compare the photos' detail, not their intensities: each level's blurred photo less "
                                "the photo blurred this wide (standard deviation, pixels), so that shading the "
                                "shared texture cannot explain (a lamp that moves with the camera, soft shadows, "
                                "sheen) does not pull cameras and mesh; 0: intensities", min=0.0)
    iterations: int = option(8, "iterations per level (at most: rel_tol)", min=1)
    photo_level: int = option(-1, "the pyramid level (L: 2^L x 2^L pixel boxes averaged) of the finest blur level: "
                                  "-1 automatic, the coarsest whose pixels are no larger than the atlas's texels "
                                  "(geometry/refine_levels.py); 0 the photos as they are", min=-1, max=8)
    rel_tol: float = option(1e-3, "a level stops before its iterations are done once an iteration lowered the "
                                  "fitted photos' mean objective per sample by less than this fraction of it (settled; "
                                  "refine.json's levels say how many each ran); 0: every level runs all",
                            min=0.0, max=1.0)
    pyramid: bool = option(True, "run each blur level on the pyramid level where its blur is the finest one's (blur "
                                 "2, 1, 0.5 px: 0.5 px at two, one and zero levels above the finest; a quarter of "
                                 "the pixels per level); off: every blur level on the finest level's photos")
    coarse_texels: bool = option(True, "a coarse level samples the photos at texels as many of its pixels wide as "
                                       "the finest level's (the atlas's charts baked 2^k times coarser k levels up, "
                                       "a 4^k-th of the per-texel work); off: the atlas's texels at every level")
    min_move: float = option(0.25, "the finer blur levels run only when the first (coarsest) moved a camera or the "
                                   "mesh by at least this many pixels of the finest level (else they are skipped, "
                                   "the reason in refine.json); 0: always", min=0.0)
    smoothness: float = option(0.01, "weight of the displacements' graph Laplacian relative to the mean data "
                                    "curvature per vertex", min=0.0)
    max_displacement_px: float = option(
        1.0, "largest displacement of a vertex of a mesh made by dense stereo (mesh_level >= 0), in pixels of the "
             "level it was made at, or of the finest refine level where that is coarser, at the object's median "
             "depth (the median fitted photo's): such a mesh is about that close to the surface, and larger moves "
             "fit the few photos that see a vertex rather than the surface (the temple, 10 fitted photos: the "
             "bound of 1% of the bounding-box diagonal, 6.1 px there, put vertices at the bound and held out 0.45 dB "
             "under no refinement: issue 40)", min=0.0)
    max_displacement: float = option(0.01, "largest displacement of a vertex of any other mesh (mesh_level -1: sparse "
                                           "SfM points' Poisson surface, a visual hull, a given mesh), as a fraction "
                                           "of the mesh's bounding-box diagonal: their error is not a pixel's (the "
                                           "6 MP sphere's Poisson of 16,283 SfM points moved 6.6 px and held out "
                                           "1.3 dB better than at a 1 px bound)", min=0.0)
    mesh_level: int = option(-1, "the photo pyramid level dense stereo made the mesh at (texstream run sets it from its "
                                 "mesh stage), or -1: another source (max_displacement bounds its vertices)", min=-1)
    max_rotation_step: float = option(0.25, "largest rotation of a camera per iteration (degrees)", min=0.0)
    max_translation_step: float = option(0.002, "largest translation of a camera per iteration, as a fraction of "
                                                "its distance to the object", min=0.0)
    huber: float = option(0.1, "scale of the Huber loss as a fraction of the photos' mean foreground value "
                               "(residuals beyond it, occlusions and highlights, count linearly)", min=1e-6)
    normal_smoothing: str = option("0,2,5,10,20", "shading normals of the refined mesh: rounds of 1-ring averaging "
                                                  "of its vertex normals to try (comma-separated); with known "
                                                  "lights the one whose shading best explains the fitted photos' "
                                                  "intensities is kept and written as the mesh's normals (positions "
                                                  "a stereo mesh and the refinement make are good to a fraction of "
                                                  "a pixel, their normals to a few degrees, which under a known "
                                                  "light is several percent of shading); 0 alone: the mesh's own",
                                   )
    normal_iterations: int = option(
        6, "with known lights: iterations of photometric shading normals after the levels (a 2-degree-of-"
           "freedom tilt of each welded vertex's normal, a texel's normal interpolating its face's; damped "
           "Gauss-Newton on the photos' intensities averaged over each vertex's faces, alternated with the "
           "texture's colours), from the normal_smoothing choice; written as the mesh's normals; 0: off (the "
           "smoothing choice is written)", min=0)
    intensity_iterations: int = option(
        8, "with known lights, after the shading normals: iterations of pose and displacement steps "
           "comparing the photos' intensities (not their detail) with the texture shaded by the fitted "
           "normals, each followed by one iteration of the normals (needs normal_iterations > 0)", min=0)
    intensity_blur: float = option(0.0, "Gaussian blur (standard deviation in pixels) of the photos the "
                                        "shading normals and the intensity iterations compare", min=0.0)
    normal_smoothness: float = option(0.1, "weight of the smoothness of the shading normals' correction (its "
                                           "difference between neighbouring vertices) relative to the mean "
                                           "data curvature per vertex", min=0.0)
    normal_prior: float = option(0.01, "weight of the shading normals' pull toward their start relative to "
                                       "the mean data curvature per vertex (holds vertices the photos barely "
                                       "see)", min=0.0)
    max_normal_tilt: float = option(20.0, "largest tilt of a shading normal from its start (degrees)",
                                    min=0.0, max=80.0)
    cos_view_min: float = option(0.2, "samples seen more grazingly than this cosine are left out", min=0.0, max=1.0)
    depth_tol: float = option(0.01, "visibility test tolerance, as a fraction of the camera distance", min=0.0)
    threads: int = option(0, "on the CPU, the threads the heavy kernels (depth maps, colours, objectives, blur) "
                             "split their photos or texels over (Warp runs a CPU kernel on one core; the results "
                             "are the same to the bit); 0: one per CPU core this process may use (at most 8)",
                          min=0, max=64)
    checkpoint_every_s: float = option(10.0, "seconds between saves of the levels' state to the work folder (a kill "
                                             "loses at most this much; each level's last iteration is always saved; "
                                             "0: every iteration). Saving copies the state to the host, which on a GPU "
                                             "costs more than an iteration", min=0.0)
    max_photo_mb: float = option(8192.0, "largest size of the photos (float32) this stage holds on the device; "
                                         "beyond it the stage refuses with a one-line error", min=1.0)

    def smoothing_rounds(self) -> list[int]:
        try:
            out = sorted({int(x) for x in str(self.normal_smoothing).split(",") if x.strip()})
        except ValueError:
            out = []
        if not out or out[0] < 0:
            raise ConfigError(f"refine normal_smoothing {self.normal_smoothing!r} is not a comma-separated list of "
                              "rounds", fix="write it as 0,2,5,10,20 (or 0 to keep the mesh's normals)")
        return out

    def levels(self) -> list[float]:
        try:
            out = [float(x) for x in str(self.blur).split(",") if x.strip()]
        except ValueError:
            out = []
        if not out or any(not (math.isfinite(x) and x >= 0.0) for x in out):
            raise ConfigError(f"refine blur {self.blur!r} is not a comma-separated list of pixel widths",
                              fix="write it as 2,1,0.5 (coarse to fine)")
        return out
