"""Device choice, in one place: CUDA when present, otherwise the CPU; and the seeded random
draws (`rand`, `randint`, `randperm`) that work whatever device their result goes to."""

from __future__ import annotations


def choose_device(requested: str = "auto"):
    """A torch.device for `requested` ("auto", "cpu", "cuda", "cuda:1").

    "auto" takes CUDA when torch sees a GPU. Asking for CUDA without one is an error, not a
    silent fallback, so a cluster job that lost its GPU fails loudly.
    """
    import torch

    if requested == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(requested)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {requested!r} was requested but torch sees no CUDA GPU")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise RuntimeError(f"device {requested!r} was requested but torch sees {torch.cuda.device_count()} CUDA GPU(s)")
    return device


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory for reuse instead of returning it to the OS.

    A training step allocates and frees tensors the size of the dense grids (a 96^3 x 16 feature
    gradient is 57 MB). glibc serves every allocation above 32 MB with a fresh mmap and unmaps it
    on free, so each step page-faults that memory in again: zeroing such a buffer took 59 ms
    instead of 17 ms here (one thread), and a demo training step 0.66 s instead of 0.43 s (two).
    Serving everything from the heap (no mmap) and trimming it only above 1 GB keeps those pages
    resident. Returns False (and changes nothing) where glibc is not the C library.
    """
    import ctypes
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # mallopt parameters from <malloc.h>
    return bool(libc.mallopt(m_mmap_max, 0)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))


# ----------------------------------------------------------------------------- random draws
# Every seeded random draw in srfpipe/ goes through these helpers: tests/test_device.py fails on
# any other call that passes `generator=`.


def _draw_device(generator):
    return generator.device if generator is not None else "cpu"


def _size(shape) -> tuple:
    """A size tuple from an int (a numpy integer too) or a sequence of them."""
    import operator

    return (operator.index(shape),) if hasattr(shape, "__index__") else tuple(operator.index(s) for s in shape)


def _moved(values, device):
    """`values` on `device`. Towards an accelerator the copy is queued (non_blocking) from page-locked
    memory: from pageable memory CUDA first waits for everything queued on the stream, a host wait in
    the middle of each training step. A non-blocking copy *to* the CPU could be read before it lands."""
    import torch

    device = torch.device(device)
    if device.type == "cpu" or values.device == device:
        return values.to(device)
    return page_locked(values, device).to(device, non_blocking=True)


class DeviceBacklog:
    """Keeps the host at most `steps` steps ahead of the device, so that a clock read after a step
    counts the device's work of all but the last few (training seconds, `train.time_budget`).

    On CUDA a step returns once its kernels are queued (a replayed graph: microseconds). The
    training clock then counted the queuing alone, and the device's backlog (up to
    `train.log_every` steps) was waited for in the next hook that read a value, outside the
    training seconds: on an H100 (2026-11-28) a 30-s orchard budget ran 42 s of loop, 7345 steps
    counted as 244 steps/s where the wall saw 175. Each step records an event, and the host waits
    for the one `steps` back: still queued ahead (the device never waits for the host), and never
    more than `steps` steps of device work left uncounted. On the CPU nothing is queued: no-op.
    """

    def __init__(self, device, steps: int = 2):
        import collections

        import torch

        self.cuda = torch.device(device).type == "cuda"
        self.steps = steps
        self.pending = collections.deque()

    def settle(self) -> None:
        """After a step is queued: wait until no more than `steps` steps are left on the device."""
        if not self.cuda:
            return
        import torch

        event = torch.cuda.Event()
        event.record()
        self.pending.append(event)
        while len(self.pending) > self.steps:
            self.pending.popleft().synchronize()


def page_locked(values, device):
    """A CPU tensor bound for CUDA in page-locked (pinned) memory, from which the copy need not wait;
    any other as it is."""
    import torch

    return values.pin_memory() if values.device.type == "cpu" and torch.device(device).type == "cuda" else values


def rand(shape, generator, device, dtype=None):
    """Uniform [0, 1) values of `shape`, drawn on `generator`'s device and moved to `device`.

    Why not torch.rand(shape, generator=generator, device=device): a torch.Generator draws only on
    its own device, so a CPU generator with a CUDA `device` raises "Expected a 'cuda' device type
    for generator but found 'cpu'" (issue 31). Drawing on the generator's device instead (the CPU
    for the per-step generators of `srfpipe.srf.trainer.step_generator`) and moving the result
    also gives a seed the same samples (rays, jitter, cells) whether the model sits on the CPU or
    on CUDA, and a resumed run replays the same stream. Without a generator (None) the draw
    comes from torch's global CPU generator (seeded by torch.manual_seed), likewise moved.
    """
    import torch

    return _moved(torch.rand(_size(shape), generator=generator, device=_draw_device(generator), dtype=dtype), device)


def randint(low: int, high: int, shape, generator, device):
    """int64 values uniform in [low, high) of `shape`, drawn on `generator`'s device (the CPU
    without one) and moved to `device`; see `rand` for why."""
    import torch

    return _moved(torch.randint(int(low), int(high), _size(shape), generator=generator,
                                device=_draw_device(generator)), device)


def randperm(n: int, generator, device):
    """A random permutation of 0..n-1 (int64), drawn on `generator`'s device (the CPU without one)
    and moved to `device`; see `rand` for why."""
    import torch

    return _moved(torch.randperm(int(n), generator=generator, device=_draw_device(generator)), device)
