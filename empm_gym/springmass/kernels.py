"""Warp kernels of the spring-mass step: spring and dashpot forces, control springs, semi-implicit Euler
with table and end-effector contact.

End-effector shapes and Coulomb projection are the MPM solver's (:mod:`empm_gym.sim.kernels`), so both
model families see the same grippers and the same friction law.
"""

from __future__ import annotations

import warp as wp

from empm_gym.sim.kernels import coulomb_project, shape_sdf_normal


@wp.kernel
def spring_force_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=float),
    weight: wp.array(dtype=float),
    log_scale: wp.array(dtype=float),
    stiffness: wp.array(dtype=float),
    damping: wp.array(dtype=float),
    f: wp.array(dtype=wp.vec3),
):
    """Hooke spring plus dashpot along each spring: k (l - L) + c dl/dt [N], k = Y w e^s, c = eta w."""
    s = wp.tid()
    ij = springs[s]
    i = ij[0]
    j = ij[1]
    d = x[j] - x[i]
    l = wp.length(d)
    n = d / wp.max(l, 1.0e-9)
    w = weight[s]
    k = stiffness[0] * w * wp.exp(log_scale[s])
    c = damping[0] * w
    mag = k * (l - rest[s]) + c * wp.dot(v[j] - v[i], n)
    fs = mag * n
    wp.atomic_add(f, i, fs)
    wp.atomic_sub(f, j, fs)


@wp.kernel
def control_force_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    attach_particle: wp.array(dtype=int),
    attach_ee: wp.array(dtype=int),
    attach_local: wp.array(dtype=wp.vec3),
    ee_pos: wp.array(dtype=wp.vec3),
    ee_rot: wp.array(dtype=wp.quat),
    ee_vel: wp.array(dtype=wp.vec3),
    ee_omega: wp.array(dtype=wp.vec3),
    ee_count: int,
    step: int,
    omega_c: float,
    f: wp.array(dtype=wp.vec3),
):
    """Critically damped control spring from a held particle to its anchor in the closed gripper's frame
    (natural frequency ``omega_c`` [rad/s] whatever the particle's mass)."""
    a = wp.tid()
    p = attach_particle[a]
    e = step * ee_count + attach_ee[a]
    c = ee_pos[e]
    anchor = c + wp.quat_rotate(ee_rot[e], attach_local[a])
    v_anchor = ee_vel[e] + wp.cross(ee_omega[e], anchor - c)
    m = mass[p]
    fa = m * omega_c * omega_c * (anchor - x[p]) + 2.0 * m * omega_c * (v_anchor - v[p])
    wp.atomic_add(f, p, fa)


_INTEGRATE = {}


def integrate_kernel(ee_count: int):
    """The integration kernel for ``ee_count`` end-effectors (its contact loop unrolled: Warp's adjoint does
    not replay variables reassigned in a dynamic loop)."""
    if ee_count not in _INTEGRATE:
        _INTEGRATE[ee_count] = _make_integrate_kernel(ee_count)
    return _INTEGRATE[ee_count]


def _make_integrate_kernel(ee_count: int):
    EE = ee_count

    @wp.kernel(module="unique")
    def integrate(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        attached: wp.array(dtype=int),
        gravity: wp.vec3,
        dt: float,
        drag: float,
        has_table: int,
        table_z: float,
        table_mu: float,
        contact_radius: float,
        ee_shape: wp.array(dtype=int),
        ee_radius: wp.array(dtype=float),
        ee_half_height: wp.array(dtype=float),
        ee_half_extents: wp.array(dtype=wp.vec3),
        ee_friction: wp.array(dtype=float),
        ee_pos: wp.array(dtype=wp.vec3),
        ee_rot: wp.array(dtype=wp.quat),
        ee_vel: wp.array(dtype=wp.vec3),
        ee_omega: wp.array(dtype=wp.vec3),
        step: int,
        x_out: wp.array(dtype=wp.vec3),
        v_out: wp.array(dtype=wp.vec3),
    ):
        """Semi-implicit Euler: v += dt (f / m + g), drag, contacts (velocity projection where the step would
        end in contact, then push-out of what still penetrates); x += dt v. Fixed particles (inv_mass 0) keep their position."""
        p = wp.tid()
        im = inv_mass[p]
        xp = x[p]
        if im == 0.0:
            x_out[p] = xp
            v_out[p] = wp.vec3(0.0)
            return
        vn = (v[p] + dt * (im * f[p] + gravity)) * wp.exp(-dt * drag)
        held = attached[p]
        r = contact_radius
        # contact where the particle would touch a shape (at its new pose; not the gripper holding the
        # particle) or the table after this step: Coulomb projection of the relative velocity
        for k in range(EE):
            e = (step + 1) * EE + k
            if ee_shape[k] >= 0 and k != held:
                c = ee_pos[e]
                xq = xp + dt * vn
                d, n = shape_sdf_normal(ee_shape[k], xq, c, ee_rot[e], ee_radius[k], ee_half_height[k],
                                        ee_half_extents[k])
                if d < r:
                    v_ee = ee_vel[step * EE + k] + wp.cross(ee_omega[step * EE + k], xq - c)
                    vn = v_ee + coulomb_project(vn - v_ee, n, ee_friction[k])
        if has_table != 0:
            if xp[2] + dt * vn[2] < table_z + r:
                vn = coulomb_project(vn, wp.vec3(0.0, 0.0, 1.0), table_mu)
        xn = xp + dt * vn
        # push-out: a particle still inside a shape at its new pose (or below the table) is moved to its surface
        for k in range(EE):
            e = (step + 1) * EE + k
            if ee_shape[k] >= 0 and k != held:
                d, n = shape_sdf_normal(ee_shape[k], xn, ee_pos[e], ee_rot[e], ee_radius[k], ee_half_height[k],
                                        ee_half_extents[k])
                if d < r:
                    xn = xn + (r - d) * n
        if has_table != 0:
            if xn[2] < table_z + r:
                xn = wp.vec3(xn[0], xn[1], table_z + r)
        x_out[p] = xn
        v_out[p] = vn

    return integrate


@wp.kernel
def sdf_kernel(
    x: wp.array(dtype=wp.vec3),
    shape: int,
    c: wp.vec3,
    q: wp.quat,
    radius: float,
    half_height: float,
    half_extents: wp.vec3,
    out: wp.array(dtype=float),
):
    """Signed distance [m] of each point to one end-effector shape (negative inside)."""
    p = wp.tid()
    d, n = shape_sdf_normal(shape, x[p], c, q, radius, half_height, half_extents)
    out[p] = d
