"""Training losses: Eq. 5 (photometric MSE) + lambda * Eq. 4 (per-class binary cross-entropy).

The BCE is computed from the rendered logits with `binary_cross_entropy_with_logits` (a stable
log-sigmoid), never as log(sigmoid(x)), so logits of +-1e4 give finite values and gradients.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from srfpipe.device import randint


def photometric_loss(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_photo = 1/|R| sum_r ||C(r) - C_hat(r)||^2 (Eq. 5), rgb and target (R, 3) in [0, 1]."""
    if rgb.shape[0] == 0:
        return rgb.sum() * 0.0
    return ((rgb.float() - target.float()) ** 2).sum(dim=-1).mean()


def semantic_loss(
    logits: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor | None = None,
    positive_weight: float = 1.0,
) -> torch.Tensor:
    """L_sem = 1/|R| sum_r sum_c BCE(sigmoid(S_hat_c(r)), y_c(r)) (Eq. 4).

    logits (R, C) rendered per-class logits; labels (R, C) in [0, 1] (the 0/1 multi-hot bits, or
    the masks' probabilities); `valid` (R,) excludes rays that carry no label information.
    `positive_weight` w scales each class's positive term, -w y log p - (1 - y) log(1 - p), whose
    minimum over p is at w y / (w y + 1 - y): p >= 0.5 wherever y >= 1 / (1 + w).
    Returns 0 (with a graph) when no ray is valid.
    """
    weight = None if positive_weight == 1.0 else torch.full((logits.shape[-1],), float(positive_weight),
                                                             device=logits.device)
    per_ray = F.binary_cross_entropy_with_logits(
        logits.float(), labels.float(), reduction="none", pos_weight=weight
    ).sum(dim=-1)
    if per_ray.numel() == 0:
        return logits.sum() * 0.0
    if valid is None:
        return per_ray.mean()
    # a masked mean, not a boolean index: no host sync on CUDA (and a CUDA graph can replay it)
    # (where, not a product: an unlabelled ray's value, whatever it is, never reaches the sum)
    return torch.where(valid, per_ray, 0.0).sum() / valid.float().sum().clamp_min(1.0)


def total_loss(
    rgb: torch.Tensor,
    target_rgb: torch.Tensor,
    logits: torch.Tensor,
    labels: torch.Tensor,
    lambda_sem: float = 1.0,
    valid: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """L = L_photo + lambda L_sem (Eq. 5), with the parts for logging."""
    photo = photometric_loss(rgb, target_rgb)
    sem = semantic_loss(logits, labels, valid)
    return {"loss": photo + lambda_sem * sem, "photometric": photo, "semantic": sem}


def background_opacity_loss(accumulation: torch.Tensor, labels: torch.Tensor,
                            valid: torch.Tensor | None = None,
                            shows_backdrop: torch.Tensor | None = None) -> torch.Tensor:
    """Mean opacity of the rays whose pixel shows the empty backdrop.

    Such a ray crosses empty space: any opacity it gathers is fog or a floater that the
    photometric loss cannot see against a plain background (dark density in front of a dark
    backdrop costs nothing in the training views and hides the object in the others). The whole
    ray counts, the model box and the contracted shell alike: the background colour model
    shows the backdrop, and fog asked out of the box only settles just beyond it (a tight box
    round a plant), where new views see it beside the plant. accumulation (R,), labels (R, C) multi-hot.

    `shows_backdrop` (R,): the pixel has the backdrop's colour (from the image, in every frame).
    A pixel counts when it shows the backdrop and none of the classes: a part the masks missed (a
    thin stem, a leaf dropped from one view's mask) is not backdrop-coloured and is not emptied,
    and a pixel a mask marks keeps its matter even where it is as dark as the backdrop.
    Without it (labels.zarr written before backdrop_level), a pixel no mask marks counts, and
    `valid` (R,) excludes rays of frames without masks (their zero labels say nothing).
    """
    background = labels.sum(dim=-1) == 0
    if shows_backdrop is not None:
        background = background & shows_backdrop
    elif valid is not None:
        background = background & valid
    # a masked mean, not a boolean index: no host sync on CUDA; 0 when no ray shows background
    weight = background.float()
    return (accumulation.float() * weight).sum() / weight.sum().clamp_min(1.0)


def shows_backdrop(rgb: torch.Tensor, colour: torch.Tensor, level: float) -> torch.Tensor:
    """(R,) bool: pixels (R, 3) in [0, 1] within `level` 8-bit levels of the backdrop `colour` (3,)
    in every channel."""
    return ((rgb.float() - colour) * 255.0).abs().amax(dim=-1) <= level


def total_variation(table: torch.Tensor, resolution, samples: int | None = None,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """Mean squared difference between neighbouring grid points along x, y and z (Plenoxels' TV).

    table (Rx*Ry*Rz, F) channels-last, x-major (as `DenseGrid` stores it). Penalising it makes a
    cell's value agree with its neighbours unless the photometric loss insists, which removes the
    isolated floaters that a dense grid otherwise grows to fit single training views.

    With `samples` smaller than the number of cells, the mean is estimated at that many random
    cells (as Plenoxels does): the exact sum reads and differentiates the whole table every step,
    which on the CPU nearly doubles a step of a multi-level feature grid.
    """
    rx, ry, rz = (int(r) for r in resolution)
    cells = (rx - 1) * (ry - 1) * (rz - 1)
    if samples is None or samples >= cells:
        grid = table.view(rx, ry, rz, -1).float()
        dx = (grid[1:] - grid[:-1]).square().mean()
        dy = (grid[:, 1:] - grid[:, :-1]).square().mean()
        dz = (grid[:, :, 1:] - grid[:, :, :-1]).square().mean()
        return dx + dy + dz
    # a cell's corner (i, j, k) with i < rx - 1 etc., and its +x, +y, +z neighbours
    cell = randint(0, cells, int(samples), generator, table.device)
    k = cell % (rz - 1)
    j = (cell // (rz - 1)) % (ry - 1)
    i = cell // ((rz - 1) * (ry - 1))
    base = (i * ry + j) * rz + k
    # index_select: its backward is an index_add_, far faster on the CPU than indexing's index_put_
    value = table.index_select(0, base).float()
    return sum((table.index_select(0, base + stride).float() - value).square().mean()
               for stride in (ry * rz, rz, 1))


def grid_total_variation(encoding, samples: int | None = None,
                         generator: torch.Generator | None = None) -> torch.Tensor:
    """`total_variation` summed over the dense grids of an encoding (every level of a
    multi-resolution grid); `samples` random cells per grid, or every cell when None."""
    from srfpipe.srf.encodings import DenseGrid

    # a hashed level's rows are not neighbours in space
    grids = [m for m in encoding.modules() if isinstance(m, DenseGrid) and not m.hashed]
    return sum(total_variation(g.table, g.resolution, samples, generator) for g in grids)


def appearance_smoothness_loss(embedding: torch.Tensor, weight: torch.Tensor, neighbour: torch.Tensor) -> torch.Tensor:
    """mean_i ||W_a (a_i - a_n(i))||^2 over the training images i and the image n(i) taken nearest
    to each (`neighbour`: pairs (K, 2) of embedding rows; none gives 0). W_a (hidden, dim): the
    colour MLP's first-layer weights on the embedding; on a_i alone the penalty would be undone by
    a W_a that grows as the embeddings shrink."""
    if neighbour.shape[0] == 0:
        return embedding.sum() * 0.0
    # in float32 whatever autocast says, like the other losses: a half-precision product lost
    # ~0.3 % of it in bf16, and its squares overflowed fp16 at differences of a few hundred
    with torch.autocast(embedding.device.type, enabled=False):
        difference = (embedding[neighbour[:, 0]] - embedding[neighbour[:, 1]]).float() @ weight.float().T
        return difference.pow(2).sum(dim=-1).mean()
