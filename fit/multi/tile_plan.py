"""The plan of a tiled fit (fit/multi/tiles.py, fit/multi/tiles_ray.py): the texels' tiles, each tile's photos,
halo and device slot, the tiles' shared config and start, and their results put back in the untiled order."""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError

from texstream.fit.optim.fitter import FitConfig, FitResult, trace_rows
from texstream.fit.kernels.tiles import tile_visibility_kernel, tile_visibility_radiance_kernel
from texstream.fit.stream.photo_set import MAX_LAUNCH_THREADS
from texstream.fit.stream.problem import StreamProblem
from texstream.fit.stream.texels import TexelSet


@dataclasses.dataclass
class TilePlan:
    """How a fit is split: per tile its texel range, device slot and photos.

    Attributes:
        bounds: (T, 2) int64 [begin, end) compact texel indices of each tile.
        devices: the device of each worker slot (a device may appear twice: two threads on it).
        slots: (T,) int64 worker slot of each tile (tile t on slot t mod the slot count).
        photos: per tile, the (P_t,) int64 indices of the photos that see it, ascending.
        halo: per tile, the (H_t,) int64 texels of other tiles its own texels' smoothness reads
            (ascending; empty without smoothness). A tile's problem holds its own texels, then these.
    """

    bounds: np.ndarray
    devices: list[str]
    slots: np.ndarray
    photos: list[np.ndarray]
    halo: list[np.ndarray]

    def texels(self, t: int) -> np.ndarray:
        """Tile t's texels (global indices) in its problem's order: its own range, then its halo."""
        b, e = self.bounds[t]
        return np.concatenate([np.arange(b, e, dtype=np.int64), self.halo[t]])

    def report(self, n_photos: int) -> dict:
        """A plain summary for model.json and benchmarks."""
        return {"tiles": int(len(self.bounds)), "devices": list(self.devices),
                "texels_per_tile": [int(e - b) for b, e in self.bounds],
                "photos_per_tile": [int(p.size) for p in self.photos],
                "photos_streamed_per_tile": [int(tile_photos(self, t, n_photos).size) for t in range(len(self.photos))],
                "photos": int(n_photos)}


def parse_devices(devices: str, default: str) -> list[str]:
    """The worker devices of ``StreamConfig.devices`` ("cuda:0,cuda:1"; empty: ``default``)."""
    names = [d.strip() for d in str(devices).split(",") if d.strip()]
    if not names:
        return [default]
    for d in names:
        if d != "cpu" and not d.startswith("cuda"):
            raise ConfigError(f"device {d!r} in stream.devices unknown", fix="use cpu or cuda:N, comma separated")
        try:
            wp.get_device(d)
        except Exception as e:  # warp raises RuntimeError / ValueError for a device it lacks
            raise ConfigError(f"device {d!r} in stream.devices is not available ({e})",
                              fix="list devices this machine has (warp.get_cuda_device_count())") from None
    return names


def check_tileable(cfg: FitConfig) -> None:
    """Refuse options that couple texels across tiles without a halo exchange (LM's smoothness has one),
    naming the option."""
    coupled = []
    if cfg.penalties.laplacian_weight > 0:
        coupled.append("penalties.laplacian_weight (the Laplacian over neighbouring texels)")
    if cfg.stream.model_lookup == "bilinear":
        coupled.append("stream.model_lookup bilinear (neighbours' held values)")
    if cfg.linesearch.acceptance == "global":
        coupled.append("linesearch.acceptance global (one step for all texels)")
    if coupled:
        raise ConfigError("a tiled fit needs texels that are fitted independently (or LM's smoothness, whose "
                          "halo the threads exchange), and " + "; ".join(coupled) + " couple them",
                          fix="set stream.tiles to 0 with one device, or turn those options off")


def split_texels(n: int, tiles: int) -> np.ndarray:
    """(T, 2) [begin, end) ranges of ``tiles`` near-equal runs of consecutive texels (fewer when n < tiles)."""
    tiles = max(1, min(int(tiles), max(n, 1)))
    edges = np.linspace(0, n, tiles + 1).round().astype(np.int64)
    return np.stack([edges[:-1], edges[1:]], axis=1)


def texel_range(texels: TexelSet, begin: int, end: int) -> TexelSet:
    """Texels begin..end-1 as a TexelSet of their own (:func:`texel_subset`)."""
    return texel_subset(texels, np.arange(begin, end, dtype=np.int64))


def texel_subset(texels: TexelSet, indices: np.ndarray) -> TexelSet:
    """Texels ``indices`` (in that order) as a TexelSet of their own: neighbours and padding sources map to
    their positions in ``indices``, or -1 (none) outside it."""
    idx = np.asarray(indices, np.int64)
    where = -np.ones(texels.n + 1, np.int64)  # row n: the -1 of a missing neighbour maps to -1
    where[idx] = np.arange(idx.size)

    def cut(a):
        return None if a is None else np.ascontiguousarray(a[idx])

    def local(ids):
        ids = np.asarray(ids, np.int64)
        return where[np.where(ids >= 0, ids, texels.n)]

    source = None if texels.grid_source is None else local(texels.grid_source)
    return TexelSet(cut(texels.position), cut(texels.normal), cut(texels.tangent), cut(texels.bitangent),
                    cut(texels.grid_index), local(texels.neighbors[idx]).astype(np.int32),
                    texels.width, texels.height, cut(texels.face_normal), cut(texels.normal_jacobian),
                    cut(texels.coordinate_gradients), source)


def halo_texels(texels: TexelSet, begin: int, end: int) -> np.ndarray:
    """The texels outside begin..end-1 that are grid neighbours of texels inside it (ascending)."""
    nb = np.asarray(texels.neighbors[begin:end], np.int64).reshape(-1)
    return np.unique(nb[(nb >= 0) & ((nb < begin) | (nb >= end))])


def tile_photo_visibility(problem: StreamProblem, bounds: np.ndarray) -> np.ndarray:
    """(T, photos) bool: whether photo k has a sample of any texel of tile t (one launch over photos x
    texels per window of photos; the acceptance test of the passes, fit/kernels/tiles.py)."""
    n, dev, photos = problem.n, problem.device, problem.photos
    sizes = (bounds[:, 1] - bounds[:, 0]).astype(np.int64)
    tile_of = wp.array(np.repeat(np.arange(len(bounds), dtype=np.int32), sizes), dtype=wp.int32, device=dev)
    seen = wp.zeros((len(bounds), photos.n), dtype=wp.int32, device=dev)
    kernel = tile_visibility_radiance_kernel if problem.radiance else tile_visibility_kernel
    offset = 0
    step = max(1, MAX_LAUNCH_THREADS // max(n, 1))  # a launch's size stays within Warp's 32-bit bounds
    for images, depth, shadow, infos, b, e in photos.windows():
        for k0 in range(b, e, step):
            wp.launch(kernel, dim=(min(step, e - k0), n), device=dev,
                      inputs=[problem.tex, images, depth, shadow, infos, k0, offset - b, problem.opt, tile_of],
                      outputs=[seen])
        offset += e - b
    return seen.numpy() > 0


def plan_tiles(problem: StreamProblem, cfg: FitConfig) -> TilePlan:
    """Tiles (``StreamConfig.tiles``, 0: one per device), their devices and their photos."""
    check_tileable(cfg)
    devices = parse_devices(cfg.stream.devices, problem.device)
    # streamed photos share one set of window buffers: only one thread on the fit's device may stream them
    if (len(devices) > 1 or devices[0] != problem.device) and problem.photos.residency != "device":
        raise ConfigError(f"fitting on {','.join(devices)} needs the photos resident on the device, and they are "
                          f"{problem.photos.residency} ({problem.photos.residency_reason})",
                          fix="set stream.photo_residency device (and a memory cap that holds them), or fit on "
                              "the one device")
    bounds = split_texels(problem.n, cfg.stream.tiles or len(devices))
    seen = tile_photo_visibility(problem, bounds)
    # a tile no photo sees keeps photo 0: its texels stay unseen (no sample passes the same test), as untiled
    photos = [np.flatnonzero(row) if row.any() else np.zeros(1, np.int64) for row in seen]
    smooth = cfg.penalties.smooth_weight > 0
    halo = [halo_texels(problem.texels, int(b), int(e)) if smooth else np.zeros(0, np.int64) for b, e in bounds]
    return TilePlan(bounds, devices, np.arange(len(bounds)) % len(devices), photos, halo)


ALL_PHOTOS_FRACTION = 0.75
"""a tile that sees at least this fraction of the photos streams them all: the others add only samples the
distribution step rejects (cheaply, at the projection or the depth test), and the tile then needs no copy of
its photos on the parent's device (one device-to-device copy of the arrays elsewhere) instead of a gather
through the host"""


def tile_photos(plan: TilePlan, t: int, n_photos: int) -> np.ndarray:
    """The photos tile t streams: those that see it, or all of them past :data:`ALL_PHOTOS_FRACTION`."""
    idx = plan.photos[t]
    return np.arange(n_photos) if idx.size >= ALL_PHOTOS_FRACTION * n_photos else idx


def tile_start(plan: TilePlan, t: int, guess: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tile t's starting (parameters, sample counts): its halo starts where its owners do, counted as unseen
    (never stepped, never in the trace's sums)."""
    idx = plan.texels(t)
    c = counts[idx].copy()
    c[plan.bounds[t][1] - plan.bounds[t][0]:] = 0
    return guess[idx], c


def tile_config(problem: StreamProblem, cfg: FitConfig) -> FitConfig:
    """The tiles' config: the accumulate precision resolved for all the photos (a tile sees fewer, and
    ``auto`` would pick by its own count) and the untiled problem's photo groups (automatic groups follow
    the texel count; the same groups over the same photos sum each texel in the same order)."""
    return dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, accumulate=problem.accumulate,
                                                                groups=problem.groups))


def halo_pairs(plan: TilePlan) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(owner u, receiver t, rows of u's texels, rows of t's halo) for every pair of tiles with a halo between
    them: what an exchange copies, in the tiles' problems' texel order."""
    owner = np.searchsorted(plan.bounds[:, 1], np.arange(plan.bounds[-1, 1]), side="right")
    pairs = []
    for t, halo in enumerate(plan.halo):
        own_t = int(plan.bounds[t, 1] - plan.bounds[t, 0])
        for u in np.unique(owner[halo]):
            pick = np.flatnonzero(owner[halo] == u)
            pairs.append((int(u), t, (halo[pick] - plan.bounds[u, 0]).astype(np.int32),
                          (own_t + pick).astype(np.int32)))
    return pairs


def assemble(problem: StreamProblem, cfg: FitConfig, counts: np.ndarray, parts: list, sums: np.ndarray,
             times: list, it_done: int) -> FitResult:
    """The tiles' (parameters, passes, robust scale) as one FitResult in the untiled texel order."""
    passes = max(p[1] for p in parts)
    problem.passes += passes  # the passes each photo streamed through, as an untiled fit counts them
    return FitResult(params=np.concatenate([p[0] for p in parts]), samples=counts,
                     trace=trace_rows(sums, times[:it_done + 1], cfg), layout=problem.layout, passes=problem.passes,
                     robust_loss=cfg.loss(problem.layout), robust_scale=parts[0][2])
