"""Numba kernels of the cache queries: one pass over the points, parallel over 2+ cores.

Conventions shared by all kernels: `points` (M, 3) world xyz (float32 or float64), grids indexed
[z, y, x], `origin` world xyz of the grid's min corner, `inv_v` = 1 / voxel size. Each kernel
returns how many points had a NaN coordinate; the Python side turns that into a ValueError.
Points outside the grid box are free space (0 / no class).
"""

from __future__ import annotations

import numpy as np
from numba import config, njit, prange

# OpenMP first: numba's default TBB layer warns (and is skipped) with the TBB that pip installs
config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

_OPTS = dict(parallel=True, cache=True, nogil=True, fastmath=False)


@njit(inline="always")
def grid_coordinates(points, m, origin, inv_v):
    """Point m in voxel units from the grid's min corner (x, y, z): voxel i spans [i, i + 1)."""
    return ((points[m, 0] - origin[0]) * inv_v, (points[m, 1] - origin[1]) * inv_v,
            (points[m, 2] - origin[2]) * inv_v)


@njit(inline="always")
def inside_grid(gx, gy, gz, nx, ny, nz):
    """Whether voxel coordinates lie in the grid (False for NaN: every comparison fails)."""
    return gx >= 0 and gy >= 0 and gz >= 0 and gx < nx and gy < ny and gz < nz


@njit(inline="always")
def any_nan(gx, gy, gz):
    return gx != gx or gy != gy or gz != gz


@njit(**_OPTS)
def nearest_u8(points, grid, origin, inv_v, out):
    """out[m] = grid value of the voxel containing points[m], 0 outside."""
    nz, ny, nx = grid.shape
    flat = grid.reshape(-1)
    bad = 0
    for m in prange(points.shape[0]):
        gx, gy, gz = grid_coordinates(points, m, origin, inv_v)
        if inside_grid(gx, gy, gz, nx, ny, nz):
            out[m] = flat[(int(gz) * ny + int(gy)) * nx + int(gx)]
        else:
            out[m] = 0
            if any_nan(gx, gy, gz):
                bad += 1
    return bad


@njit(**_OPTS)
def nearest_channels_u8(points, grid, origin, inv_v, out):
    """out[m, c] = grid[z, y, x, c] of the voxel containing points[m] (channels last), 0 outside."""
    nz, ny, nx, nc = grid.shape
    bad = 0
    for m in prange(points.shape[0]):
        gx, gy, gz = grid_coordinates(points, m, origin, inv_v)
        if inside_grid(gx, gy, gz, nx, ny, nz):
            iz, iy, ix = int(gz), int(gy), int(gx)
            for c in range(nc):
                out[m, c] = grid[iz, iy, ix, c]
        else:
            for c in range(nc):
                out[m, c] = 0
            if any_nan(gx, gy, gz):
                bad += 1
    return bad


@njit(inline="always")
def axis_corners(u, n):
    """Lower corner index, the other corner and the weight of the upper one along one axis.

    u is the coordinate in voxel-centre units (centre of voxel i at u = i); beyond the outermost
    centres the value is held constant (both corners clamp to the edge). Also the trilinear
    lookup of the baked field's ray march (srfpipe.sim.baked).
    """
    i0 = int(np.floor(u))
    f = u - i0
    i1 = i0 + 1
    if i0 < 0:
        i0 = 0
    if i1 < 0:
        i1 = 0
    if i0 > n - 1:
        i0 = n - 1
    if i1 > n - 1:
        i1 = n - 1
    return i0, i1, f


@njit(**_OPTS)
def trilinear_channels_u8(points, grid, origin, inv_v, scale, out):
    """out[m, :] = scale * trilinear interpolation of grid (z, y, x, C) uint8, 0 outside the grid."""
    nz, ny, nx, nc = grid.shape
    bad = 0
    for m in prange(points.shape[0]):
        gx, gy, gz = grid_coordinates(points, m, origin, inv_v)
        if not inside_grid(gx, gy, gz, nx, ny, nz):
            for c in range(nc):
                out[m, c] = 0
            if any_nan(gx, gy, gz):
                bad += 1
            continue
        x0, x1, fx = axis_corners(gx - 0.5, nx)
        y0, y1, fy = axis_corners(gy - 0.5, ny)
        z0, z1, fz = axis_corners(gz - 0.5, nz)
        w000 = (1 - fz) * (1 - fy) * (1 - fx)
        w001 = (1 - fz) * (1 - fy) * fx
        w010 = (1 - fz) * fy * (1 - fx)
        w011 = (1 - fz) * fy * fx
        w100 = fz * (1 - fy) * (1 - fx)
        w101 = fz * (1 - fy) * fx
        w110 = fz * fy * (1 - fx)
        w111 = fz * fy * fx
        for c in range(nc):
            acc = (w000 * grid[z0, y0, x0, c] + w001 * grid[z0, y0, x1, c]
                   + w010 * grid[z0, y1, x0, c] + w011 * grid[z0, y1, x1, c]
                   + w100 * grid[z1, y0, x0, c] + w101 * grid[z1, y0, x1, c]
                   + w110 * grid[z1, y1, x0, c] + w111 * grid[z1, y1, x1, c])
            out[m, c] = acc * scale
    return bad


@njit(**_OPTS)
def trilinear_f32(points, grid, origin, inv_v, out):
    """out[m] = trilinear interpolation of a float grid (z, y, x), 0 outside the grid."""
    nz, ny, nx = grid.shape
    bad = 0
    for m in prange(points.shape[0]):
        gx, gy, gz = grid_coordinates(points, m, origin, inv_v)
        if not inside_grid(gx, gy, gz, nx, ny, nz):
            out[m] = 0
            if any_nan(gx, gy, gz):
                bad += 1
            continue
        x0, x1, fx = axis_corners(gx - 0.5, nx)
        y0, y1, fy = axis_corners(gy - 0.5, ny)
        z0, z1, fz = axis_corners(gz - 0.5, nz)
        c00 = grid[z0, y0, x0] * (1 - fx) + grid[z0, y0, x1] * fx
        c01 = grid[z0, y1, x0] * (1 - fx) + grid[z0, y1, x1] * fx
        c10 = grid[z1, y0, x0] * (1 - fx) + grid[z1, y0, x1] * fx
        c11 = grid[z1, y1, x0] * (1 - fx) + grid[z1, y1, x1] * fx
        out[m] = (c00 * (1 - fy) + c01 * fy) * (1 - fz) + (c10 * (1 - fy) + c11 * fy) * fz
    return bad


@njit(**_OPTS)
def distance_gradient(points, grid, origin, voxel_size, out_d, out_g):
    """Signed distance and its gradient (world units) from a distance grid (z, y, x).

    Inside the box of voxel centres: trilinear interpolation and its exact gradient. Beyond it the
    point q is clamped onto that box and d(p) = d(q) + |p - q|, which stays continuous and whose
    gradient points away from the grid (free space outside).
    """
    nz, ny, nx = grid.shape
    inv_v = 1.0 / voxel_size
    bad = 0
    for m in prange(points.shape[0]):
        u = np.empty(3)
        e = np.zeros(3)
        u[0] = (points[m, 0] - origin[0]) * inv_v - 0.5
        u[1] = (points[m, 1] - origin[1]) * inv_v - 0.5
        u[2] = (points[m, 2] - origin[2]) * inv_v - 0.5
        if u[0] != u[0] or u[1] != u[1] or u[2] != u[2]:
            bad += 1
            out_d[m] = np.nan
            out_g[m, 0] = np.nan
            out_g[m, 1] = np.nan
            out_g[m, 2] = np.nan
            continue
        free = np.ones(3)  # 1 where the axis is not clamped (the interpolant depends on it)
        n3 = (nx, ny, nz)
        for a in range(3):
            hi = n3[a] - 1.0
            if u[a] < 0.0:
                e[a] = u[a] * voxel_size
                u[a] = 0.0
                free[a] = 0.0
            elif u[a] > hi:
                e[a] = (u[a] - hi) * voxel_size
                u[a] = hi
                free[a] = 0.0
        x0, x1, fx = axis_corners(u[0], nx)
        y0, y1, fy = axis_corners(u[1], ny)
        z0, z1, fz = axis_corners(u[2], nz)
        d000 = grid[z0, y0, x0]
        d001 = grid[z0, y0, x1]
        d010 = grid[z0, y1, x0]
        d011 = grid[z0, y1, x1]
        d100 = grid[z1, y0, x0]
        d101 = grid[z1, y0, x1]
        d110 = grid[z1, y1, x0]
        d111 = grid[z1, y1, x1]
        c00 = d000 * (1 - fx) + d001 * fx
        c01 = d010 * (1 - fx) + d011 * fx
        c10 = d100 * (1 - fx) + d101 * fx
        c11 = d110 * (1 - fx) + d111 * fx
        c0 = c00 * (1 - fy) + c01 * fy
        c1 = c10 * (1 - fy) + c11 * fy
        d = c0 * (1 - fz) + c1 * fz
        # derivatives of the trilinear interpolant per voxel, then per world unit
        dx = ((d001 - d000) * (1 - fy) + (d011 - d010) * fy) * (1 - fz) + \
             ((d101 - d100) * (1 - fy) + (d111 - d110) * fy) * fz
        dy = (c01 - c00) * (1 - fz) + (c11 - c10) * fz
        dz = c1 - c0
        # a degenerate axis (one voxel thick) has no interpolation partner
        gx = dx * inv_v * free[0] if x1 != x0 else 0.0
        gy = dy * inv_v * free[1] if y1 != y0 else 0.0
        gz = dz * inv_v * free[2] if z1 != z0 else 0.0
        outside = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        if outside > 0:
            d += outside
            gx += e[0] / outside
            gy += e[1] / outside
            gz += e[2] / outside
        out_d[m] = d
        out_g[m, 0] = gx
        out_g[m, 1] = gy
        out_g[m, 2] = gz
    return bad


@njit(**_OPTS)
def raycast(origins, directions, max_t, levels, offsets, shapes, leaf_class, origin, voxel_size, out_t, out_c):
    """First occupied voxel along each ray, skipping empty space through the octree levels.

    levels: all levels concatenated (uint8, level k = cells of 2^k voxels, [z, y, x] order) at
    `offsets[k]` with `shapes[k]` = (nz, ny, nx); level 0 is the voxel grid. At each step the ray
    jumps to the exit of the largest empty cell containing it. out_t = distance along the (unit)
    direction to the entry of the hit voxel, inf for a miss; out_c = its class, -1 for none.
    """
    n_levels = offsets.shape[0]
    nz, ny, nx = shapes[0, 0], shapes[0, 1], shapes[0, 2]
    dims = (nx, ny, nz)
    nudge = 1e-4 * voxel_size
    bad = 0
    for r in prange(origins.shape[0]):
        out_t[r] = np.inf
        out_c[r] = -1
        o = origins[r]
        d = directions[r]
        if o[0] != o[0] or o[1] != o[1] or o[2] != o[2] or d[0] != d[0] or d[1] != d[1] or d[2] != d[2]:
            bad += 1
            continue
        t0 = 0.0
        t1 = max_t[r]
        miss = False
        for a in range(3):
            lo = origin[a]
            hi = origin[a] + dims[a] * voxel_size
            if d[a] != 0.0:
                ta = (lo - o[a]) / d[a]
                tb = (hi - o[a]) / d[a]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
            elif o[a] < lo or o[a] >= hi:
                miss = True
        if miss or t0 > t1:
            continue
        # march from the box's entry point: t measured from there keeps a voxel's nudge above the
        # float spacing of t even for an origin far away (1e300 away, t + nudge == t never advanced)
        entry = np.empty(3, dtype=np.float64)
        for a in range(3):
            entry[a] = min(max(o[a] + t0 * d[a], origin[a]), origin[a] + dims[a] * voxel_size)
        t = 0.0
        t_end = t1 - t0
        while t <= t_end:
            idx = np.empty(3, dtype=np.int64)
            for a in range(3):
                g = (entry[a] + (t + nudge) * d[a] - origin[a]) / voxel_size
                i = int(np.floor(g))
                idx[a] = min(max(i, 0), dims[a] - 1)
            # the coarsest empty level containing the point (0 = the voxel itself)
            empty_level = -1
            for k in range(n_levels - 1, -1, -1):
                cx, cy, cz = idx[0] >> k, idx[1] >> k, idx[2] >> k
                flat = offsets[k] + (cz * shapes[k, 1] + cy) * shapes[k, 2] + cx
                if levels[flat] == 0:
                    empty_level = k
                    break
            if empty_level < 0:
                out_t[r] = t0 + t
                out_c[r] = leaf_class[idx[2], idx[1], idx[0]]
                break
            size = 1 << empty_level
            t_exit = np.inf
            for a in range(3):
                if d[a] != 0.0:
                    lo_cell = (idx[a] >> empty_level) << empty_level
                    bound = lo_cell + size if d[a] > 0 else lo_cell
                    t_a = (origin[a] + bound * voxel_size - entry[a]) / d[a]
                    if t_a < t_exit:
                        t_exit = t_a
            t_next = max(t_exit, t + nudge)
            if not t_next > t:  # no progress (rounding): leave the ray rather than loop forever
                break
            t = t_next
    return bad


# The same kernel on one thread: the simulator asks for a hundred points per step, where waking
# the parallel threads costs more than the work (and a busy machine makes it much worse).
distance_gradient_serial = njit(cache=True, nogil=True, fastmath=False)(distance_gradient.py_func)
