"""The Warp device a command runs on: ``auto`` picks the first CUDA device Warp sees, else the CPU.

``auto`` is the default of ``run``, ``fit``, ``refine``, ``mesh`` and ``atlas``: a user with a GPU gets it
without knowing the option, and CI (no GPU) runs on the CPU. A device named explicitly is checked against
what Warp sees, so ``--device cuda:1`` on a one-GPU machine is a one-line error, not a traceback deep in a
kernel launch. Warp is imported inside the function (``core`` imports only the standard library and numpy).
"""

from __future__ import annotations

from .errors import ConfigError

AUTO = "auto"
DEVICE_HELP = "Warp device: auto (the first CUDA device when Warp sees one, else the CPU), cpu or cuda:N"


def cuda_device_count() -> int:
    """CUDA devices Warp sees (0 without a driver or a GPU)."""
    import warp as wp

    try:
        return int(wp.get_cuda_device_count())
    except Exception:  # noqa: BLE001 - a broken driver is the same as no GPU for choosing a device
        return 0


def resolve_device(requested: str | None) -> str:
    """The Warp device name to run on: ``auto`` (or None) -> ``cuda:0`` when Warp sees a CUDA device, else
    ``cpu``; ``cpu``, ``cuda`` and ``cuda:N`` are checked to exist (ConfigError naming the fix otherwise)."""
    name = AUTO if requested is None else str(requested).strip().lower()
    if name == AUTO:
        return "cuda:0" if cuda_device_count() > 0 else "cpu"
    if name == "cpu":
        return name
    if name == "cuda" or name.startswith("cuda:"):
        index = 0 if name == "cuda" else name.split(":", 1)[1]
        if not str(index).isdigit():
            raise ConfigError(f"device {requested!r} is not cuda:N", fix="use --device auto, cpu or cuda:0")
        count = cuda_device_count()
        if int(index) >= count:
            raise ConfigError(f"device {requested!r} is not available (Warp sees {count} CUDA device(s))",
                              fix="use --device auto or cpu" + (f", or cuda:0..cuda:{count - 1}" if count else ""))
        return f"cuda:{int(index)}"
    raise ConfigError(f"device {requested!r} unknown", fix="use --device auto, cpu or cuda:N")


def available_memory_bytes() -> int | None:
    """Memory the OS says a new allocation may take (Linux MemAvailable); None where it does not say."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return None
