"""Warp kernels of the environments: per-world reset, point gathering, Chamfer distance and occupancy IoU.

They run on the simulation's device, so a batch of 1024 worlds never copies its particles to the host
just to compute a reward.
"""

import warp as wp


@wp.kernel
def reset_worlds_kernel(
    mask: wp.array(dtype=int),
    particle_world: wp.array(dtype=int),
    rest_x: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
):
    """Put the particles of every world with mask[w] != 0 back at rest (x = rest, v = 0, C = 0, F = I)."""
    p = wp.tid()
    if mask[particle_world[p]] != 0:
        x[p] = rest_x[p]
        v[p] = wp.vec3(0.0)
        C[p] = wp.mat33(0.0)
        F[p] = wp.identity(n=3, dtype=float)


@wp.kernel
def reset_ee_kernel(
    mask: wp.array(dtype=int),
    ee_count: int,
    rest_pos: wp.array(dtype=wp.vec3),
    rest_rot: wp.array(dtype=wp.quat),
    pos: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
):
    """Put the end-effectors of every world with mask[w] != 0 back at their initial pose."""
    s = wp.tid()
    if mask[s // ee_count] != 0:
        pos[s] = rest_pos[s]
        rot[s] = rest_rot[s]


@wp.kernel
def gather_kernel(x: wp.array(dtype=wp.vec3), index: wp.array2d(dtype=int), worlds: wp.array(dtype=int),
                  out: wp.array2d(dtype=wp.vec3)):
    """out[w, i] = x[index[w, i]] for w = worlds[j]: a fixed subsample of some worlds' particles."""
    j, i = wp.tid()
    w = worlds[j]
    out[w, i] = x[index[w, i]]


@wp.kernel
def observe_points_kernel(x: wp.array(dtype=wp.vec3), index: wp.array2d(dtype=int), worlds: wp.array(dtype=int),
                          lower: wp.vec3, upper: wp.vec3, out: wp.array2d(dtype=wp.vec3)):
    """out[j, i] = x[index[worlds[j], i]] with NaN read as 0 and every coordinate clamped to [lower, upper]
    (infinities to the bound): the observed points of some worlds, ready for the observation space."""
    j, i = wp.tid()
    p = x[index[worlds[j], i]]
    q = wp.vec3()
    for k in range(3):
        v = p[k]
        if wp.isnan(v):
            v = 0.0
        q[k] = wp.clamp(v, lower[k], upper[k])
    out[j, i] = q


@wp.kernel
def scatter_rows_vec3_kernel(worlds: wp.array(dtype=int), src: wp.array2d(dtype=wp.vec3),
                             dst: wp.array2d(dtype=wp.vec3)):
    """dst[worlds[j], i] = src[j, i]: rows for some worlds, uploaded together."""
    j, i = wp.tid()
    dst[worlds[j], i] = src[j, i]


@wp.kernel
def scatter_rows_int_kernel(worlds: wp.array(dtype=int), src: wp.array2d(dtype=int), dst: wp.array2d(dtype=int)):
    """dst[worlds[j], i] = src[j, i]."""
    j, i = wp.tid()
    dst[worlds[j], i] = src[j, i]


@wp.kernel
def nearest_mean_kernel(
    a: wp.array2d(dtype=wp.vec3), b: wp.array2d(dtype=wp.vec3), worlds: wp.array(dtype=int), scale: float,
    out: wp.array(dtype=float),
):
    """out[w] += scale * distance [m] from a[w, i] to its nearest neighbour in b[w, :] (one-sided Chamfer), for
    w = worlds[n]."""
    n, i = wp.tid()
    w = worlds[n]
    p = a[w, i]
    best = float(1.0e30)
    for j in range(b.shape[1]):
        d = wp.length_sq(b[w, j] - p)
        best = wp.min(best, d)
    wp.atomic_add(out, w, scale * wp.sqrt(best))


@wp.kernel
def occupancy_kernel(
    x: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    mask: wp.array(dtype=int),
    origin: wp.vec3,
    inv_voxel: float,
    res: wp.vec3i,
    occ: wp.array4d(dtype=int),
):
    """Mark the voxel of every particle of a world with mask[w] != 0 as occupied (particles outside the voxel
    box are ignored)."""
    p = wp.tid()
    w = particle_world[p]
    if mask[w] == 0:
        return
    q = (x[p] - origin) * inv_voxel
    i = int(wp.floor(q[0]))
    j = int(wp.floor(q[1]))
    k = int(wp.floor(q[2]))
    if i >= 0 and j >= 0 and k >= 0 and i < res[0] and j < res[1] and k < res[2]:
        occ[w, i, j, k] = 1


@wp.kernel
def iou_counts_kernel(
    occ: wp.array4d(dtype=int), target: wp.array4d(dtype=int), worlds: wp.array(dtype=int),
    inter_count: wp.array(dtype=int), union_count: wp.array(dtype=int)
):
    """Voxel counts of intersection and union of two occupancy grids, for world w = worlds[n]."""
    n, i, j, k = wp.tid()
    w = worlds[n]
    a = occ[w, i, j, k]
    b = target[w, i, j, k]
    if a != 0 and b != 0:
        wp.atomic_add(inter_count, w, 1)
    if a != 0 or b != 0:
        wp.atomic_add(union_count, w, 1)  # (a parameter named "union" breaks the C++ build)
