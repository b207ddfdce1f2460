"""Procedural sapling geometry for the plant scene: a thin stem, twigs, leaves on stalks, berry clusters.

World frame: millimetres, z up, the stem base at the origin, nothing below it (no ground, no pot).
Built from the orchard's primitives (`srfpipe.scenes.tree`): capsule wood for the stem, twigs,
leaf stalks and berry stalks (all class stem), flat pointed-oval leaves, sphere berries. Sizes
are fractions of `plant_height`, and the whole plant is scaled at the end so its top is exactly
`plant_height`. Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from srfpipe.scenes.tree import (
    Mesh, Segment, point_segment_distance, tilted, far_from, leaves, spheres, wood_mesh,
)

STEM_SEGMENTS = 8
STEM_LENGTH = 0.86  # of plant_height; the top leaves reach the rest
STEM_RADIUS = 0.011  # base radius, of plant_height (3.3 mm on a 300 mm plant)
TAPER = 0.85  # radius ratio end / start of every wood segment, so a chain of segments stays continuous
TWIG_SEGMENTS = 3
TWIG_LENGTH = 0.34  # of plant_height, for the lowest twig; higher twigs are shorter (a cone)
TWIG_RADIUS = 0.45  # of the stem radius where the twig sprouts
MIN_WOOD_RADIUS = 0.0017  # of plant_height: twigs never get thinner than about half a millimetre
LEAF_LENGTH = 0.12  # of plant_height
LEAF_ASPECT = 0.45  # width / length
STALK_LENGTH = 0.035  # leaf stalk (petiole), of plant_height
STALK_RADIUS = 0.0016  # of plant_height: about a pixel wide in the default views
BERRY_RADIUS = 0.017  # of plant_height (5 mm on a 300 mm plant)
BERRY_STALK = 0.04  # of plant_height
BERRIES_PER_CLUSTER = 3
# a pointed oval: base, left flank, widest, towards the tip, tip, and back down the other side
LEAF_OUTLINE = ((-1.0, 0.0), (-0.7, 0.6), (-0.2, 1.0), (0.45, 0.75), (1.0, 0.0),
                (0.45, -0.75), (-0.2, -1.0), (-0.7, -0.6))
TRIANGLES_PER_LEAF = len(LEAF_OUTLINE) - 2


@dataclass
class Sapling:
    """All geometry of one generated plant (world frame, millimetres)."""

    stem: Mesh  # stem, twigs, leaf stalks and berry stalks: the thin class
    leaf: Mesh
    berry: Mesh
    berry_centres: np.ndarray  # (B, 3)
    berry_radius: float
    berry_hue: np.ndarray  # (B,) 0 = scarlet, 1 = orange
    leaf_tint: np.ndarray  # (L,) in [0, 1], dark to light green
    height: float
    info: dict = field(default_factory=dict)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) the tight box of every surface: the object's true extent."""
        points = np.concatenate([self.stem.vertices, self.leaf.vertices, self.berry.vertices])
        return np.stack([points.min(0), points.max(0)]).astype(np.float64)


# ----------------------------------------------------------------------------- skeleton


def _chain(rng, start, direction, length, radius, count, bend, level) -> list[Segment]:
    """`count` segments from `start`, each turning up to `bend` radians and leaning a little upward."""
    segments = []
    for _ in range(count):
        direction = tilted(direction, rng.uniform(0.0, bend), rng.uniform(0, 2 * np.pi))
        direction = direction + np.array([0.0, 0.0, 0.15])  # phototropism
        direction /= np.linalg.norm(direction)
        end = start + (length / count) * direction
        segments.append(Segment(start, end, radius, level))
        start, radius = end, radius * TAPER
    return segments


def _point_on(chain: list[Segment], fraction: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Position, unit direction and radius at `fraction` of a chain's length."""
    lengths = np.array([np.linalg.norm(s.end - s.start) for s in chain])
    at = fraction * lengths.sum()
    k = int(min(np.searchsorted(np.cumsum(lengths), at), len(chain) - 1))
    seg = chain[k]
    local = (at - lengths[:k].sum()) / lengths[k]
    axis = (seg.end - seg.start) / lengths[k]
    return seg.start + local * (seg.end - seg.start), axis, seg.radius * TAPER**local


def _twigs(rng, stem: list[Segment], n_twigs: int, height: float) -> list[list[Segment]]:
    """Twigs along the upper stem at golden-angle azimuths, longest at the bottom."""
    golden = np.pi * (3.0 - np.sqrt(5.0))
    azimuth0 = rng.uniform(0, 2 * np.pi)
    fractions = np.sort(np.linspace(0.3, 0.92, n_twigs) + rng.normal(0, 0.02, n_twigs)) if n_twigs else []
    twigs = []
    for k, fraction in enumerate(fractions):
        start, axis, stem_radius = _point_on(stem, float(np.clip(fraction, 0.05, 0.98)))
        direction = tilted(axis, rng.uniform(0.75, 1.15), azimuth0 + k * golden + rng.normal(0, 0.2))
        length = TWIG_LENGTH * height * (1.0 - 0.6 * fraction) * rng.uniform(0.8, 1.15)
        radius = max(TWIG_RADIUS * stem_radius, MIN_WOOD_RADIUS * height / TAPER**TWIG_SEGMENTS)
        twigs.append(_chain(rng, start, direction, length, radius, TWIG_SEGMENTS, 0.25, 1))
    return twigs


# ----------------------------------------------------------------------------- leaves and berries


def _leaf_on(rng, point, axis, side_angle, height, stalks):
    """One leaf on a stalk sprouting at `point` of a twig or stem with direction `axis`.

    Appends the stalk to `stalks`; returns the leaf's centre, normal, blade direction and length.
    """
    out = tilted(axis, np.radians(rng.uniform(50, 80)), side_angle)
    stalk_end = point + STALK_LENGTH * height * out
    stalks.append(Segment(point, stalk_end, STALK_RADIUS * height, 2))
    blade = out + np.array([0.0, 0.0, -0.25]) + rng.normal(0, 0.15, 3)  # blades droop a little
    blade /= np.linalg.norm(blade)
    length = LEAF_LENGTH * height * rng.uniform(0.75, 1.15)
    centre = stalk_end + 0.5 * length * blade
    normal = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.35, 3) - 0.3 * blade
    return centre, normal, blade, length


def _leaves(rng, stem, twigs, leaves_per_twig: int, height: float):
    """Alternate leaves along every twig and a terminal tuft on the stem; returns leaf arrays and stalks."""
    stalks: list[Segment] = []
    found = []
    for chain in twigs:
        for j in range(leaves_per_twig):
            fraction = 0.3 + 0.7 * (j + rng.uniform(0.3, 0.7)) / leaves_per_twig
            point, axis, _ = _point_on(chain, min(fraction, 1.0))
            found.append(_leaf_on(rng, point, axis, np.pi * j + rng.normal(0, 0.4), height, stalks))
    tip, axis, _ = _point_on(stem, 1.0)
    azimuth0 = rng.uniform(0, 2 * np.pi)
    for j in range(3):
        found.append(_leaf_on(rng, tip, axis, azimuth0 + 2.1 * j, height, stalks))
    centres, normals, blades, lengths = (np.array(v) for v in zip(*found))
    return centres, normals, blades, lengths, stalks


BERRY_TRY_BUDGET = 60_000  # _hang_berries, past this many tries (1000 berries' 60 each: fewer asked, unchanged) ...
BERRY_MAX_MISSES = 6_000  # ... gives up after this many in a row without room: the plant is full


def _hang_berries(rng, twigs, wood, n_berries: int, height: float):
    """Berry centres in clusters near twig tips, each on its own stalk; none touch each other or wood."""
    radius = BERRY_RADIUS * height
    starts = np.array([s.start for s in wood])
    ends = np.array([s.end for s in wood])
    radii = np.array([s.radius for s in wood])
    centres: list[np.ndarray] = []
    stalks: list[Segment] = []
    misses = 0
    for tries in range(60 * max(n_berries, 1)):
        if len(centres) >= n_berries or not twigs or (tries >= BERRY_TRY_BUDGET and misses >= BERRY_MAX_MISSES):
            break
        if misses % 20 == 0 and (misses or len(centres) % BERRIES_PER_CLUSTER == 0):
            # a new cluster on another twig, or a crowded anchor given up
            anchor, _, _ = _point_on(twigs[rng.integers(len(twigs))], rng.uniform(0.55, 0.9))
        down = np.array([*rng.normal(0.0, 0.7, 2), -1.0])
        down /= np.linalg.norm(down)
        stalk_end = anchor + BERRY_STALK * height * rng.uniform(0.8, 1.2) * down
        centre = stalk_end + radius * down
        clearance = point_segment_distance(centre[None], starts, ends)[0] - radii
        if np.any(clearance < radius * 1.05) or not far_from(centre[None], np.array(centres), 2.1 * radius)[0]:
            misses += 1
            continue
        misses = 0
        centres.append(centre)
        stalks.append(Segment(anchor, stalk_end, STALK_RADIUS * height, 2))
    return np.array(centres).reshape(-1, 3), stalks


def _clear_of_berries(leaf_centres, blades, lengths, berry_centres, radius):
    """True for leaves whose midrib passes no berry closer than the berry radius plus half the leaf width."""
    if len(berry_centres) == 0:
        return np.ones(len(leaf_centres), bool)
    bases = leaf_centres - 0.5 * lengths[:, None] * blades
    tips = leaf_centres + 0.5 * lengths[:, None] * blades
    distance = point_segment_distance(berry_centres, bases, tips)  # (B, L)
    return distance.min(0) > radius + 0.5 * LEAF_ASPECT * lengths


# ----------------------------------------------------------------------------- the whole plant


def build_sapling(seed: int, plant_height: float, n_twigs: int, leaves_per_twig: int, n_berries: int) -> Sapling:
    """Generate the full, deterministic plant geometry for one seed."""
    rng = np.random.default_rng(seed)
    h = float(plant_height)
    up = tilted(np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 0.1), rng.uniform(0, 2 * np.pi))
    stem = _chain(rng, np.zeros(3), up, STEM_LENGTH * h, STEM_RADIUS * h, STEM_SEGMENTS, 0.12, 0)
    twigs = _twigs(rng, stem, n_twigs, h)
    leaf_centres, leaf_normals, blades, lengths, leaf_stalks = _leaves(rng, stem, twigs, leaves_per_twig, h)
    wood = stem + [s for chain in twigs for s in chain]
    berry_centres, berry_stalks = _hang_berries(rng, twigs, wood, n_berries, h)
    keep = _clear_of_berries(leaf_centres, blades, lengths, berry_centres, BERRY_RADIUS * h)
    # the berry stalks must not taper to nothing: a stalk is a constant thin tube
    thin = [s for s, k in zip(leaf_stalks, keep) if k] + berry_stalks
    stem_mesh = Mesh.concatenate([wood_mesh(wood, TAPER), wood_mesh(thin, 1.0)])
    # every leaf has its own length: one mesh per leaf keeps leaf k on triangles [k*T, (k+1)*T)
    leaf_mesh = Mesh.concatenate([
        leaves(c[None], n[None], b[None], length, LEAF_ASPECT * length, LEAF_OUTLINE)
        for c, n, b, length in zip(leaf_centres[keep], leaf_normals[keep], blades[keep], lengths[keep])
    ])
    sapling = Sapling(
        stem=stem_mesh, leaf=leaf_mesh, berry=spheres(berry_centres, BERRY_RADIUS * h),
        berry_centres=berry_centres, berry_radius=BERRY_RADIUS * h,
        berry_hue=rng.uniform(0.0, 1.0, len(berry_centres)), leaf_tint=rng.uniform(0.0, 1.0, int(keep.sum())),
        height=h,
    )
    sapling = _scaled(sapling, h / sapling.bounds[1, 2])
    sapling.info = {"n_twigs": len(twigs), "n_leaves": int(keep.sum()), "n_berries": len(berry_centres)}
    return sapling


def _scaled(sapling: Sapling, scale: float) -> Sapling:
    """The plant scaled about the stem base, so its top lands exactly at `height`."""
    def mesh(m: Mesh) -> Mesh:
        return Mesh((m.vertices * scale).astype(np.float32), m.triangles)

    return Sapling(
        stem=mesh(sapling.stem), leaf=mesh(sapling.leaf), berry=mesh(sapling.berry),
        berry_centres=sapling.berry_centres * scale, berry_radius=sapling.berry_radius * scale,
        berry_hue=sapling.berry_hue, leaf_tint=sapling.leaf_tint, height=sapling.height,
    )
