"""Warp kernels and functions of the MLS-MPM / APIC step (quadratic B-splines, batched worlds)."""

from __future__ import annotations

import warp as wp

SHAPE_SPHERE = wp.constant(0)
SHAPE_CAPSULE = wp.constant(1)
SHAPE_BOX = wp.constant(2)
SQRT_2_3 = wp.constant(0.816496580927726)


# ---------------------------------------------------------------------------
# constitutive model
# ---------------------------------------------------------------------------


@wp.func
def lame_parameters(E: float, nu: float):
    """(mu, lambda) [Pa] from Young's modulus and Poisson's ratio."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


@wp.func
def von_mises_return(F: wp.mat33, mu: float, yield_stress: float, min_singular: float):
    """Project a trial elastic F onto the von Mises yield surface (Hencky strain, volume preserving).

    The yield condition is sqrt(3/2) * |dev(tau)| <= yield_stress with tau = 2 mu eps + lambda tr(eps) I,
    eps the logarithmic (Hencky) strain; plastic flow is deviatoric, so det(F) is kept.
    """
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    s = wp.vec3(wp.max(s[0], min_singular), wp.max(s[1], min_singular), wp.max(s[2], min_singular))
    eps = wp.vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))
    tr = (eps[0] + eps[1] + eps[2]) / 3.0
    eps_hat = eps - wp.vec3(tr, tr, tr)
    n2 = wp.dot(eps_hat, eps_hat)
    out = F
    if n2 > 1.0e-20:
        norm = wp.sqrt(n2)
        dgamma = norm - SQRT_2_3 * yield_stress / (2.0 * mu)
        if dgamma > 0.0:
            eps_new = eps - (dgamma / norm) * eps_hat
            S = wp.diag(wp.vec3(wp.exp(eps_new[0]), wp.exp(eps_new[1]), wp.exp(eps_new[2])))
            out = U * S * wp.transpose(V)
    return out


@wp.func
def damaged_kirchhoff(F: wp.mat33, mu: float, lam: float, damage: float):
    """Fixed-corotated Kirchhoff stress [Pa] with the deviatoric part, and the volumetric part under
    tension (J > 1), scaled by (1 - damage): a broken particle resists compression but not pulling."""
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    R = U * wp.transpose(V)
    J = wp.determinant(F)
    keep = 1.0 - damage
    vol = lam * J * (J - 1.0)
    if J > 1.0:
        vol = vol * keep
    return (2.0 * mu * keep) * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * vol


@wp.func
def fixed_corotated_kirchhoff(F: wp.mat33, mu: float, lam: float):
    """Kirchhoff stress tau = P F^T of the fixed-corotated model [Pa] (an undamaged particle)."""
    return damaged_kirchhoff(F, mu, lam, 0.0)


@wp.func
def damage_from_stretch(F: wp.mat33, strain: float, softening: float):
    """Damage [0, 1] reached by the elastic F: a smoothstep of the largest principal strain (stretch - 1)
    from ``strain`` to ``strain + softening``."""
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    e = wp.max(s[0], wp.max(s[1], s[2])) - 1.0
    r = wp.clamp((e - strain) / softening, 0.0, 1.0)
    return r * r * (3.0 - 2.0 * r)


@wp.func
def grip_hold(v_rel: wp.vec3, limit: float):
    """Relative velocity left after a grip that can remove at most ``limit`` [m/s] of it (Coulomb: sticks
    when |v_rel| <= limit)."""
    n2 = wp.dot(v_rel, v_rel)
    out = wp.vec3(0.0)
    if n2 > limit * limit:
        n = wp.sqrt(n2)
        out = v_rel * (1.0 - limit / n)
    return out


@wp.kernel
def eval_kirchhoff_kernel(F: wp.array(dtype=wp.mat33), E: float, nu: float, tau: wp.array(dtype=wp.mat33)):
    """Evaluate the fixed-corotated Kirchhoff stress for a batch of F (tests and tools)."""
    i = wp.tid()
    mu, lam = lame_parameters(E, nu)
    tau[i] = fixed_corotated_kirchhoff(F[i], mu, lam)


@wp.kernel
def eval_return_mapping_kernel(
    F: wp.array(dtype=wp.mat33), E: float, nu: float, yield_stress: float, out: wp.array(dtype=wp.mat33)
):
    """Apply the von Mises return mapping to a batch of trial F (tests and tools)."""
    i = wp.tid()
    mu, lam = lame_parameters(E, nu)
    out[i] = von_mises_return(F[i], mu, yield_stress, 1.0e-3)


# ---------------------------------------------------------------------------
# end-effector shapes
# ---------------------------------------------------------------------------


@wp.func
def shape_sdf_normal(
    shape: int, p: wp.vec3, c: wp.vec3, q: wp.quat, radius: float, half_height: float, half_extents: wp.vec3
):
    """Signed distance [m] from p to the shape surface (negative inside) and the outward normal."""
    d = float(1.0e6)
    n = wp.vec3(0.0, 0.0, 1.0)
    local = wp.quat_rotate_inv(q, p - c)
    if shape == SHAPE_SPHERE:
        r = p - c
        l = wp.length(r)
        d = l - radius
        if l > 1.0e-9:
            n = r / l
    elif shape == SHAPE_CAPSULE:
        z = wp.clamp(local[2], -half_height, half_height)
        r = local - wp.vec3(0.0, 0.0, z)
        l = wp.length(r)
        d = l - radius
        if l > 1.0e-9:
            n = wp.quat_rotate(q, r / l)
    elif shape == SHAPE_BOX:
        a = wp.vec3(wp.abs(local[0]), wp.abs(local[1]), wp.abs(local[2])) - half_extents
        outside = wp.vec3(wp.max(a[0], 0.0), wp.max(a[1], 0.0), wp.max(a[2], 0.0))
        lo = wp.length(outside)
        inside = wp.min(wp.max(a[0], wp.max(a[1], a[2])), 0.0)
        d = lo + inside
        sx = wp.sign(local[0])
        sy = wp.sign(local[1])
        sz = wp.sign(local[2])
        if lo > 1.0e-9:
            nl = wp.vec3(sx * outside[0], sy * outside[1], sz * outside[2]) / lo
            n = wp.quat_rotate(q, nl)
        else:
            if a[0] >= a[1] and a[0] >= a[2]:
                n = wp.quat_rotate(q, wp.vec3(sx, 0.0, 0.0))
            elif a[1] >= a[2]:
                n = wp.quat_rotate(q, wp.vec3(0.0, sy, 0.0))
            else:
                n = wp.quat_rotate(q, wp.vec3(0.0, 0.0, sz))
    return d, n


@wp.func
def coulomb_project(v_rel: wp.vec3, n: wp.vec3, mu: float):
    """Remove the approaching normal velocity and apply Coulomb friction to the tangential part."""
    vn = wp.dot(v_rel, n)
    out = v_rel
    if vn < 0.0:
        vt = v_rel - vn * n
        vt2 = wp.dot(vt, vt)
        limit = -mu * vn
        if vt2 <= limit * limit:
            out = wp.vec3(0.0)  # sticking: inside the friction cone
        else:
            vt_norm = wp.sqrt(vt2)
            out = vt * (1.0 - limit / vt_norm)
    return out


# ---------------------------------------------------------------------------
# MPM step
# ---------------------------------------------------------------------------


@wp.func
def bspline_weights(fx: wp.vec3):
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.matrix_from_rows(w0, w1, w2)


@wp.func
def cell_base(x: wp.vec3, origin: wp.vec3, inv_dx: float, res: wp.vec3i):
    xl = (x - origin) * inv_dx
    bx = wp.clamp(int(xl[0] - 0.5), 0, res[0] - 3)
    by = wp.clamp(int(xl[1] - 0.5), 0, res[1] - 3)
    bz = wp.clamp(int(xl[2] - 0.5), 0, res[2] - 3)
    base = wp.vec3i(bx, by, bz)
    fx = xl - wp.vec3(float(bx), float(by), float(bz))
    return base, fx


@wp.kernel
def p2g_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    damage: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    particle_vol: wp.array(dtype=float),
    particle_E: wp.array(dtype=float),
    particle_nu: wp.array(dtype=float),
    particle_density: wp.array(dtype=float),
    particle_viscosity: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    res: wp.vec3i,
    dt: float,
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
):
    """Scatter particle mass, momentum and stress impulse to the grid (MLS-MPM / APIC)."""
    p = wp.tid()
    w = particle_world[p]
    vol = particle_vol[p]
    mass = particle_density[p] * vol
    mu, lam = lame_parameters(particle_E[p], particle_nu[p])
    Fp = F[p]
    Cp = C[p]
    tau = damaged_kirchhoff(Fp, mu, lam, damage[p])
    # Kelvin-Voigt viscous stress (zero when eta = 0); APIC's C is the velocity gradient, so
    # tau_v = J eta (C + C^T). No branch: a data-dependent branch here slows the adjoint kernel.
    tau = tau + (particle_viscosity[p] * wp.determinant(Fp)) * (Cp + wp.transpose(Cp))
    affine = (-dt * vol * 4.0 * inv_dx * inv_dx) * tau + mass * Cp
    mv = mass * v[p]
    base, fx = cell_base(x[p], origin, inv_dx, res)
    W = bspline_weights(fx)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                wp.atomic_add(grid_mv, w, base[0] + i, base[1] + j, base[2] + k, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, w, base[0] + i, base[1] + j, base[2] + k, weight * mass)


def make_grid_update_kernel(ee_count: int):
    """Build the grid-update kernel for a fixed number of end-effectors per world (loop unrolled)."""
    EE = ee_count

    @wp.kernel(module="unique")
    def grid_update_kernel(
        grid_m: wp.array4d(dtype=float),
        grid_mv: wp.array4d(dtype=wp.vec3),
        origin: wp.vec3,
        dx: float,
        res: wp.vec3i,
        dt: float,
        gravity: wp.vec3,
        boundary_cells: int,
        has_table: int,
        table_z: float,
        world_table_friction: wp.array(dtype=float),
        ee_shape: wp.array(dtype=int),
        ee_radius: wp.array(dtype=float),
        ee_half_height: wp.array(dtype=float),
        ee_half_extents: wp.array(dtype=wp.vec3),
        ee_friction: wp.array(dtype=float),
        ee_gripper: wp.array(dtype=int),
        ee_pos: wp.array(dtype=wp.vec3),
        ee_rot: wp.array(dtype=wp.quat),
        ee_vel: wp.array(dtype=wp.vec3),
        ee_omega: wp.array(dtype=wp.vec3),
        ee_grip: wp.array(dtype=int),
        world_grip_friction: wp.array(dtype=float),
        clear_inputs: int,
        grid_v: wp.array4d(dtype=wp.vec3),
    ):
        """Grid velocity update: momentum / mass, gravity, end-effectors, table and walls.

        With ``clear_inputs`` the touched mass and momentum nodes are zeroed once read, which saves the
        next substep two full-grid clears (only when no tape needs those values again).
        """
        w, i, j, k = wp.tid()
        m = grid_m[w, i, j, k]
        mv = grid_mv[w, i, j, k]
        if clear_inputs != 0 and m != 0.0:
            grid_m[w, i, j, k] = 0.0
            grid_mv[w, i, j, k] = wp.vec3(0.0)
        vel = wp.vec3(0.0)
        if m > 1.0e-12:
            vel = mv / m + dt * gravity
            node = origin + wp.vec3(float(i), float(j), float(k)) * dx
            for e in range(EE):
                s = w * EE + e
                shape = ee_shape[s]
                if shape >= 0:
                    c = ee_pos[s]
                    d, n = shape_sdf_normal(shape, node, c, ee_rot[s], ee_radius[s], ee_half_height[s], ee_half_extents[s])
                    if d < 0.0:
                        v_ee = ee_vel[s] + wp.cross(ee_omega[s], node - c)
                        if ee_grip[s] != 0:
                            # a closed gripper carries the nodes it covers, by friction: it removes at most
                            # grip_friction * g0 * dt of their relative velocity per substep (g0 = 9.81 m/s^2:
                            # the squeeze presses with the grasped weight; the rigid,
                            # Dirichlet grip when that is large)
                            limit = wp.min(world_grip_friction[w] * 9.81 * dt, 1.0e10)
                            vel = v_ee + grip_hold(vel - v_ee, limit)
                        elif ee_gripper[s] == 0 or d > -0.5 * dx:
                            # a tool pushes what it covers out through its nearest face; an open gripper
                            # only within half a cell of its surface (what it held lies free inside)
                            vel = v_ee + coulomb_project(vel - v_ee, n, ee_friction[s])
            if has_table != 0:
                # the node layer nearest the table plane (and any below) carries the table, so the table
                # sits within half a cell of its height however the grid lines up with it
                if node[2] < table_z + 0.5 * dx:
                    vel = coulomb_project(vel, wp.vec3(0.0, 0.0, 1.0), world_table_friction[w])
            b = boundary_cells
            if i < b and vel[0] < 0.0:
                vel = wp.vec3(0.0, vel[1], vel[2])
            if i >= res[0] - b and vel[0] > 0.0:
                vel = wp.vec3(0.0, vel[1], vel[2])
            if j < b and vel[1] < 0.0:
                vel = wp.vec3(vel[0], 0.0, vel[2])
            if j >= res[1] - b and vel[1] > 0.0:
                vel = wp.vec3(vel[0], 0.0, vel[2])
            if k < b and vel[2] < 0.0:
                vel = wp.vec3(vel[0], vel[1], 0.0)
            if k >= res[2] - b and vel[2] > 0.0:
                vel = wp.vec3(vel[0], vel[1], 0.0)
        grid_v[w, i, j, k] = vel

    return grid_update_kernel


@wp.kernel
def g2p_kernel(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    damage: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    particle_E: wp.array(dtype=float),
    particle_nu: wp.array(dtype=float),
    particle_yield: wp.array(dtype=float),
    particle_plastic: wp.array(dtype=int),
    particle_fracture_strain: wp.array(dtype=float),
    particle_fracture_softening: wp.array(dtype=float),
    grid_v: wp.array4d(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    res: wp.vec3i,
    dt: float,
    min_singular: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    damage_out: wp.array(dtype=float),
):
    """Gather velocity and affine field, update F (with plastic return mapping) and advect particles."""
    p = wp.tid()
    w = particle_world[p]
    base, fx = cell_base(x[p], origin, inv_dx, res)
    W = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gv = grid_v[w, base[0] + i, base[1] + j, base[2] + k]
                new_v = new_v + weight * gv
                new_C = new_C + (4.0 * inv_dx * inv_dx * weight) * wp.outer(gv, dpos)
    Fn = (wp.identity(n=3, dtype=float) + dt * new_C) * F[p]
    if particle_plastic[p] != 0:
        mu, lam = lame_parameters(particle_E[p], particle_nu[p])
        Fn = von_mises_return(Fn, mu, particle_yield[p], min_singular)
    # damage only grows (fracture effect; a threshold of 1e30 keeps it at 0)
    dmg = damage[p]
    strain = particle_fracture_strain[p]
    if strain < 1.0e20:
        dmg = wp.max(dmg, damage_from_stretch(Fn, strain, particle_fracture_softening[p]))
    damage_out[p] = dmg
    xn = x[p] + dt * new_v
    # keep every particle's stencil inside the grid
    lo = origin + wp.vec3(dx)
    hi = origin + wp.vec3(float(res[0] - 2), float(res[1] - 2), float(res[2] - 2)) * dx
    xn = wp.vec3(wp.clamp(xn[0], lo[0], hi[0]), wp.clamp(xn[1], lo[1], hi[1]), wp.clamp(xn[2], lo[2], hi[2]))
    x_out[p] = xn
    v_out[p] = new_v
    C_out[p] = new_C
    F_out[p] = Fn


@wp.kernel
def expand_materials_kernel(
    particle_world: wp.array(dtype=int),
    particle_stiffness: wp.array(dtype=float),
    particle_body_coord: wp.array(dtype=wp.vec3),
    world_E: wp.array(dtype=float),
    world_nu: wp.array(dtype=float),
    world_density: wp.array(dtype=float),
    world_yield: wp.array(dtype=float),
    world_plastic: wp.array(dtype=int),
    world_viscosity: wp.array(dtype=float),
    world_stiffness_slope: wp.array(dtype=wp.vec3),
    world_fracture_strain: wp.array(dtype=float),
    world_fracture_softening: wp.array(dtype=float),
    particle_E: wp.array(dtype=float),
    particle_nu: wp.array(dtype=float),
    particle_density: wp.array(dtype=float),
    particle_yield: wp.array(dtype=float),
    particle_plastic: wp.array(dtype=int),
    particle_viscosity: wp.array(dtype=float),
    particle_fracture_strain: wp.array(dtype=float),
    particle_fracture_softening: wp.array(dtype=float),
):
    """Copy each world's material to its particles (E scaled by the per-particle stiffness multiplier and
    the heterogeneous-stiffness field exp(slope . u))."""
    p = wp.tid()
    w = particle_world[p]
    particle_E[p] = world_E[w] * particle_stiffness[p] * wp.exp(wp.dot(world_stiffness_slope[w], particle_body_coord[p]))
    particle_nu[p] = world_nu[w]
    particle_density[p] = world_density[w]
    particle_yield[p] = world_yield[w]
    particle_plastic[p] = world_plastic[w]
    particle_viscosity[p] = world_viscosity[w]
    particle_fracture_strain[p] = world_fracture_strain[w]
    particle_fracture_softening[p] = world_fracture_softening[w]


@wp.kernel
def reduce_material_grads_kernel(
    particle_world: wp.array(dtype=int),
    particle_stiffness: wp.array(dtype=float),
    particle_body_coord: wp.array(dtype=wp.vec3),
    world_E: wp.array(dtype=float),
    world_stiffness_slope: wp.array(dtype=wp.vec3),
    gE: wp.array(dtype=float),
    gnu: wp.array(dtype=float),
    grho: wp.array(dtype=float),
    gys: wp.array(dtype=float),
    geta: wp.array(dtype=float),
    gfs: wp.array(dtype=float),
    gfw: wp.array(dtype=float),
    world_E_grad: wp.array(dtype=float),
    world_nu_grad: wp.array(dtype=float),
    world_density_grad: wp.array(dtype=float),
    world_yield_grad: wp.array(dtype=float),
    world_viscosity_grad: wp.array(dtype=float),
    stiffness_grad: wp.array(dtype=float),
    world_stiffness_slope_grad: wp.array(dtype=wp.vec3),
    world_fracture_strain_grad: wp.array(dtype=float),
    world_fracture_softening_grad: wp.array(dtype=float),
):
    """Adjoint of expand_materials_kernel: sum per-particle parameter gradients into their worlds."""
    p = wp.tid()
    w = particle_world[p]
    u = particle_body_coord[p]
    field = wp.exp(wp.dot(world_stiffness_slope[w], u))
    Ep = world_E[w] * particle_stiffness[p] * field
    wp.atomic_add(world_E_grad, w, gE[p] * particle_stiffness[p] * field)
    wp.atomic_add(world_nu_grad, w, gnu[p])
    wp.atomic_add(world_density_grad, w, grho[p])
    wp.atomic_add(world_yield_grad, w, gys[p])
    wp.atomic_add(world_viscosity_grad, w, geta[p])
    wp.atomic_add(world_stiffness_slope_grad, w, (gE[p] * Ep) * u)
    wp.atomic_add(world_fracture_strain_grad, w, gfs[p])
    wp.atomic_add(world_fracture_softening_grad, w, gfw[p])
    stiffness_grad[p] = stiffness_grad[p] + gE[p] * world_E[w] * field


@wp.kernel
def ee_integrate_kernel(
    pos: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
    vel: wp.array(dtype=wp.vec3),
    omega: wp.array(dtype=wp.vec3),
    dt: float,
    pos_out: wp.array(dtype=wp.vec3),
    rot_out: wp.array(dtype=wp.quat),
):
    """Advance kinematic end-effector poses by one step of their commanded velocities."""
    s = wp.tid()
    pos_out[s] = pos[s] + dt * vel[s]
    q = rot[s]
    w = omega[s]
    dq = wp.quat(w[0], w[1], w[2], 0.0) * q
    qn = q + (0.5 * dt) * dq
    rot_out[s] = wp.normalize(qn)


@wp.kernel
def check_state_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    particle_world: wp.array(dtype=int),
    max_speed: float,
    flags: wp.array(dtype=int),
):
    """Flag worlds whose particles hold non-finite values (1) or exceed the speed limit (2)."""
    p = wp.tid()
    xp = x[p]
    vp = v[p]
    Fp = F[p]
    bad = int(0)
    s = xp[0] + xp[1] + xp[2] + vp[0] + vp[1] + vp[2]
    for r in range(3):
        for c in range(3):
            s = s + Fp[r, c]
    if not wp.isfinite(s):
        bad = 1
    elif wp.length(vp) > max_speed:
        bad = 2
    if bad > 0:
        wp.atomic_max(flags, particle_world[p], bad)
