"""Training steps replayed as one CUDA graph (`train.cuda_graph`, on by default on CUDA).

An eager step launches some hundreds of small kernels and waits on the device a few times (the
occupancy culling and the colour threshold size tensors by what they find). On an H100 that
bound the orchard at 58 steps/s, the GPU mostly idle. Here the step runs with sizes fixed by the
batch (`SRFModel.use_static_shapes`), so it is recorded once and replayed: one launch, no wait.

What stays outside the graph, in the eager loop: the random draws (the step's CPU generator, so a
seed gives the CPU's batches), the occupancy update every `occupancy_update_every` steps (it
rewrites the grid's buffers in place, which the graph reads), the learning rate (written into a
tensor the graph's Adam reads), the hooks. The capacities (how many kept intervals a step may read
the density at, and how many significant samples it may colour) are measured over the first
steps; each step's counts are kept on the device and read at each occupancy update, and a larger
count re-records the graph with room for it (a much smaller one, with less).
"""

from __future__ import annotations

import logging
import math

import torch

log = logging.getLogger(__name__)

# eager steps (static shapes, on a side stream) before the capture: CUDA graphs need the lazy
# initialisations (cuBLAS workspaces, autograd's buffers) done outside the recording
WARMUP_STEPS = 3
# room above the most samples a step has had, and the unit capacities are rounded to
CAPACITY_MARGIN = 1.25
CAPACITY_QUANTUM = 1 << 14
# re-record smaller when the peak falls below this share of the capacity (training concentrates
# the weight on surfaces: the first steps' fog shades many more samples than later ones)
SHRINK_BELOW = 0.4
# Batches up to this many rays are graphed. Measured on an H100 (orchard, 10-s runs): 4096 rays
# 141 steps/s as a graph against 47 step by step; 65536 rays 5.6 against 20, as the capacities
# sized by the first steps' fog pad every step of a large batch (and the plant: 1.5 steps/s).
MAX_GRAPHED_RAYS = 8192


def graph_unavailable(run) -> str | None:
    """Why this run's step cannot be a CUDA graph, or None when it can."""
    s = run.settings
    if run.device.type != "cuda":
        return "not on CUDA"
    if not s.cuda_graph:
        return "train.cuda_graph is false"
    if s.rays_per_batch > MAX_GRAPHED_RAYS:
        return (f"train.rays_per_batch {s.rays_per_batch} is over {MAX_GRAPHED_RAYS}, where step by step measured "
                f"faster (srfpipe.srf.graphed.MAX_GRAPHED_RAYS)")
    if run.scaler is not None:
        return "fp16 loss scaling reads its overflow flag on the host"
    if s.tv_samples is not None and (s.tv_density or s.tv_features):
        return "tv_samples draws random cells inside the step"
    return None


def capacity_for(count: int, limit: int) -> int:
    """A capacity for a peak of `count` samples: with the margin, rounded up, at most `limit`."""
    wanted = int(math.ceil(max(count, 1) * CAPACITY_MARGIN / CAPACITY_QUANTUM)) * CAPACITY_QUANTUM
    return min(wanted, limit)


class GraphedSteps:
    """The part of a training step from the drawn pixels to Adam's update, captured and replayed.

    `step(image, v, u, jitter, within)` runs one step on those pixels (tensors of any device; rays
    through the points `within` of their pixels: (n, 2) in [0, 1), or one number for all, 0.5 the
    centres) and returns (terms, loss, outputs): tensors the next step overwrites.
    """

    def __init__(self, run):
        from dataclasses import replace

        self.run = run
        device = run.device
        data = run.data
        # the images and labels on the device: a replayed step gathers its pixels there
        self.data = replace(data, images=data.images.to(device), poses_scene=data.poses_scene.to(device),
                            intrinsics=data.intrinsics.to(device),
                            multihot=None if data.multihot is None else data.multihot.to(device),
                            probability=None if data.probability is None else data.probability.to(device))
        n = run.settings.rays_per_batch
        # on the CPU (tests) the same static-shape steps run eagerly: nothing is recorded
        self.cuda = device.type == "cuda"
        self.image = torch.zeros(n, dtype=torch.long, device=device)
        self.v = torch.zeros(n, dtype=torch.long, device=device)
        self.u = torch.zeros(n, dtype=torch.long, device=device)
        self.jitter = torch.zeros(n, device=device)
        self.within = torch.full((n, 2), 0.5, device=device)  # the point of each pixel its ray passes
        for group in run.optimizer.param_groups if self.cuda else []:
            # read by the captured Adam from device memory, so a new value needs no new graph
            group["lr"] = torch.tensor(float(group["lr"]), device=device)
            group["capturable"] = True
        self.autocast = (torch.autocast("cuda", dtype=torch.bfloat16 if run.precision == "bf16" else torch.float16,
                                        cache_enabled=False)  # autocast's weight cache breaks replays
                         if run.precision in ("bf16", "fp16") else None)
        self.limit = None  # candidate intervals of a batch: the capacity that can never overflow
        self.capacity = None  # (kept, shaded)
        # the most kept and shaded samples a step has had since the last check
        self.peak = torch.zeros(2, dtype=torch.long, device=device)
        self.graph = None
        self.warm = 0
        self.stream = torch.cuda.Stream(device) if self.cuda else None
        self.captures = 0
        self.result = None

    def step(self, image, v, u, jitter, within=0.5):
        from srfpipe.device import page_locked

        for static, drawn in ((self.image, image), (self.v, v), (self.u, u), (self.jitter, jitter)):
            # page-locked: from pageable memory each copy would wait for the steps queued before it
            static.copy_(page_locked(drawn, static.device), non_blocking=True)
        if isinstance(within, (int, float)):  # one point for every pixel (0.5: the centres); a device fill
            self.within.fill_(float(within))
        else:
            self.within.copy_(page_locked(within, self.within.device), non_blocking=True)
        if self.warm < WARMUP_STEPS or not self.cuda:
            return self._eager_step()
        if self.graph is None:
            self._capture()
        self.graph.replay()
        return self.result

    def stop(self) -> None:
        """Back to eager steps (the trainer's path) after a capture failed."""
        self.graph = None
        self.run.model.use_static_shapes(None)
        self.run.optimizer.zero_grad(set_to_none=True)

    def _eager_step(self):
        """An eager step with static shapes (on CUDA on a side stream, as a warm-up). The warm-up
        runs with room for every candidate (nothing can overflow) and its peak sets the capacity."""
        import contextlib

        model = self.run.model
        if self.limit is None:
            self.limit = self._candidates()
        model.use_static_shapes(self.capacity or (self.limit, self.limit))
        if self.cuda:
            self.stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self.stream) if self.cuda else contextlib.nullcontext():
            self.run.optimizer.zero_grad(set_to_none=True)
            terms, loss, outputs = self._body()
        if self.cuda:
            torch.cuda.current_stream().wait_stream(self.stream)
        self.peak = torch.maximum(self.peak, self._counts(outputs))
        self.warm += 1
        if self.warm == WARMUP_STEPS:
            self.capacity = tuple(capacity_for(count, self.limit) for count in self.peak.tolist())
            self.peak.zero_()
        return terms, loss, outputs

    def _candidates(self) -> int:
        """Candidate intervals per batch (rays x intervals per ray), from one unculled sampling."""
        from srfpipe.srf.sampling import generate_intervals

        model, n = self.run.model, self.image.shape[0]
        origins = torch.zeros(1, 3, device=self.image.device)
        directions = torch.tensor([[0.0, 0.0, 1.0]], device=self.image.device)
        t_start, _ = generate_intervals(origins, directions, model.field.box_min, model.field.box_max,
                                        model.settings, None, model.extent)
        return n * t_start.shape[1]

    def _capture(self) -> None:
        model, optimizer = self.run.model, self.run.optimizer
        model.use_static_shapes(self.capacity)
        optimizer.zero_grad(set_to_none=True)
        self.result = None
        graph = torch.cuda.CUDAGraph()
        # recorded on the warm-up's stream: the parameters' gradient accumulators were made there
        with torch.cuda.graph(graph, stream=self.stream):
            result = self._body()
            self.peak.copy_(torch.maximum(self.peak, self._counts(result[2])))
        self.graph, self.result = graph, result
        self.captures += 1
        n = self.image.shape[0]
        log.info("training step recorded as a CUDA graph: density at up to %d samples a step, colour and "
                 "semantics at up to %d (%.1f and %.1f per ray)", *self.capacity, *(c / n for c in self.capacity))

    @staticmethod
    def _counts(outputs):
        return torch.stack([outputs["samples"], outputs["shaded"]])

    def check_capacity(self) -> None:
        """Re-record the graph when the steps since the last check shaded more samples than it has
        room for, or far fewer (one read back, at the occupancy update's pace)."""
        if self.capacity is None:
            return
        peak = self.peak.tolist()
        self.peak.zero_()
        over = [p > c for p, c in zip(peak, self.capacity)]
        if any(over):
            log.info("a step had %d kept and %d significant samples, over the graph's room for %d and %d: the "
                     "last ones counted as empty or went unshaded; recording it again with more room",
                     *peak, *self.capacity)
        elif not any(p < SHRINK_BELOW * c and c > CAPACITY_QUANTUM for p, c in zip(peak, self.capacity)):
            return
        self.capacity = tuple(capacity_for(p, self.limit) for p in peak)
        self.graph = None

    def _body(self):
        """Pixels to Adam's update: what the graph records (`training_step`'s eager path, on the
        device's copy of the data)."""
        from srfpipe.srf.trainer import loss_terms, pixel_batch, sum_terms

        run, model = self.run, self.run.model
        origins, directions, rgb, labels = pixel_batch(self.data, self.image, self.v, self.u, self.within)
        if run.cameras is not None:
            origins, directions = run.cameras(self.image, origins, directions)
        valid = None if run.labelled_frames is None else run.labelled_frames[self.image]
        with self.autocast if self.autocast is not None else run.autocast:
            outputs = model(origins, directions, self.image, self.jitter)
        terms = loss_terms(run.settings, model, outputs, rgb, labels, valid, None, run.backdrop, run.cameras)
        loss = sum_terms(terms)
        loss.backward()
        run.optimizer.step()
        # detached: a result that kept the autograd graph alive would keep the parameters'
        # gradient accumulators of this step's stream, and the next capture fails on them
        return ({name: value.detach() for name, value in terms.items()}, loss.detach(),
                {name: value.detach() for name, value in outputs.items()})
