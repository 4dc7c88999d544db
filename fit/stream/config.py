"""The streaming fit's numerical and streaming options (:class:`StreamConfig`) and the precision they resolve to.

Imports only warp and the spine's config fields."""

from __future__ import annotations

import dataclasses

import warp as wp

from texstream.core.config import option
from texstream.core.errors import ConfigError

PRECISIONS = {"fp16": wp.float16, "fp32": wp.float32, "fp64": wp.float64}
"""parameter storage precisions (``StreamConfig.storage``) and their Warp scalars"""

FP32_SAFE_TOLERANCE = 5e-6
"""relative error of a texel's error sum E that the automatic choice allows a plain float32 accumulation: half
of issue 20's 1e-5, a margin for sign mixes and term orders the study did not try (the float32 error grows
about linearly with the photo count there, so this is also about a factor 2 in photos)"""
FP32_SAFE_PHOTOS = 1000
"""the largest photo count per texel (3 channel terms each) at which every all-positive error sum of the
summation study (benchmarks/summation.py, benchmarks/results/summation_cpu) stayed within
:data:`FP32_SAFE_TOLERANCE` summed naively in float32, one photo after another as a CPU pass does (a GPU pass
splits the photos into groups, shorter chains: it is safer still)"""


@dataclasses.dataclass
class StreamConfig:
    """Numerical and streaming options of the evaluation passes."""

    accumulate: str = option("auto", "accumulator and compute precision of the passes: auto picks fp32 up to "
                                      f"{FP32_SAFE_PHOTOS:,} photos and fp64 above (where the summation study found "
                                      "fp32 sums of the error outside 5e-6 relative; docs/numerics.md)",
                             choices=("auto", "fp32", "fp64"))
    storage: str = option("fp32", "parameter storage precision", choices=("fp16", "fp32", "fp64"))
    image_precision: str = option("fp32", "photo storage on the device (fp16 halves the streamed bytes)",
                                  choices=("fp32", "fp16"))
    kahan: bool = option(False, "Kahan-compensated sums of objective and gradient over photos (seed Alg. 14)")
    residual_space: str = option("radiance", "fit pixel values (radiance) or divide out E cos (reflectance, the "
                                             "seed's choice)", choices=("radiance", "reflectance"))
    cos_light_min: float = option(0.1, "reject samples lit more grazingly than this cosine (the seed's 0.1)",
                                  min=0.0, max=1.0)
    cos_view_min: float = option(0.05, "reject samples seen more grazingly than this cosine", min=0.0, max=1.0)
    depth_tol: float = option(0.01, "visibility test tolerance, as a fraction of the camera distance", min=0.0)
    shadow_tol: float = option(0.01, "shadow test tolerance, as a fraction of the light distance", min=0.0)
    shadow_map_size: int = option(512, "shadow map side per photo (0: no cast-shadow rejection, no traced shadow "
                                       "rays)", min=0)
    photo_sampling: str = option("filtered", "how a texel samples a photo: filtered (the photo's bilinear filter "
                                             "applied to the model too, at each tap's surface point: highlights a "
                                             "few pixels wide stay sharp; 4 model evaluations per sample), point "
                                             "(nearest pixel) or bilinear (the seed's: the filter at the texel "
                                             "centre's projection)", choices=("filtered", "point", "bilinear"))
    model_lookup: str = option("texel", "the model a sample sees near its texel: texel (the texel's own, the "
                                        "seed's) or bilinear (the renderer's texture lookup, neighbours held "
                                        "between refreshes: exact at material edges; needs filtered sampling "
                                        "and an atlas)", choices=("texel", "bilinear"))
    tap_geometry: str = option("plane", "where filtered sampling evaluates a tap: plane (the texel's face plane "
                                        "to first order) or mesh (the tap's pixel ray traced to the mesh, with "
                                        "the renderer's normal, UV and shadow; a ray query per tap)",
                               choices=("plane", "mesh"))
    groups: int = option(0, "photo groups per pass, parallelism over photos (0: automatic)", min=0)
    photos_per_window: int = option(0, "photos on the device at once when streaming (0: all when they fit, else "
                                       "sized from the memory available); a positive value with photo_residency "
                                       "auto streams in windows", min=0)
    photo_residency: str = option("auto", "where the photos live: device (all on the device), host (all in pinned "
                                          "host memory, uploaded a window per pass), disk (decoded from the "
                                          "capture's files a window per pass, depth and shadow maps recomputed per "
                                          "window), or auto (the first that fits half the memory available and "
                                          "memory_limit_mb; printed, and recorded in model.json's photos)",
                                  choices=("auto", "device", "host", "disk"))
    memory_limit_mb: float = option(0.0, "cap on the memory the photos and their maps may take on the device "
                                         "and in host memory (0: half of what is available)", min=0.0)
    crop_photos: bool = option(True, "store each photo cropped to the object's footprint (the mesh's projected "
                                     "bounding box plus 3 px): only pixels a texel can see; results equal the "
                                     "uncropped photos' to float rounding of the projection")
    decode_threads: int = option(0, "threads (or worker processes) that decode and crop photos (0: 4 threads, at "
                                    "most the CPU count; for files under worker processes one process per CPU up "
                                    "to 16)", min=0)
    photo_decoder: str = option("auto", "what decodes photo files: threads of the fitting process, worker "
                                        "processes (no lock shared with the fit; same bytes), or auto (processes "
                                        "under the texstream command with 16 or more CPUs, else threads)",
                                choices=("auto", "threads", "processes"))
    photo_cache: str = option("auto", "decoded photos cached beside the capture (CAPTURE/.texstream-cache: the "
                                      "cropped photos in the image precision; the same values, so the same "
                                      "fit), read instead of decoding again by later passes and later fits "
                                      "of the same photos, crops and precision. auto: written when photos "
                                      "stream from disk (by the first pass), read whenever ready; on: also "
                                      "written by fits with the photos on the device (in the background, "
                                      "for repeated fits of one capture); off: never read or written",
                              choices=("auto", "on", "off"))
    tiles: int = option(0, "split the atlas's texels into this many tiles of consecutive texels, each fitted over "
                           "only the photos that see it (fit/multi/tiles.py; the untiled fit's result: texels are fitted "
                           "independently, LM's smoothness by a halo exchange; the Laplacian penalty, bilinear "
                           "model_lookup and global line search are refused); 0: one tile per device, i.e. "
                           "untiled on one device", min=0)
    devices: str = option("", "comma-separated devices that share the fit (e.g. cuda:0,cuda:1; empty: the fit's "
                              "device), as device_split says; several devices need photo_residency device")
    device_split: str = option("tiles", "how several devices share the fit: tiles (each fits tiles of texels "
                                        "over every photo that sees them, one thread per device; fit/multi/tiles.py) "
                                        "or photos (each holds a run of the photos, built on it at once, and "
                                        "streams them over every texel; the first device, the fit's, adds "
                                        "their sums each pass and steps every texel; fit/multi/photo_split.py)",
                               choices=("tiles", "photos"))
    tile_backend: str = option("threads", "where the tiles run: threads (one per device in this process) or ray "
                                          "(one Ray actor per tile; needs texstream[distributed] and the photos "
                                          "as files on storage every Ray worker reads)", choices=("threads", "ray"))
    cpu_threads: int = option(0, "worker threads of a fit on the CPU: its texels split into this many tiles, one "
                                 "thread each (Warp runs a CPU kernel on the launching thread, one core; the "
                                 "untiled fit's maps to the bit, its checkpoint and warm start kept; "
                                 "fit/multi/cpu_threads.py). 0: one per CPU core this process may use, at most 8 "
                                 "and each with 2,000 texels or more (2 on a 2-core machine), where the fit can be "
                                 "tiled (the CPU device, photos resident, no stream.tiles or devices given, no "
                                 "option coupling texels), else one; on CUDA always one; 1: one thread", min=0)
    cuda_block_dim: int = option(128, "threads per CUDA block of the accumulation kernels (128 fits three blocks "
                                      "per SM at the register cap; docs/gpu-performance.md)", min=32, max=1024)
    cuda_max_registers: int = option(-1, "registers per CUDA thread of the accumulation kernels: 0 uncapped, -1 "
                                         "168 for layouts of at most 9 parameters (docs/gpu-performance.md)",
                                     min=-1)

def resolve_accumulate(accumulate: str, photos: int) -> str:
    """The accumulate precision a pass uses: "fp32" or "fp64" as given; "auto": fp32 up to
    :data:`FP32_SAFE_PHOTOS` photos, fp64 above (every pass kind honours it, LM's too, unlike Kahan)."""
    if accumulate in ("fp32", "fp64"):
        return accumulate
    if accumulate == "auto":
        return "fp32" if photos <= FP32_SAFE_PHOTOS else "fp64"
    raise ConfigError(f"accumulate precision {accumulate!r} unknown", fix="use auto, fp32 or fp64")
