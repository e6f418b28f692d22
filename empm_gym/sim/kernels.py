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
def symmetric_eigenvalues(A: wp.mat33):
    """The eigenvalues of a symmetric 3 x 3 matrix in closed form (the trigonometric solution of its
    characteristic cubic), largest first; accurate to about 1e-6 of |A| in float32, 1e-4 where two
    eigenvalues are equal (acos at +-1)."""
    q = wp.trace(A) / 3.0
    p1 = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
    d0 = A[0, 0] - q
    d1 = A[1, 1] - q
    d2 = A[2, 2] - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1
    out = wp.vec3(q, q, q)
    if p2 > 1.0e-30:
        p = wp.sqrt(p2 / 6.0)
        B = (A - wp.identity(n=3, dtype=float) * q) * (1.0 / p)
        r = wp.clamp(0.5 * wp.determinant(B), -1.0, 1.0)
        phi = wp.acos(r) / 3.0
        e0 = q + 2.0 * p * wp.cos(phi)
        e2 = q + 2.0 * p * wp.cos(phi + 2.0943951023931953)
        out = wp.vec3(e0, 3.0 * q - e0 - e2, e2)
    return out


#: von_mises_return skips its SVD where the closed-form eigenvalues put the deviatoric Hencky strain under
#: ELASTIC_CHECK_MARGIN times the yield strain less ELASTIC_CHECK_SLACK [-]: their float32 error is at most
#: about 1e-4 of |F^T F| (two equal eigenvalues), 5e-5 in strain.
ELASTIC_CHECK_MARGIN = wp.constant(0.95)
ELASTIC_CHECK_SLACK = wp.constant(2.0e-4)


@wp.func
def surely_elastic(F: wp.mat33, threshold: float, min_singular: float):
    """1 when F's deviatoric Hencky strain is clearly under ``threshold`` (the return mapping would keep F),
    from the eigenvalues of F^T F (the squared singular values); 0 when it may not be, F is inverted, or a
    singular value is under min_singular. A cheap test before von_mises_return's SVD; control flow only."""
    out = int(0)
    if wp.determinant(F) > 0.0:
        mu2 = symmetric_eigenvalues(wp.transpose(F) * F)
        if mu2[2] > min_singular * min_singular:
            eps = 0.5 * wp.vec3(wp.log(mu2[0]), wp.log(mu2[1]), wp.log(mu2[2]))
            tr = (eps[0] + eps[1] + eps[2]) / 3.0
            eps_hat = eps - wp.vec3(tr, tr, tr)
            bound = ELASTIC_CHECK_MARGIN * threshold - ELASTIC_CHECK_SLACK
            if bound > 0.0 and wp.dot(eps_hat, eps_hat) < bound * bound:
                out = 1
    return out


@wp.func_grad(surely_elastic)
def adj_surely_elastic(F: wp.mat33, threshold: float, min_singular: float, adj_ret: int):
    """surely_elastic only chooses a branch: no gradient flows through it (Warp's automatic adjoint would
    differentiate acos at +-1, where it is infinite)."""
    pass


@wp.func
def von_mises_return(F: wp.mat33, mu: float, yield_stress: float, min_singular: float):
    """Project a trial elastic F onto the von Mises yield surface (Hencky strain, volume preserving).

    The yield condition is sqrt(3/2) * |dev(tau)| <= yield_stress with tau = 2 mu eps + lambda tr(eps) I,
    eps the logarithmic (Hencky) strain; plastic flow is deviatoric, so det(F) is kept. A particle that
    surely_elastic finds well inside the surface keeps F without an SVD (the result is the same).
    """
    out = F
    threshold = SQRT_2_3 * yield_stress / (2.0 * mu)
    if surely_elastic(F, threshold, min_singular) == 0:
        out = von_mises_project(F, threshold, min_singular)
    return out


@wp.func
def von_mises_project(F: wp.mat33, threshold: float, min_singular: float):
    """von_mises_return's projection through F's SVD: the deviatoric Hencky strain scaled back to
    ``threshold`` [-] when above it."""
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
        dgamma = norm - threshold
        if dgamma > 0.0:
            eps_new = eps - (dgamma / norm) * eps_hat
            S = wp.diag(wp.vec3(wp.exp(eps_new[0]), wp.exp(eps_new[1]), wp.exp(eps_new[2])))
            out = U * S * wp.transpose(V)
    return out


@wp.func
def svd_polar(F: wp.mat33):
    """svd3's signed SVD of F (U and V rotations, the last singular value negative when det F < 0) and the
    polar rotation R = U V^T."""
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    return U, s, V, U * wp.transpose(V)


@wp.func
def cofactor(F: wp.mat33):
    """d det(F) / dF = det(F) F^{-T}, without dividing: row i is the cross product of the two other rows."""
    r0 = F[0]
    r1 = F[1]
    r2 = F[2]
    return wp.matrix_from_rows(wp.cross(r1, r2), wp.cross(r2, r0), wp.cross(r0, r1))


#: Scaled Newton iterations of polar_rotation before it falls back to the SVD (F within a stretch ratio of
#: about 10^3 converges in fewer), and the change of an iterate [-] under which it has converged.
POLAR_NEWTON_ITERS = wp.constant(8)
POLAR_NEWTON_TOL = wp.constant(1.0e-6)
#: det F under which polar_rotation takes the SVD at once (an inverted or nearly flat F, whose signed
#: rotation Newton's iteration does not give).
POLAR_NEWTON_MIN_DET = wp.constant(1.0e-3)


@wp.func
def polar_newton(F: wp.mat33):
    """Higham's scaled Newton iteration for the rotation R of F = R S (S symmetric): X <- (g X + (g X)^-T) / 2,
    g = |det X|^(-1/3) in the first three iterations, from X = F. Returns (R, 1) once an iterate changes by
    less than POLAR_NEWTON_TOL, and (F, 0) when det F <= POLAR_NEWTON_MIN_DET (an inverted or nearly flat F,
    whose signed rotation this iteration does not give) or it did not converge in POLAR_NEWTON_ITERS."""
    X = F
    done = int(0)
    if wp.determinant(F) > POLAR_NEWTON_MIN_DET:
        for _it in range(POLAR_NEWTON_ITERS):
            if done == 0:
                d = wp.determinant(X)
                g = float(1.0)
                if _it < 3:
                    g = wp.pow(d, -1.0 / 3.0)
                Xn = 0.5 * (g * X + (1.0 / (g * d)) * cofactor(X))
                diff = Xn - X
                X = Xn
                if wp.ddot(diff, diff) < POLAR_NEWTON_TOL * POLAR_NEWTON_TOL:
                    done = 1
    if done == 0:
        X = F
    return X, done


@wp.func
def polar_rotation(F: wp.mat33):
    """The rotation R of F's polar decomposition F = R S (S symmetric), as svd_polar's U V^T.

    polar_newton's few iterations are about three times cheaper than Warp's svd3 on the CPU and more
    accurate (svd3's R is off by up to 4e-5 at 1 % strain, 1e-7 here); where they do not apply (inverted,
    nearly flat, not converged) it is svd_polar's signed rotation."""
    R, ok = polar_newton(F)
    if ok == 0:
        U, s, V, Rs = svd_polar(F)
        R = Rs
    return R


@wp.func
def vee(A: wp.mat33):
    """The axial vector a of a skew matrix A = [a]x (A v = a x v)."""
    return wp.vec3(A[2, 1], A[0, 2], A[1, 0])


@wp.func
def skew(a: wp.vec3):
    """[a]x, the matrix of v -> a x v."""
    return wp.mat33(0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0)


@wp.func
def polar_rotation_adjoint(F: wp.mat33, R: wp.mat33, newton: int, M: wp.mat33):
    """dL/dF through the polar rotation R of F (``newton``: polar_newton's flag), given M = dL/dR:
    R [z]x with z = (tr(S) I - S)^-1 vee(N - N^T),
    N = R^T M, S = R^T F (R^T dR = [w]x with (tr(S) I - S) w = vee(R^T dF - dF^T R); tr(S) I - S has the
    eigenvalues s_i + s_j). Where polar_newton does not apply, the same derivative from svd3's signed SVD:
    U Y V^T with Y_ij = (Mt_ij - Mt_ji) / (s_i + s_j), Mt = U^T M V, which holds because U and V are rotations
    and the last singular value is negative when det F < 0."""
    out = wp.mat33()
    if newton != 0:
        S = wp.transpose(R) * F
        S = 0.5 * (S + wp.transpose(S))
        K = wp.identity(n=3, dtype=float) * wp.trace(S) - S
        N = wp.transpose(R) * M
        z = wp.inverse(K) * vee(N - wp.transpose(N))
        out = R * skew(z)
    else:
        U, s, V, Rs = svd_polar(F)
        Mt = wp.transpose(U) * M * V
        y01 = (Mt[0, 1] - Mt[1, 0]) / polar_pair_denominator(s[0] + s[1])
        y02 = (Mt[0, 2] - Mt[2, 0]) / polar_pair_denominator(s[0] + s[2])
        y12 = (Mt[1, 2] - Mt[2, 1]) / polar_pair_denominator(s[1] + s[2])
        Y = wp.mat33(0.0, y01, y02, -y01, 0.0, y12, -y02, -y12, 0.0)
        out = U * Y * wp.transpose(V)
    return out


@wp.func
def damaged_kirchhoff(F: wp.mat33, mu: float, lam: float, damage: float):
    """Fixed-corotated Kirchhoff stress [Pa] with the deviatoric part, and the volumetric part under
    tension (J > 1), scaled by (1 - damage): a broken particle resists compression but not pulling."""
    R = polar_rotation(F)
    J = wp.determinant(F)
    keep = 1.0 - damage
    vol = lam * J * (J - 1.0)
    if J > 1.0:
        vol = vol * keep
    return (2.0 * mu * keep) * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * vol


#: Smallest |s_i + s_j| the polar rotation's adjoint divides by (signed singular values; the rotation is
#: undefined where two of them cancel, as when F flattens or inverts so that s_2 = -s_3).
POLAR_ADJOINT_EPS = wp.constant(1.0e-6)


@wp.func
def polar_pair_denominator(d: float):
    """s_i + s_j kept at least POLAR_ADJOINT_EPS away from zero, on its own side."""
    out = d
    if wp.abs(d) < POLAR_ADJOINT_EPS:
        out = POLAR_ADJOINT_EPS
        if d < 0.0:
            out = -POLAR_ADJOINT_EPS
    return out



@wp.func_grad(damaged_kirchhoff)
def adj_damaged_kirchhoff(F: wp.mat33, mu: float, lam: float, damage: float, adj_ret: wp.mat33):
    """Analytic adjoint of damaged_kirchhoff, in place of Warp's automatic one through svd3's adjoint: that
    one costs more and divides by s_j^2 - s_i^2 (clamped), which put its dL/dF 4-15 % off where two singular
    values are equal (F = I, a rotation, an axisymmetric stretch). With G = dL/dtau, a = 2 mu (1 - damage):
    dL/dF = a (G F + G^T (F - R)) + polar_rotation_adjoint(F, R, ., -a G F) + tr(G) lam k' (2J - 1) cof(F), with
    k' = 1 - damage under tension (J > 1), else 1 (-a G F is dL/dR). func_grad passes no forward
    intermediates, so R is computed again here. p2g_affine's inline=True only force-inlines the generated
    functions: its adjoint calls this one."""
    R, newton = polar_newton(F)
    if newton == 0:
        U, s, V, Rs = svd_polar(F)  # polar_rotation's fallback, without running the iteration again
        R = Rs
    J = wp.determinant(F)
    keep = 1.0 - damage
    G = adj_ret
    a = 2.0 * mu * keep
    FmR = F - R
    GF = G * F
    dev = wp.ddot(G, FmR * wp.transpose(F))  # G : ((F - R) F^T)
    trG = wp.trace(G)
    vol_keep = 1.0
    if J > 1.0:
        vol_keep = keep
    dF = a * (GF + wp.transpose(G) * FmR) + polar_rotation_adjoint(F, R, newton, (-a) * GF)
    dF = dF + (trG * lam * vol_keep * (2.0 * J - 1.0)) * cofactor(F)
    wp.adjoint[F] += dF
    wp.adjoint[mu] += 2.0 * keep * dev
    wp.adjoint[lam] += trG * J * (J - 1.0) * vol_keep
    d_keep = 2.0 * mu * dev
    if J > 1.0:
        d_keep = d_keep + trG * lam * J * (J - 1.0)
    wp.adjoint[damage] += -d_keep


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
def broken_deformation(F: wp.mat33, min_singular: float):
    """The deformation gradient a fully broken particle keeps: J^(1/3) I with J = det F capped at 1 (and kept
    at least min_singular^3). Its stress (damaged_kirchhoff with damage 1: the volumetric part under
    compression alone) depends on J only and is the same for both; without the reset, the stretch that no
    stress resists any more accumulates in F without bound (principal stretches of thousands within a second
    in a torn rope) until the SVD and then the state turn non-finite. A torn piece pressed back resists
    compression from its current volume, not from the volume it had before it was pulled open."""
    J = wp.clamp(wp.determinant(F), min_singular * min_singular * min_singular, 1.0)
    return wp.identity(n=3, dtype=float) * wp.pow(J, 1.0 / 3.0)


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


@wp.func(inline=True)
def p2g_affine_scaled(Fp: wp.mat33, Cp: wp.mat33, damage: float, mu_vol: float, lam_vol: float, eta_vol: float,
                      mass: float, dt: float, inv_dx: float):
    """APIC's affine matrix of one particle [kg/s]: its stress impulse over dt and mass * C, from the Lame
    parameters and the viscosity times the particle's volume (the stress is linear in all three)."""
    tau_vol = damaged_kirchhoff(Fp, mu_vol, lam_vol, damage)
    # Kelvin-Voigt viscous stress (zero when eta = 0); APIC's C is the velocity gradient, so
    # tau_v = J eta (C + C^T). No branch: a data-dependent branch here slows the adjoint kernel.
    tau_vol = tau_vol + (eta_vol * wp.determinant(Fp)) * (Cp + wp.transpose(Cp))
    return (-dt * 4.0 * inv_dx * inv_dx) * tau_vol + mass * Cp


@wp.func(inline=True)
def p2g_affine(Fp: wp.mat33, Cp: wp.mat33, damage: float, E: float, nu: float, viscosity: float, vol: float,
               mass: float, dt: float, inv_dx: float):
    """APIC's affine matrix of one particle [kg/s] from its material (p2g_affine_scaled)."""
    mu, lam = lame_parameters(E, nu)
    return p2g_affine_scaled(Fp, Cp, damage, mu * vol, lam * vol, viscosity * vol, mass, dt, inv_dx)


@wp.kernel
def pack_p2g_materials_kernel(
    particle_vol: wp.array(dtype=float),
    particle_E: wp.array(dtype=float),
    particle_nu: wp.array(dtype=float),
    particle_density: wp.array(dtype=float),
    particle_viscosity: wp.array(dtype=float),
    packed: wp.array(dtype=wp.vec4),
):
    """What the sorted P2G reads of a particle's material, in one 16-byte load: (mu V, lambda V, eta V, mass)
    (five scattered 4-byte loads otherwise, each a 32-byte memory sector)."""
    p = wp.tid()
    mu, lam = lame_parameters(particle_E[p], particle_nu[p])
    vol = particle_vol[p]
    packed[p] = wp.vec4(mu * vol, lam * vol, particle_viscosity[p] * vol, particle_density[p] * vol)


@wp.func
def mark_columns(columns: wp.array3d(dtype=int), w: int, base: wp.vec3i):
    """Flag the 3 x 3 grid columns (w, i, j) that a stencil with this base node reaches, so that the grid
    update skips the columns no particle reached."""
    for i in range(3):
        for j in range(3):
            columns[w, base[0] + i, base[1] + j] = 1


@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    float* node = reinterpret_cast<float*>(&wp::index(grid, w, i, j, k));
    atomicAdd(reinterpret_cast<float4*>(node), make_float4(value[0], value[1], value[2], value[3]));
#else
    wp::atomic_add(&wp::index(grid, w, i, j, k), value);
#endif
""",
    adj_snippet="""
    if (adj_grid.data)
        adj_value += wp::index(adj_grid, w, i, j, k);
    else if (grid.grad)
        adj_value += wp::index_grad(grid, w, i, j, k);
""",
    replay_snippet="",
)
def packed_add(grid: wp.array4d(dtype=wp.vec4), w: int, i: int, j: int, k: int, value: wp.vec4):
    """grid[w, i, j, k] += value with one 16-byte atomic (sm_90 and later; one per component elsewhere)."""
    ...


@wp.kernel
def mark_columns_kernel(
    x: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    origin: wp.vec3,
    inv_dx: float,
    res: wp.vec3i,
    columns: wp.array3d(dtype=int),
):
    """Flag the grid columns each particle's stencil reaches (p2g_kernel's companion; not differentiated)."""
    p = wp.tid()
    base, fx = cell_base(x[p], origin, inv_dx, res)
    mark_columns(columns, particle_world[p], base)


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
    packed: int,
    grid_mvm: wp.array4d(dtype=wp.vec4),
):
    """Scatter particle momentum and mass to the grid (xyz: momentum, w: mass), one particle per thread:
    the CPU path and taped steps (``packed``: one 16-byte atomic per node on CUDA; 0: Warp's atomics, one
    per component, as the CPU and CUDA's deterministic mode need). mark_columns_kernel flags the columns,
    outside the tape."""
    p = wp.tid()
    w = particle_world[p]
    vol = particle_vol[p]
    mass = particle_density[p] * vol
    affine = p2g_affine(F[p], C[p], damage[p], particle_E[p], particle_nu[p], particle_viscosity[p], vol, mass, dt,
                        inv_dx)
    mv = mass * v[p]
    base, fx = cell_base(x[p], origin, inv_dx, res)
    W = bspline_weights(fx)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                m = weight * (mv + affine * dpos)
                node = wp.vec4(m[0], m[1], m[2], weight * mass)
                if packed != 0:
                    packed_add(grid_mvm, w, base[0] + i, base[1] + j, base[2] + k, node)
                else:
                    wp.atomic_add(grid_mvm, w, base[0] + i, base[1] + j, base[2] + k, node)


# -- P2G on CUDA: particles visited in cell order, each warp sums what its threads give one node before a
# single atomic per node (one 16-byte atomic on sm_90 and later). Thread t handles particle order[t]; the
# lanes of a warp whose particles share a stencil base (the same key) form a segment, whose first lane
# adds the segment's sum. The sums are exact reorderings of the same float additions that per-particle
# atomics make (atomics have no fixed order either); the adjoint is unchanged: every particle reads the
# gradient of the nodes it wrote.

_WARP_LANES = """
    const int lane = tid & 31;
    const int first = tid - lane;
    const unsigned mask = (n - first >= 32) ? 0xffffffffu : ((1u << (n - first)) - 1u);
"""


@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__)
""" + _WARP_LANES + """
    __syncwarp(mask);
    const int prev = __shfl_up_sync(mask, key, 1);
    const bool head = (lane == 0) || (prev != key);
    const unsigned ends = __ballot_sync(mask, head) | ~mask;
    const unsigned later = (lane == 31) ? 0u : (ends & (0xffffffffu << (lane + 1)));
    const int end = later ? (__ffs(later) - 1) : 32;
    int longest = head ? (end - lane) : 0;
    for (int off = 16; off > 0; off >>= 1) {
        const int other = __shfl_xor_sync(mask, longest, off);
        longest = other > longest ? other : longest;
    }
    int steps = 0;
    while ((1 << steps) < longest)
        ++steps;
    return end | (head ? 64 : 0) | (steps << 8);  // no int(...): Warp's generated code defines int(x) as a macro
#else
    return 64;
#endif
""",
    adj_snippet="",
)
def warp_segment(key: int, tid: int, n: int) -> int:
    """This lane's segment of equal keys in its warp: the lane after its end (bits 0-5), whether it is the
    segment's first lane (bit 6), and the log2 steps that sum the warp's longest segment (bits 8+)."""
    ...


def _segment_sum(names):
    """CUDA text: sum the float variables ``names`` over each lane's segment (exact at the segment's first
    lane); needs _WARP_LANES and ``seg`` (from warp_segment) in scope. ``steps`` is the same on every lane,
    so every lane of the mask runs every shuffle."""
    shuffles = "".join(f"        const float {v}_ = __shfl_down_sync(mask, {v}, off);\n" for v in names)
    adds = " ".join(f"{v} += {v}_;" for v in names)
    return (f"    for (int it = 0, off = 1; it < (seg >> 8); ++it, off <<= 1) {{\n{shuffles}"
            f"        if (lane + off < (seg & 63)) {{ {adds} }}\n    }}\n")


@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__)
""" + _WARP_LANES + """
    float s0 = value[0], s1 = value[1], s2 = value[2], s3 = value[3];
""" + _segment_sum(["s0", "s1", "s2", "s3"]) + """
    if (seg & 64) {
        float* node = reinterpret_cast<float*>(&wp::index(grid, w, i, j, k));
#if __CUDA_ARCH__ >= 900
        atomicAdd(reinterpret_cast<float4*>(node), make_float4(s0, s1, s2, s3));
#else
        atomicAdd(node, s0); atomicAdd(node + 1, s1); atomicAdd(node + 2, s2); atomicAdd(node + 3, s3);
#endif
    }
#else
    wp::atomic_add(&wp::index(grid, w, i, j, k), value);
#endif
""",
    adj_snippet="""
    if (adj_grid.data)
        adj_value += wp::index(adj_grid, w, i, j, k);
    else if (grid.grad)
        adj_value += wp::index_grad(grid, w, i, j, k);
""",
    replay_snippet="",
)
def warp_segment_add(grid: wp.array4d(dtype=wp.vec4), w: int, i: int, j: int, k: int, value: wp.vec4, seg: int,
                     tid: int, n: int):
    """grid[w, i, j, k] += the sum of ``value`` over this lane's segment (see warp_segment)."""
    ...


#: A grid node of the deterministic P2G: momentum (xyz) and mass (w) as 64-bit fixed-point integers.
vec4l = wp.types.vector(length=4, dtype=wp.int64)

# Deterministic P2G (SolverConfig.deterministic): a float sum depends on the order of its terms, and the order in
# which a GPU's atomics land changes from run to run; an integer sum does not. Each segment's float sum (fixed: the
# particles' cell order and the warp's lanes decide it) is rounded to an integer in units of 1 / scale and added
# with 64-bit integer atomics, which give the same total in any order; fixed_grid_to_float_kernel turns the totals
# back into floats for the grid update. The CPU branch adds the same integers one particle at a time.
@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__)
""" + _WARP_LANES + """
    float s0 = value[0], s1 = value[1], s2 = value[2], s3 = value[3];
""" + _segment_sum(["s0", "s1", "s2", "s3"]) + """
    if (seg & 64) {
        unsigned long long* node = reinterpret_cast<unsigned long long*>(&wp::index(grid, w, i, j, k));
        const double q0 = (double)s0 * (double)scale[0], q1 = (double)s1 * (double)scale[0];
        const double q2 = (double)s2 * (double)scale[0], q3 = (double)s3 * (double)scale[1];
        atomicAdd(node, (unsigned long long)(long long)(q0 >= 0.0 ? q0 + 0.5 : q0 - 0.5));
        atomicAdd(node + 1, (unsigned long long)(long long)(q1 >= 0.0 ? q1 + 0.5 : q1 - 0.5));
        atomicAdd(node + 2, (unsigned long long)(long long)(q2 >= 0.0 ? q2 + 0.5 : q2 - 0.5));
        atomicAdd(node + 3, (unsigned long long)(long long)(q3 >= 0.0 ? q3 + 0.5 : q3 - 0.5));
    }
#else
    long long* node = reinterpret_cast<long long*>(&wp::index(grid, w, i, j, k));
    for (int c = 0; c < 4; ++c) {
        const double q = (double)value[c] * (double)scale[c == 3 ? 1 : 0];
        node[c] += (long long)(q >= 0.0 ? q + 0.5 : q - 0.5);
    }
#endif
""",
    adj_snippet="",
    replay_snippet="",
)
def warp_segment_add_fixed(grid: wp.array4d(dtype=vec4l), w: int, i: int, j: int, k: int, value: wp.vec4,
                           scale: wp.vec2, seg: int, tid: int, n: int):
    """grid[w, i, j, k] += the sum of ``value`` over this lane's segment, in integer units of 1 / ``scale``
    (momentum: scale[0] per kg m/s; mass: scale[1] per kg). Forward only."""
    ...


@wp.func
def active_node(active: wp.array(dtype=int), q: int, res: wp.vec3i):
    """The grid node (w, i, j, k) that the ``q``-th thread of a stride over the active columns' nodes visits
    (``active`` lists columns by flat index (w * res_i + i) * res_j + j; see active_columns_kernel)."""
    col = active[q / res[2]]
    k = q - (q / res[2]) * res[2]
    j = col % res[1]
    i = (col / res[1]) % res[0]
    w = col / (res[1] * res[0])
    return w, i, j, k


@wp.kernel
def fixed_grid_to_float_kernel(
    grid_fixed: wp.array4d(dtype=vec4l),
    active: wp.array(dtype=int),
    active_count: wp.array(dtype=int),
    res: wp.vec3i,
    inv_scale_mv: wp.float64,
    inv_scale_m: wp.float64,
    threads: int,
    grid_mvm: wp.array4d(dtype=wp.vec4),
):
    """The deterministic P2G's integer totals as the momentum and mass the grid update reads, on the active
    columns' nodes (``threads`` threads striding over them); each integer node is zeroed once read."""
    t = wp.tid()
    for q in range(t, active_count[0] * res[2], threads):
        w, i, j, k = active_node(active, q, res)
        f = grid_fixed[w, i, j, k]
        grid_mvm[w, i, j, k] = wp.vec4(float(wp.float64(f[0]) * inv_scale_mv), float(wp.float64(f[1]) * inv_scale_mv),
                                       float(wp.float64(f[2]) * inv_scale_mv), float(wp.float64(f[3]) * inv_scale_m))
        grid_fixed[w, i, j, k] = vec4l()


@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__)
""" + _WARP_LANES + """
    float s0 = value;
""" + _segment_sum(["s0"]) + """
    return s0;
#else
    return value;
#endif
""",
    adj_snippet="",
)
def warp_segment_sum(value: float, seg: int, tid: int, n: int) -> float:
    """The sum of ``value`` over this lane's segment, exact at its first lane (forward only)."""
    ...


@wp.func_native(
    snippet="""
#if defined(__CUDA_ARCH__)
""" + _WARP_LANES + """
    const unsigned want = __ballot_sync(mask, flag != 0);
    if (want == 0u)
        return -1;
    const int leader = __ffs(want) - 1;
    int start = 0;
    if (lane == leader)
        start = atomicAdd(&wp::index(counter, 0), __popc(want));
    start = __shfl_sync(mask, start, leader);
    return flag ? start + __popc(want & ((1u << lane) - 1u)) : -1;
#else
    return flag ? wp::atomic_add(&wp::index(counter, 0), 1) : -1;
#endif
""",
    adj_snippet="",
    replay_snippet="return -1;",
)
def claim_slot(flag: int, counter: wp.array(dtype=int), tid: int, n: int) -> int:
    """A unique slot (counter[0] counts them) for each lane whose flag is set, -1 for the others: one
    atomic per warp."""
    ...


@wp.kernel(grid_stride=False)
def active_columns_kernel(columns: wp.array(dtype=int), count: int, active: wp.array(dtype=int),
                          active_count: wp.array(dtype=int)):
    """List the flagged columns (flat index (w * res_i + i) * res_j + j) for the grid update, and clear their
    flags: between steps every flag is 0, and no step needs a memset of them."""
    t = wp.tid()
    slot = claim_slot(columns[t], active_count, t, count)
    if slot >= 0:
        active[slot] = t
        columns[t] = 0


@wp.func
def stencil_key(w: int, base: wp.vec3i, res: wp.vec3i):
    """One integer per (world, stencil base node): the particle sort's key."""
    return ((w * res[0] + base[0]) * res[1] + base[1]) * res[2] + base[2]


@wp.kernel(grid_stride=False)
def p2g_sorted_kernel(
    order: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    damage: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    particle_p2g: wp.array(dtype=wp.vec4),
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    res: wp.vec3i,
    dt: float,
    count: int,
    fixed: int,
    fixed_scale: wp.vec2,
    grid_mvm: wp.array4d(dtype=wp.vec4),
    columns: wp.array3d(dtype=int),
    grid_fixed: wp.array4d(dtype=vec4l),
):
    """p2g_kernel for CUDA with warp-summed atomics; thread t scatters particle order[t] (one thread per
    particle: no grid-stride loop, so the lanes of a warp are the consecutive threads below ``count``). The
    material comes packed (pack_p2g_materials_kernel): in cell order a particle's reads scatter, and each
    read costs a memory sector. With ``fixed`` the sums go to ``grid_fixed`` as integers (deterministic P2G;
    on the CPU, with the particles in any order, as well)."""
    t = wp.tid()
    p = order[t]
    w = particle_world[p]
    mat = particle_p2g[p]
    mass = mat[3]
    affine = p2g_affine_scaled(F[p], C[p], damage[p], mat[0], mat[1], mat[2], mass, dt, inv_dx)
    mv = mass * v[p]
    base, fx = cell_base(x[p], origin, inv_dx, res)
    seg = warp_segment(stencil_key(w, base, res), t, count)
    if (seg & 64) != 0:
        mark_columns(columns, w, base)  # once per segment: its lanes share the stencil
    W = bspline_weights(fx)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                m = weight * (mv + affine * dpos)
                node = wp.vec4(m[0], m[1], m[2], weight * mass)
                if fixed != 0:  # deterministic: integer totals in grid_fixed (see warp_segment_add_fixed)
                    warp_segment_add_fixed(grid_fixed, w, base[0] + i, base[1] + j, base[2] + k, node, fixed_scale,
                                           seg, t, count)
                else:
                    warp_segment_add(grid_mvm, w, base[0] + i, base[1] + j, base[2] + k, node, seg, t, count)


@wp.kernel
def sort_keys_kernel(
    x: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    origin: wp.vec3,
    inv_dx: float,
    res: wp.vec3i,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
):
    """Each particle's stencil key and its index, for the radix sort that orders P2G's threads."""
    p = wp.tid()
    base, fx = cell_base(x[p], origin, inv_dx, res)
    keys[p] = stencil_key(particle_world[p], base, res)
    values[p] = p


def make_grid_update_kernel(ee_count: int):
    """Build the grid-update kernel for a fixed number of end-effectors per world (loop unrolled)."""
    EE = ee_count

    @wp.kernel(module="unique")
    def grid_update_kernel(
        grid_mvm: wp.array4d(dtype=wp.vec4),
        active: wp.array(dtype=int),
        active_count: wp.array(dtype=int),
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
        threads: int,
        grid_v: wp.array4d(dtype=wp.vec3),
        ee_pos_out: wp.array(dtype=wp.vec3),
        ee_rot_out: wp.array(dtype=wp.quat),
    ):
        """Grid velocity update: momentum / mass, gravity, end-effectors, table and walls, on the nodes of
        the columns listed in ``active`` (see active_columns_kernel): ``threads`` threads stride over them,
        so that the work follows the nodes particles reached, not the grid's size (a heavy kernel launched
        over every node, most of them empty, was the step's largest cost for many small worlds). The first
        worlds x ee_count threads also advance the kinematic end-effector poses by their commanded velocities
        (a launch of its own cost a CUDA graph node per substep, forward and backward).

        With ``clear_inputs`` the touched mass and momentum nodes are zeroed once read, which saves the
        next substep a full-grid clear (only when no tape needs those values again). Nodes no particle
        reached (mass exactly 0) are neither read further nor written.
        """
        t = wp.tid()
        if wp.static(EE > 0):
            if t < ee_pos.shape[0]:
                ee_pos_out[t] = ee_pos[t] + dt * ee_vel[t]
                q0 = ee_rot[t]
                om = ee_omega[t]
                ee_rot_out[t] = wp.normalize(q0 + (0.5 * dt) * (wp.quat(om[0], om[1], om[2], 0.0) * q0))
        for q in range(t, active_count[0] * res[2], threads):
            w, i, j, k = active_node(active, q, res)
            mvm = grid_mvm[w, i, j, k]
            m = mvm[3]
            if m == 0.0:
                # no particle reached this node: G2P reads it only with weight 0, so its velocity is left as is
                continue
            if clear_inputs != 0:
                grid_mvm[w, i, j, k] = wp.vec4(0.0)
            mv = wp.vec3(mvm[0], mvm[1], mvm[2])
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


@wp.func
def g2p_finish(
    p: int,
    new_v: wp.vec3,
    new_C: wp.mat33,
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    damage: wp.array(dtype=float),
    particle_E: wp.array(dtype=float),
    particle_nu: wp.array(dtype=float),
    particle_yield: wp.array(dtype=float),
    particle_plastic: wp.array(dtype=int),
    particle_fracture_strain: wp.array(dtype=float),
    particle_fracture_softening: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    res: wp.vec3i,
    dt: float,
    min_singular: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    damage_out: wp.array(dtype=float),
):
    """Particle p's update from its gathered velocity and affine field: F (with the plastic return
    mapping), damage, and advection inside the grid."""
    Fn = (wp.identity(n=3, dtype=float) + dt * new_C) * F[p]
    if particle_plastic[p] != 0:
        mu, lam = lame_parameters(particle_E[p], particle_nu[p])
        Fn = von_mises_return(Fn, mu, particle_yield[p], min_singular)
    # damage only grows (fracture effect; a threshold of 1e30 keeps it at 0)
    dmg = damage[p]
    strain = particle_fracture_strain[p]
    if strain < 1.0e20:
        dmg = wp.max(dmg, damage_from_stretch(Fn, strain, particle_fracture_softening[p]))
        if dmg >= 1.0:
            Fn = broken_deformation(Fn, min_singular)
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
    active_count: wp.array(dtype=int),
    clear_count: int,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    damage_out: wp.array(dtype=float),
):
    """Gather velocity and affine field, update F (with plastic return mapping) and advect particles
    (one particle per thread; the adjoint adds one atomic per particle, node and component). With
    ``clear_count`` the grid's active-column count, read by the grid update before, is zeroed for the next
    step (a memset node less per step)."""
    p = wp.tid()
    if clear_count != 0 and p == 0:
        active_count[0] = 0
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
    g2p_finish(p, new_v, new_C, x, F, damage, particle_E, particle_nu, particle_yield, particle_plastic,
               particle_fracture_strain, particle_fracture_softening, origin, dx, res, dt, min_singular,
               x_out, v_out, C_out, F_out, damage_out)


# -- Transfers with hand-written adjoints (taped steps). Warp's own adjoint of the 27-node loops above keeps
# every unrolled iteration's intermediates alive from its forward replay into the reverse sweep; these
# recompute each node's weight in the reverse sweep instead. The forward code is the loops' own arithmetic.
# Their atomics bypass Warp's deterministic mode, which therefore keeps the loops above.

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
"""Gathered APIC fields of one particle: columns 0-2 the affine velocity C [1/s], column 3 the velocity [m/s]."""

_BSPLINE_AND_DERIVATIVE = """
    float wt[3][3], dw[3][3];  // [node offset][axis]: quadratic B-spline weights and their d/dfx
    for (int a = 0; a < 3; ++a) {
        const float p = 1.5f - fx[a], q = fx[a] - 1.0f, r = fx[a] - 0.5f;
        wt[0][a] = 0.5f * (p * p); wt[1][a] = 0.75f - q * q; wt[2][a] = 0.5f * (r * r);
        dw[0][a] = -p; dw[1][a] = -2.0f * q; dw[2][a] = r;
    }
"""

_NODES_BEGIN = """
    for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) {
        const float weight = wt[i][0] * wt[j][1] * wt[k][2];
        const float dpos[3] = {((float)i - fx[0]) * dx, ((float)j - fx[1]) * dx, ((float)k - fx[2]) * dx};
"""

_WEIGHT_GRADIENT = """
        const float gw[3] = {dw[i][0] * wt[j][1] * wt[k][2], wt[i][0] * dw[j][1] * wt[k][2],
                             wt[i][0] * wt[j][1] * dw[k][2]};
"""


@wp.func_native(
    snippet=_BSPLINE_AND_DERIVATIVE + """
    const float cscale = 4.0f * inv_dx * inv_dx;
    wp::mat_t<3, 4, wp::float32> out;
""" + _NODES_BEGIN + """
        const wp::vec3 gv = wp::index(grid_v, w, base[0] + i, base[1] + j, base[2] + k);
        const float cw = cscale * weight;
        for (int r = 0; r < 3; ++r) {
            out.data[r][3] += weight * gv[r];
            for (int c = 0; c < 3; ++c)
                out.data[r][c] += cw * (gv[r] * dpos[c]);
        }
    }
    return out;
""",
    adj_snippet=_BSPLINE_AND_DERIVATIVE + """
    const float cscale = 4.0f * inv_dx * inv_dx;
    float gfx[3] = {0.0f, 0.0f, 0.0f};
""" + _NODES_BEGIN + _WEIGHT_GRADIENT + """
        const wp::vec3 gv = wp::index(grid_v, w, base[0] + i, base[1] + j, base[2] + k);
        const float cw = cscale * weight;
        // new_v += weight gv, new_C += cw gv dpos^T; A = adj new_C, a = adj new_v
        float aw = 0.0f;
        wp::vec3 g;
        for (int r = 0; r < 3; ++r) {
            const float Ad = adj_ret.data[r][0] * dpos[0] + adj_ret.data[r][1] * dpos[1] + adj_ret.data[r][2] * dpos[2];
            g[r] = weight * adj_ret.data[r][3] + cw * Ad;
            aw += gv[r] * (adj_ret.data[r][3] + cscale * Ad);
        }
        // into the sink, not grid_v's gradient: one 16-byte atomic per node on sm_90 instead of three
        wp::vec4* s = &wp::index(sink, w, base[0] + i, base[1] + j, base[2] + k);
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
        atomicAdd(reinterpret_cast<float4*>(s), make_float4(g[0], g[1], g[2], 0.0f));
#else
        wp::atomic_add(s, wp::vec4(g[0], g[1], g[2], 0.0f));
#endif
        for (int c = 0; c < 3; ++c) {
            const float atg = adj_ret.data[0][c] * gv[0] + adj_ret.data[1][c] * gv[1] + adj_ret.data[2][c] * gv[2];
            gfx[c] += aw * gw[c] - dx * cw * atg;  // d dpos / d fx = -dx
        }
    }
    adj_fx[0] += gfx[0]; adj_fx[1] += gfx[1]; adj_fx[2] += gfx[2];
""",
)
def apic_gather(grid_v: wp.array4d(dtype=wp.vec3), sink: wp.array4d(dtype=wp.vec4), w: int, base: wp.vec3i,
                fx: wp.vec3, dx: float, inv_dx: float) -> mat34:
    """G2P's gather over the 27 nodes of the stencil at ``base`` (fractional position fx in cells): the
    particle's new velocity (column 3) and affine velocity C (columns 0-2), as g2p_kernel's loop computes
    them. Differentiable in fx and in grid_v, whose gradient the adjoint adds to ``sink`` (xyz; w stays 0):
    flush_adjoint_sink_kernel moves it into grid_v's gradient."""
    ...


@wp.func_native(
    snippet="""
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            wp::index(columns, w, base[0] + i, base[1] + j) = 1;
""" + _BSPLINE_AND_DERIVATIVE + _NODES_BEGIN + """
        float m[3];
        for (int r = 0; r < 3; ++r)
            m[r] = weight * (mv[r] + (affine.data[r][0] * dpos[0] + affine.data[r][1] * dpos[1]
                                      + affine.data[r][2] * dpos[2]));
        wp::vec4* node = &wp::index(grid, w, base[0] + i, base[1] + j, base[2] + k);
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
        if (packed) {
            atomicAdd(reinterpret_cast<float4*>(node), make_float4(m[0], m[1], m[2], weight * mass));
            continue;
        }
#endif
        wp::atomic_add(node, wp::vec4(m[0], m[1], m[2], weight * mass));
    }
""",
    adj_snippet=_BSPLINE_AND_DERIVATIVE + """
    float gfx[3] = {0.0f, 0.0f, 0.0f}, gmv[3] = {0.0f, 0.0f, 0.0f}, gaff[3][3] = {}, gmass = 0.0f;
""" + _NODES_BEGIN + _WEIGHT_GRADIENT + """
        wp::vec4 G;
        if (adj_grid.data)
            G = wp::index(adj_grid, w, base[0] + i, base[1] + j, base[2] + k);
        else if (grid.grad)
            G = wp::index_grad(grid, w, base[0] + i, base[1] + j, base[2] + k);
        // node += (weight (mv + affine dpos), weight mass)
        float aw = G[3] * mass;
        for (int r = 0; r < 3; ++r) {
            const float u = mv[r] + (affine.data[r][0] * dpos[0] + affine.data[r][1] * dpos[1]
                                     + affine.data[r][2] * dpos[2]);
            aw += G[r] * u;
            gmv[r] += weight * G[r];
            for (int c = 0; c < 3; ++c)
                gaff[r][c] += weight * G[r] * dpos[c];
        }
        gmass += weight * G[3];
        for (int c = 0; c < 3; ++c) {
            const float atg = affine.data[0][c] * G[0] + affine.data[1][c] * G[1] + affine.data[2][c] * G[2];
            gfx[c] += aw * gw[c] - dx * weight * atg;
        }
    }
    for (int r = 0; r < 3; ++r) {
        adj_fx[r] += gfx[r];
        adj_mv[r] += gmv[r];
        for (int c = 0; c < 3; ++c)
            adj_affine.data[r][c] += gaff[r][c];
    }
    adj_mass += gmass;
""",
    replay_snippet="",
)
def apic_scatter(grid: wp.array4d(dtype=wp.vec4), columns: wp.array3d(dtype=int), w: int, base: wp.vec3i,
                 fx: wp.vec3, dx: float, mv: wp.vec3, affine: wp.mat33, mass: float, packed: int):
    """P2G's scatter over the 27 nodes of the stencil at ``base``: momentum weight (mv + affine dpos) and
    mass weight mass per node, as p2g_kernel's loop adds them (``packed``: one 16-byte atomic per node on
    sm_90), and the stencil's columns flagged (mark_columns; not replayed in the adjoint). Differentiable
    in mv, affine, mass and fx."""
    ...


@wp.kernel
def p2g_native_kernel(
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
    packed: int,
    grid_mvm: wp.array4d(dtype=wp.vec4),
    columns: wp.array3d(dtype=int),
):
    """p2g_kernel with the hand-written adjoint of its scatter (apic_scatter), which also flags the columns:
    taped steps."""
    p = wp.tid()
    vol = particle_vol[p]
    mass = particle_density[p] * vol
    affine = p2g_affine(F[p], C[p], damage[p], particle_E[p], particle_nu[p], particle_viscosity[p], vol, mass, dt,
                        inv_dx)
    base, fx = cell_base(x[p], origin, inv_dx, res)
    apic_scatter(grid_mvm, columns, particle_world[p], base, fx, dx, mass * v[p], affine, mass, packed)


@wp.kernel
def g2p_native_kernel(
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
    adjoint_sink: wp.array4d(dtype=wp.vec4),
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
    """g2p_kernel with the hand-written adjoint of its gather (apic_gather), which leaves grid_v's gradient
    in ``adjoint_sink``: taped steps."""
    p = wp.tid()
    base, fx = cell_base(x[p], origin, inv_dx, res)
    R = apic_gather(grid_v, adjoint_sink, particle_world[p], base, fx, dx, inv_dx)
    new_v = wp.vec3(R[0, 3], R[1, 3], R[2, 3])
    new_C = wp.mat33(R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
    g2p_finish(p, new_v, new_C, x, F, damage, particle_E, particle_nu, particle_yield, particle_plastic,
               particle_fracture_strain, particle_fracture_softening, origin, dx, res, dt, min_singular,
               x_out, v_out, C_out, F_out, damage_out)



@wp.kernel
def flush_adjoint_sink_kernel(
    active: wp.array(dtype=int),
    active_count: wp.array(dtype=int),
    res: wp.vec3i,
    threads: int,
    has_grad: int,
    sink: wp.array4d(dtype=wp.vec4),
    grid_v_grad: wp.array4d(dtype=wp.vec3),
):
    """grid_v's gradient += the sink's xyz, and the sink zeroed, on the nodes of the listed columns (those the
    step's particles reached, striding as the grid update does): the backward pass of a taped step runs this
    between G2P's adjoint and the grid update's."""
    t = wp.tid()
    for q in range(t, active_count[0] * res[2], threads):
        w, i, j, k = active_node(active, q, res)
        s = sink[w, i, j, k]
        if s[0] != 0.0 or s[1] != 0.0 or s[2] != 0.0:
            if has_grad != 0:
                grid_v_grad[w, i, j, k] = grid_v_grad[w, i, j, k] + wp.vec3(s[0], s[1], s[2])
            sink[w, i, j, k] = wp.vec4(0.0)

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


@wp.kernel(grid_stride=False)
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
    count: int,
):
    """Adjoint of expand_materials_kernel: sum per-particle parameter gradients into their worlds (on CUDA,
    the lanes of a warp in one world are summed first: one atomic per warp and world, not per particle)."""
    p = wp.tid()
    w = particle_world[p]
    u = particle_body_coord[p]
    field = wp.exp(wp.dot(world_stiffness_slope[w], u))
    Ep = world_E[w] * particle_stiffness[p] * field
    stiffness_grad[p] = stiffness_grad[p] + gE[p] * world_E[w] * field
    seg = warp_segment(w, p, count)
    gslope = (gE[p] * Ep) * u
    sE = warp_segment_sum(gE[p] * particle_stiffness[p] * field, seg, p, count)
    snu = warp_segment_sum(gnu[p], seg, p, count)
    srho = warp_segment_sum(grho[p], seg, p, count)
    sys = warp_segment_sum(gys[p], seg, p, count)
    seta = warp_segment_sum(geta[p], seg, p, count)
    s0 = warp_segment_sum(gslope[0], seg, p, count)
    s1 = warp_segment_sum(gslope[1], seg, p, count)
    s2 = warp_segment_sum(gslope[2], seg, p, count)
    sfs = warp_segment_sum(gfs[p], seg, p, count)
    sfw = warp_segment_sum(gfw[p], seg, p, count)
    if (seg & 64) != 0:
        wp.atomic_add(world_E_grad, w, sE)
        wp.atomic_add(world_nu_grad, w, snu)
        wp.atomic_add(world_density_grad, w, srho)
        wp.atomic_add(world_yield_grad, w, sys)
        wp.atomic_add(world_viscosity_grad, w, seta)
        wp.atomic_add(world_stiffness_slope_grad, w, wp.vec3(s0, s1, s2))
        wp.atomic_add(world_fracture_strain_grad, w, sfs)
        wp.atomic_add(world_fracture_softening_grad, w, sfw)


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
