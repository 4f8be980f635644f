"""The CPU floating-point mode training and meshing run in."""

from __future__ import annotations

import torch


def flush_denormals() -> bool:
    """Treat float32 denormals as zero (x86 FTZ/DAZ) in this thread and in the compute threads it starts later.

    NeUDF's exp weight exp(-r d) and NeuS's sigmoid at r, s of several hundred underflow into denormals away
    from the surface, and an x86 core computes with those many times slower: without this a run slows
    down as it sharpens. Values below 1.2e-38 are nothing the method reads.

    The mode belongs to a thread; torch's compute threads take it from the thread that starts them, so
    call this before the first parallel operation (threads started earlier keep their mode). Returns False
    where the CPU has no such mode, and nothing changes.
    """
    return torch.set_flush_denormal(True)
