"""The one reading of a device name: ``auto`` is CUDA when torch sees a GPU, else the CPU."""

from __future__ import annotations

__all__ = ["resolve_device"]


def resolve_device(device: str = "auto") -> str:
    """``device`` as torch takes it: ``auto`` resolved on this machine, any other name (cpu, cuda, cuda:N) as given."""
    if device != "auto":
        return device
    import torch  # here, not at import: the API process names devices without loading torch

    return "cuda" if torch.cuda.is_available() else "cpu"
