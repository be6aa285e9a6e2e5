"""The torch device the numeric kernels run on (`--device`, `[tool.certify] device`).

`cpu` is the default. `cuda` runs the MPDI grid sweep and the adversarial falsifier in float64
on the GPU (`Problem.on` moves the network and P; points are made on the device). The
branch-and-bound bounds still run on the CPU: the enclosure code makes CPU tensors. Their
outward rounding would carry over unchanged (`torch.nextafter` is elementwise and exact on
CUDA as on the CPU), so moving them is plumbing. Not benchmarked on a GPU. Asking for `cuda`
where torch sees no CUDA device is bad input: one line, exit 2, before any work.
"""

from __future__ import annotations

import torch

from certify.errors import SettingsError

DEVICES = ("cpu", "cuda")


def resolve_device(name: str | None) -> torch.device:
    """`torch.device` for a setting value; `SettingsError` (exit 2) when it cannot be used."""
    name = "cpu" if name is None else str(name).strip().lower()
    base = name.split(":", 1)[0]
    if base not in DEVICES:
        raise SettingsError(f"--device must be one of {', '.join(DEVICES)}; got {name!r}")
    if base == "cuda":
        if not torch.cuda.is_available():
            raise SettingsError("--device cuda: torch sees no CUDA device on this machine "
                                f"(torch {torch.__version__}, built with CUDA "
                                f"{torch.version.cuda or 'none'}); use --device cpu")
        try:
            dev = torch.device(name)
        except RuntimeError as exc:
            raise SettingsError(f"--device {name}: {exc}") from None
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise SettingsError(f"--device {name}: only {torch.cuda.device_count()} CUDA "
                                "device(s) here")
        return dev
    return torch.device("cpu")


def describe(device: torch.device) -> str:
    """A short name for reports and benchmarks: 'cpu' or 'cuda:0 (NVIDIA H100 ...)'."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return "cpu"
