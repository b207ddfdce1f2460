"""Device choice, in one place: CUDA when present, otherwise the CPU."""

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
    return device
