"""Particle sampling: fill boxes, cylinders (ropes), spheres, point sets and meshes at a chosen density.

Every sampler returns ``(positions [n, 3] m, volumes [n] m^3)``; the particle mass follows from the
material density in the solver, so ``volumes.sum()`` is the sampled volume of the body.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np
import warp as wp

__all__ = ["sample_box", "sample_cylinder", "sample_sphere", "sample_points", "sample_mesh"]


def _lattice(lower, upper, spacing, rng, jitter):
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    counts = np.maximum(np.round((upper - lower) / spacing).astype(int), 1)
    axes = [lower[i] + (np.arange(counts[i]) + 0.5) * (upper[i] - lower[i]) / counts[i] for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    cell = (upper - lower) / counts
    if jitter > 0:
        rng = np.random.default_rng(rng)
        pts = pts + rng.uniform(-0.5, 0.5, pts.shape) * cell * jitter
    return pts, float(np.prod(cell))


def _spacing(dx: float, ppc: float) -> float:
    if dx <= 0 or ppc <= 0:
        raise ValueError(f"dx and particles_per_cell must be > 0, got dx={dx!r}, particles_per_cell={ppc!r}")
    return dx / float(ppc) ** (1.0 / 3.0)


def sample_box(lower: Sequence[float], upper: Sequence[float], dx: float, particles_per_cell: float = 8,
               *, seed: Optional[int] = 0, jitter: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """Fill the axis-aligned box [lower, upper] (m) with about ``particles_per_cell`` particles per grid cell of size dx (m)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if np.any(upper <= lower):
        raise ValueError(f"sample_box: upper {upper.tolist()} must exceed lower {lower.tolist()} on every axis")
    pts, vol = _lattice(lower, upper, _spacing(dx, particles_per_cell), seed, jitter)
    return pts, np.full(len(pts), vol)


def sample_cylinder(start: Sequence[float], end: Sequence[float], radius: float, dx: float,
                    particles_per_cell: float = 8, *, seed: Optional[int] = 0, jitter: float = 0.0):
    """Fill a solid cylinder (a rope) from ``start`` to ``end`` (m) of ``radius`` (m)."""
    a, b = np.asarray(start, float), np.asarray(end, float)
    axis = b - a
    length = np.linalg.norm(axis)
    if length <= 0 or radius <= 0:
        raise ValueError(f"sample_cylinder: need start != end and radius > 0, got length {length}, radius {radius}")
    h = _spacing(dx, particles_per_cell)
    pts, _ = _lattice([-radius, -radius, 0.0], [radius, radius, length], h, seed, jitter)
    keep = pts[:, 0] ** 2 + pts[:, 1] ** 2 <= radius**2
    pts = pts[keep]
    z = axis / length
    tmp = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    xax = np.cross(z, tmp)
    xax /= np.linalg.norm(xax)
    yax = np.cross(z, xax)
    world = a + pts[:, :1] * xax + pts[:, 1:2] * yax + pts[:, 2:3] * z
    vol = np.pi * radius**2 * length / len(world)
    return world, np.full(len(world), vol)


def sample_sphere(center: Sequence[float], radius: float, dx: float, particles_per_cell: float = 8,
                  *, seed: Optional[int] = 0, jitter: float = 0.0):
    """Fill a solid sphere of ``radius`` (m) around ``center`` (m)."""
    c = np.asarray(center, float)
    if radius <= 0:
        raise ValueError(f"sample_sphere: radius must be > 0, got {radius}")
    pts, _ = _lattice(c - radius, c + radius, _spacing(dx, particles_per_cell), seed, jitter)
    pts = pts[np.linalg.norm(pts - c, axis=1) <= radius]
    return pts, np.full(len(pts), 4.0 / 3.0 * np.pi * radius**3 / len(pts))


_NO_VOLUME = ("sample_points: the point set encloses no volume at this resolution: an open surface (e.g. a scan seen "
              "only from above: close it against the table first) or a body thinner than three voxels")


def sample_points(points: np.ndarray, dx: float, particles_per_cell: float = 8, *, voxel: Optional[float] = None,
                  fill_interior: bool = True, fill_layers: bool = False, open_thin: bool = False,
                  align_lattice: bool = False, seed: Optional[int] = 0, jitter: float = 0.0):
    """Fill the solid occupied by a point set (e.g. a fused surface scan).

    Points are voxelised at ``voxel`` (m, default dx / 4) on voxels centred on a lattice; voxels are
    closed morphologically (gaps up to ``2 * voxel`` between points) and, with ``fill_interior``,
    enclosed cavities are filled, so a closed surface-only scan yields a solid body. With ``fill_layers``
    the holes of every horizontal layer (constant z) are filled too: a body closed around its sides but
    open at the top (walls seen from a low camera and their turned copies) becomes solid. With ``open_thin``
    the voxels are then opened (eroded and dilated by one voxel, 3 x 3 x 3): sheets and slivers thinner than
    three voxels go (a completion's film under a hovering end-effector: the grid of cells 4 voxels wide
    cannot carry them). With ``align_lattice`` the particle lattice spans the body's bounding box (between
    its outermost voxel centres) instead of the padded voxel grid, so that its outer rows lie half a
    lattice step inside each face of the box: otherwise a face gains or loses a row (a third of a cell at
    27 per cell) with how the lattice happens to meet it. The body's surface is
    put through the centres of its boundary voxels (where the scanned points are, to half a voxel), not
    at the voxels' outer faces, so the sampled volume carries no systematic outward bias.
    """
    from scipy import ndimage

    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"sample_points: need at least 4 finite points, got {len(pts)}")
    h = voxel or dx / 4.0
    pad = 3
    lo = pts.min(0) - pad * h
    idx = np.rint((pts - lo) / h).astype(int)
    dims = idx.max(0) + pad + 1
    occ = np.zeros(dims, bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    occ = ndimage.binary_closing(occ, structure=np.ones((3, 3, 3), bool), iterations=2)
    if fill_interior:
        occ = ndimage.binary_fill_holes(occ)
    if fill_layers:
        for k in range(occ.shape[2]):
            occ[:, :, k] = ndimage.binary_fill_holes(occ[:, :, k])
    if open_thin:
        occ = ndimage.binary_opening(occ, structure=np.ones((3, 3, 3), bool))
    # distance (in voxels) of every occupied voxel centre to the nearest empty one: 1 on the boundary
    # layer; interpolated, "distance >= 1" is the solid bounded by the boundary voxels' centres
    depth = ndimage.distance_transform_edt(occ)
    if depth.max() < 2.0:
        # no voxel lies inside the boundary layer: an open shell (a surface seen from one side, not closed),
        # whose particles would form a sheet one row thick wherever the lattice meets the layer
        raise ValueError(_NO_VOLUME)
    # a lattice offset from the voxel centres, so that no row of particles sits exactly on the surface
    if align_lattice:  # occupied voxels exist: the check above passed
        ix = [np.nonzero(occ.any(axis=tuple(j for j in range(3) if j != i)))[0] for i in range(3)]
        box_lo = lo + np.array([v[0] for v in ix]) * h
        box_hi = lo + np.array([v[-1] for v in ix]) * h
        cand, vol = _lattice(box_lo, np.maximum(box_hi, box_lo + h), _spacing(dx, particles_per_cell), seed, jitter)
    else:
        cand, vol = _lattice(lo - 0.5 * h, lo + (dims - 0.5) * h, _spacing(dx, particles_per_cell), seed, jitter)
    coords = ((cand - lo) / h).T
    inside = ndimage.map_coordinates(depth, coords, order=1, mode="constant", cval=0.0) >= 1.0 - 1e-9
    out = cand[inside]
    if len(out) == 0:
        raise ValueError(_NO_VOLUME)
    # the lattice rows near the surface fall in or out depending on how the lattice meets the surface;
    # the volume itself is measured on the voxels: interior voxels count whole, boundary voxels half
    boundary = occ & (depth < 1.5)
    volume = h**3 * (occ.sum() - 0.5 * boundary.sum())
    vol = volume / len(out)
    return out, np.full(len(out), vol)


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, dx: float, particles_per_cell: float = 8,
                *, seed: Optional[int] = 0, jitter: float = 0.0):
    """Fill the inside of a closed triangle mesh (vertices [V, 3] m, faces [F, 3] indices)."""
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    f = np.asarray(faces, np.int32).reshape(-1, 3)
    if len(f) == 0 or f.max() >= len(v) or f.min() < 0:
        raise ValueError("sample_mesh: faces must index the vertices")
    cand, vol = _lattice(v.min(0), v.max(0), _spacing(dx, particles_per_cell), seed, jitter)
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device="cpu"), indices=wp.array(f.reshape(-1), dtype=int, device="cpu"))
    q = wp.array(cand.astype(np.float32), dtype=wp.vec3, device="cpu")
    inside = wp.zeros(len(cand), dtype=int, device="cpu")
    wp.launch(_inside_mesh_kernel, dim=len(cand), inputs=[mesh.id, q, float(np.ptp(v, axis=0).max() * 2)],
              outputs=[inside], device="cpu")
    out = cand[inside.numpy().astype(bool)]
    if len(out) == 0:
        raise ValueError("sample_mesh: no lattice point lies inside the mesh (is it closed?)")
    return out, np.full(len(out), vol)


@wp.kernel
def _inside_mesh_kernel(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), max_dist: float, inside: wp.array(dtype=int)):
    """Mark lattice points that lie inside a closed mesh (winding-number sign)."""
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, pts[i], max_dist)
    if q.result and q.sign < 0.0:
        inside[i] = 1
