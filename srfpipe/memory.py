"""Estimate before allocating: a stage that allocates in proportion to a config value or an image
header checks the estimate against the memory this run may use, and refuses naming the key and both
numbers, instead of failing a minute later with an allocator's message that names nothing.

The limit is `SRFPIPE_MAX_MEMORY_GB` when set, else the machine's physical memory (a CUDA device's
own memory for tensors that live there).
"""

from __future__ import annotations

import os

LIMIT_VARIABLE = "SRFPIPE_MAX_MEMORY_GB"


class MemoryEstimateError(ValueError):
    """An allocation a setting asks for would not fit the memory this run may use."""


def physical_memory_bytes() -> int:
    return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))


def memory_limit_bytes(device=None) -> tuple[int, str]:
    """The bytes this run may use and where that number comes from."""
    value = os.environ.get(LIMIT_VARIABLE)
    if value:
        try:
            limit = float(value)
        except ValueError:
            raise MemoryEstimateError(f"{LIMIT_VARIABLE}={value!r}: not a number of gigabytes") from None
        if not limit > 0:
            raise MemoryEstimateError(f"{LIMIT_VARIABLE}={value!r}: must be a positive number of gigabytes")
        return int(limit * 1e9), LIMIT_VARIABLE
    if device is not None and str(device).startswith("cuda"):
        import torch

        return int(torch.cuda.get_device_properties(torch.device(device)).total_memory), f"{device}'s memory"
    return physical_memory_bytes(), "the machine's memory"


def gigabytes(nbytes: float) -> str:
    return f"{nbytes / 1e9:.3g} GB"


def check_allocation(nbytes: float, key: str, what: str, device=None) -> None:
    """Raise MemoryEstimateError, naming `key`, when `nbytes` exceed the run's memory limit."""
    limit, source = memory_limit_bytes(device)
    if nbytes > limit:
        raise MemoryEstimateError(
            f"{key}: {what} needs about {gigabytes(nbytes)}, more than the {gigabytes(limit)} this run may use "
            f"({source}); lower {key} (or set {LIMIT_VARIABLE})")
