"""Photos split over several devices (``StreamConfig.device_split`` "photos").

Each device holds a share of the photos, a run of consecutive ones with their depth and shadow maps
(a :class:`~texstream.fit.stream.photo_set.PhotoSet` of its own on its device; the host crops every part's
photos in one pipeline, each chunk copied to its device while the next is cropped, and each device
makes its own photos' maps), and streams
it over every texel. A pass is then one launch per device into that device's per-group partial
sums; the first device copies the others' partials after its own and adds all of them in the fixed
order of :func:`~texstream.fit.kernels.accumulate.reduce_partials_kernel`, then steps every texel
itself (:class:`~texstream.fit.stream.problem.StreamProblem` ``peers``). Between devices only the
parameters (to the others, before a pass) and the partial sums (back) travel, device to device (peer
copies over NVLink where there is one). A copy runs on its source device's stream, and that device
is synchronised before the other device's work reads it.

Summation order: device d's photos are the run [d c, (d+1) c) with c = ceil(photos / devices), one
device's photo groups after another's. That is the order of one device with ``devices`` x
``groups`` photo groups (when each device has one group, as automatic groups give for large
atlases): the split fit equals that one-device fit to the last bit. Against the one-device fit with
one group it differs by rounding of the sums' association (in the accumulate precision: float32 up to
1,000 photos, float64 above, a few 1e-16 relative per sum).

The initial guess (a per-texel low percentile, not a sum) is exact too: each device keeps its 4
smallest samples per channel and the first merges them (:func:`~texstream.fit.kernels.stream.merge_smallest_kernel`).
"""

from __future__ import annotations

import concurrent.futures
import contextvars
import dataclasses

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError
from texstream.core.progress import say
from texstream.fit.stream.photo_set import PhotoSet, upload_photo_sets
from texstream.fit.stream.photo_stream import PhotoFiles


def split_bounds(n: int, parts: int) -> list[tuple[int, int]]:
    """[begin, end) runs of ``n`` photos over ``parts`` devices: runs of ceil(n / parts), the last shorter
    (fewer runs when n is small: a device without photos is left out)."""
    size = -(-n // max(1, parts))
    return [(b, min(n, b + size)) for b in range(0, n, size)]


def enable_peer_copies(devices: list[str]) -> None:
    """Let every pair of distinct CUDA devices copy each other's memory directly (NVLink or PCIe peer
    transfers instead of a copy through host memory), where the hardware allows."""
    cuda = sorted({d for d in devices if d.startswith("cuda")})
    for a in cuda:
        for b in cuda:
            if a == b:
                continue
            if wp.is_peer_access_supported(a, b) and not wp.is_peer_access_enabled(a, b):
                wp.set_peer_access_enabled(a, b, True)
            if wp.is_mempool_access_supported(a, b) and not wp.is_mempool_access_enabled(a, b):
                wp.set_mempool_access_enabled(a, b, True)


def check_split_devices(devices: list[str], fit_device: str) -> None:
    """Refuse device lists the photo split cannot serve, naming the fix."""
    if devices[0] != fit_device:
        raise ConfigError(f"stream.devices starts with {devices[0]}, not the fit's device {fit_device}",
                          fix="list the fit's device (--device) first: it adds the others' sums and steps the texels")
    if len({d == "cpu" for d in devices}) > 1:
        raise ConfigError(f"stream.devices {','.join(devices)} mixes the CPU and CUDA devices",
                          fix="split the photos over CUDA devices only (or cpu,cpu to check the path)")


class DevicePhotos:
    """A capture's photos split over devices: ``parts`` (one :class:`~texstream.fit.stream.photo_set.PhotoSet`
    per device, photos ``bounds[d]``), presented as one set where a fit reads what concerns all photos
    (count, exposures, light kinds, frames). Passes never stream it directly (:meth:`windows` refuses):
    a :class:`~texstream.fit.stream.problem.StreamProblem` over it streams each part on its device."""

    def __init__(self, parts: list, bounds: list[tuple[int, int]]):
        self.parts = list(parts)
        self.bounds = [(int(b), int(e)) for b, e in bounds]
        first = self.parts[0]
        self.devices = [p.device for p in self.parts]
        self.device = first.device
        self.n = sum(p.n for p in self.parts)
        self.frames = [f for p in self.parts for f in p.frames]
        self.exposures = [x for p in self.parts for x in p.exposures]
        self.light_kinds = [k for p in self.parts for k in p.light_kinds]
        self.residency = "device"
        self.residency_reason = "split over " + ", ".join(
            f"{p.device} (photos {b}-{e - 1})" for p, (b, e) in zip(self.parts, self.bounds))
        self.window = self.n
        self.streamed = False
        self.files = first.files
        self.source = None
        self.loader = None
        self.mesh, self.mesh_normals, self.mesh_uvs = first.mesh, first.mesh_normals, first.mesh_uvs
        self.mesh_arrays = first.mesh_arrays
        self.shadow_eps = first.shadow_eps
        self.image_bytes = sum(p.image_bytes for p in self.parts)
        self.crops = None if first.crops is None else np.concatenate([p.crops for p in self.parts])
        self.infos_host = np.concatenate([p.infos_host for p in self.parts])
        # the parts are built at once: a phase takes as long as its slowest part
        self.timings = {k: max(p.timings[k] for p in self.parts) for k in first.timings}

    def windows(self):
        raise RuntimeError("photos split over devices are streamed part by part (StreamProblem.peers)")

    def subset(self, indices, device: str | None = None) -> "DevicePhotos":
        """The photos ``indices`` (ascending), each kept on the device that holds it (a part without any
        left is dropped); ``device`` must be None or the first device."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        if device is not None and str(device) != self.device:
            raise ConfigError(f"photos split over {','.join(self.devices)} cannot be moved to {device}",
                              fix="fit on the first listed device")
        parts, bounds, at = [], [], 0
        for p, (b, e) in zip(self.parts, self.bounds):
            local = idx[(idx >= b) & (idx < e)] - b
            if local.size:
                parts.append(p.subset(local))
                bounds.append((at, at + int(local.size)))
                at += int(local.size)
        if not parts or parts[0].device != self.device:
            raise ConfigError("a subset of split photos holds none on the first device",
                              fix="split the photos over fewer devices")
        return DevicePhotos(parts, bounds)

    def wait_for_cache(self) -> None:
        for p in self.parts:
            p.wait_for_cache()


def build_device_photos(frames, images, mesh_points, mesh_faces, masks, config, devices: list[str],
                        mesh_normals=None, mesh_uvs=None) -> DevicePhotos:
    """The photos split over ``devices`` (:func:`split_bounds`): every part set up at once on a thread of its
    own (mesh, crops, device buffers), then all parts' photos cropped by the host once, one part after the
    other, each chunk copied to its part's device while the next is cropped, and mapped there
    (:func:`~texstream.fit.stream.photo_set.upload_photo_sets`: the host's copies, which bound the upload, are not
    made to compete). The photos stay on the devices (``photo_residency`` device or auto; a part that does
    not fit fails)."""
    check_split_devices(devices, devices[0])  # the fit's device: the caller's check
    if config.photo_residency not in ("auto", "device"):
        raise ConfigError(f"photos split over devices stay on the devices, not photo_residency "
                          f"{config.photo_residency}", fix="set stream.photo_residency to device (or auto)")
    # parts read no photo cache and write none: one cache serves one photo set
    pcfg = dataclasses.replace(config, photo_residency="device", photo_cache="off")
    bounds = split_bounds(len(frames), len(devices))
    devices = devices[:len(bounds)]
    enable_peer_copies(devices)
    # the set-up's kernels loaded on every device first: two threads must not build one module at once
    for module in ("texstream.render.visibility", "texstream.fit.stream.photo_stream"):
        wp.load_module(module, device=sorted(set(devices)))

    def build(d: int):
        b, e = bounds[d]
        part = images.subset(range(b, e)) if isinstance(images, PhotoFiles) else list(images[b:e])
        return PhotoSet(frames[b:e], part, mesh_points, mesh_faces, masks=None if masks is None else masks[b:e],
                        config=pcfg, device=devices[d], mesh_normals=mesh_normals, mesh_uvs=mesh_uvs,
                        defer_upload=True)

    with concurrent.futures.ThreadPoolExecutor(len(bounds), thread_name_prefix="texstream-photos") as pool:
        # each thread in a copy of this context: the stage's log and its registry of loaders to close
        jobs = [pool.submit(contextvars.copy_context().run, build, d) for d in range(len(bounds))]
        concurrent.futures.wait(jobs)
        parts = [j.result() for j in jobs if j.exception() is None]
    try:
        if len(parts) < len(jobs):
            next(j.result() for j in jobs if j.exception() is not None)  # the first failure, raised
        upload_photo_sets(parts)
    finally:
        for p in parts:
            p.loader.close()
            p.loader = None  # nothing is read again: drop the caller's photos' references
            p.device_masks = None
    photos = DevicePhotos(parts, bounds)
    say("fit", f"photos: {photos.residency_reason}")
    return photos
