"""Warp kernels of the XPBD cloth solver (see :mod:`anidress_core.sim.solver`).

XPBD: Macklin, Müller, Chentanez, "XPBD: Position-Based Simulation of Compliant
Constrained Dynamics", MIG 2016 (eq. 18: dlambda = (-C - alpha~ lambda) /
(sum_i w_i |grad_i C|^2 + alpha~), alpha~ = alpha / dt^2).
Long-range attachments: Kim, Chentanez, Müller, "Long Range Attachments", SCA 2012.

Every kernel is one thread per particle, per constraint or per body vertex; the
distance-constraint kernel is launched once per colour group (constraints of one
colour share no particle, so the Gauss–Seidel update within a group is race free).
"""
from __future__ import annotations

import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no greeting or "module loaded" lines


@wp.kernel
def skin_points(
    rest: wp.array(dtype=wp.vec3),  # (N,) rest positions
    bone: wp.array2d(dtype=wp.int32),  # (N, K) bone index per influence
    weight: wp.array2d(dtype=wp.float32),  # (N, K) weights (0 for padding)
    transforms: wp.array(dtype=wp.mat44),  # (S * 24,) rest -> world per substep
    offset: int,  # s * 24: first transform of this substep
    index: wp.array(dtype=wp.int32),  # (N,) where each result goes in ``out``
    out: wp.array(dtype=wp.vec3),  # (V,) skinned positions, scattered
):
    """out[index[n]] = sum_k w[n, k] (M[bone[n, k]] rest[n]) (linear blend skinning)."""
    n = wp.tid()
    p = rest[n]
    acc = wp.vec3(0.0, 0.0, 0.0)
    for k in range(bone.shape[1]):
        wk = weight[n, k]
        if wk != 0.0:
            acc += wk * wp.transform_point(transforms[offset + bone[n, k]], p)
    out[index[n]] = acc


@wp.kernel
def skin_body(
    rest: wp.array(dtype=wp.vec3),
    bone: wp.array2d(dtype=wp.int32),
    weight: wp.array2d(dtype=wp.float32),
    transforms: wp.array(dtype=wp.mat44),
    offset: int,
    inv_dt: float,
    points: wp.array(dtype=wp.vec3),  # (Vb,) in: previous substep, out: this substep
    velocities: wp.array(dtype=wp.vec3),  # (Vb,) out: (x_new - x_old) / dt
    max_move: wp.array(dtype=wp.float32),  # (1,) running max of |x_new - x_old| (reset by the consumer)
):
    """Skin the body mesh for one substep, write its per-vertex velocity and the largest
    vertex displacement (which bounds the displacement of every surface point)."""
    n = wp.tid()
    p = rest[n]
    acc = wp.vec3(0.0, 0.0, 0.0)
    for k in range(bone.shape[1]):
        wk = weight[n, k]
        if wk != 0.0:
            acc += wk * wp.transform_point(transforms[offset + bone[n, k]], p)
    dx = acc - points[n]
    velocities[n] = dx * inv_dt
    wp.atomic_max(max_move, 0, wp.length(dx))
    points[n] = acc


@wp.kernel
def integrate(
    x: wp.array(dtype=wp.vec3),  # (V,) in: positions at substep start; out: predicted
    v: wp.array(dtype=wp.vec3),  # (V,) velocities
    x_prev: wp.array(dtype=wp.vec3),  # (V,) out: positions at substep start
    inv_mass: wp.array(dtype=wp.float32),  # (V,) 0 for band (kinematic) particles
    band_target: wp.array(dtype=wp.vec3),  # (V,) skinned target (used where inv_mass == 0)
    gravity: wp.vec3,
    damping: float,  # velocity kept per substep: exp(-damping * dt)
    dt: float,
):
    """Symplectic Euler prediction; kinematic particles jump to their skinned target."""
    i = wp.tid()
    x0 = x[i]
    x_prev[i] = x0
    if inv_mass[i] == 0.0:
        x[i] = band_target[i]
        v[i] = (band_target[i] - x0) / dt
    else:
        vi = (v[i] + gravity * dt) * damping
        v[i] = vi
        x[i] = x0 + vi * dt


@wp.func
def outward_normal(mesh: wp.uint64, face: int, sign: float, d: wp.vec3, dist: float):
    """Outward normal of a closed mesh at the closest point of a query (face, sign) whose
    offset from that point is d (length dist): along d when the query point is outside,
    the face normal when it is inside or touching."""
    if sign > 0.0 and dist > 1.0e-7:
        return d / dist
    return wp.mesh_eval_face_normal(mesh, face)


@wp.kernel
def collide_query(
    mesh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    radius: float,
    contact_point: wp.array(dtype=wp.vec3),  # (V,) out: closest body point
    contact_normal: wp.array(dtype=wp.vec3),  # (V,) out: outward normal
    contact_vel: wp.array(dtype=wp.vec3),  # (V,) out: skin velocity at the closest point
    contact_flag: wp.array(dtype=wp.int32),  # (V,) out: 1 if a contact is active
):
    """Closest point on the (already skinned, refit) body within ``radius`` of x.

    A particle found inside the body (a fast limb swept over it during the substep)
    gets the face normal at its closest point, so the contact projection moves it back
    out through the nearest surface and friction carries it with the skin velocity
    (continuous handling at substep resolution: the body moves at most
    |v_skin| * dt per substep, far less than ``radius`` at the default substep).
    """
    i = wp.tid()
    contact_flag[i] = 0
    if inv_mass[i] == 0.0:
        return
    p = x[i]
    q = wp.mesh_query_point_sign_normal(mesh, p, radius)
    if not q.result:
        return
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    d = p - cp
    dist = wp.length(d)
    contact_point[i] = cp
    contact_normal[i] = outward_normal(mesh, q.face, q.sign, d, dist)
    contact_vel[i] = wp.mesh_eval_velocity(mesh, q.face, q.u, q.v)
    contact_flag[i] = 1


@wp.kernel
def solve_distance(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    ci: wp.array(dtype=wp.int32),  # (C,) first particle, constraints sorted by colour
    cj: wp.array(dtype=wp.int32),  # (C,) second particle
    rest: wp.array(dtype=wp.float32),  # (C,) rest length
    compliance: wp.array(dtype=wp.float32),  # (C,) XPBD compliance alpha
    lam: wp.array(dtype=wp.float32),  # (C,) Lagrange multipliers, reset each substep
    start: int,  # first constraint of this colour group
    inv_dt2: float,
):
    """XPBD distance constraint C = |x_i - x_j| - rest (stretch edges and bending cross-edges)."""
    c = start + wp.tid()
    i = ci[c]
    j = cj[c]
    wi = inv_mass[i]
    wj = inv_mass[j]
    w = wi + wj
    if w == 0.0:
        return
    d = x[i] - x[j]
    L = wp.length(d)
    if L < 1.0e-9:
        return
    n = d / L
    C = L - rest[c]
    at = compliance[c] * inv_dt2
    dl = (-C - at * lam[c]) / (w + at)
    lam[c] = lam[c] + dl
    x[i] = x[i] + wi * dl * n
    x[j] = x[j] - wj * dl * n


@wp.kernel
def solve_attachments(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    anchor: wp.array(dtype=wp.int32),  # (V,) nearest band particle (graph distance)
    max_dist: wp.array(dtype=wp.float32),  # (V,) rest graph distance to it
):
    """Long-range attachment: |x_i - x_anchor| <= max_dist (unilateral, band is kinematic)."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    a = anchor[i]
    if a < 0:
        return
    d = x[i] - x[a]
    L = wp.length(d)
    m = max_dist[i]
    if L > m:
        x[i] = x[a] + d * (m / L)


@wp.kernel
def solve_contacts(
    x: wp.array(dtype=wp.vec3),
    contact_point: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_flag: wp.array(dtype=wp.int32),
    thickness: float,
):
    """Push a particle out to ``thickness`` above the tangent plane of its contact."""
    i = wp.tid()
    if contact_flag[i] == 0:
        return
    n = contact_normal[i]
    s = wp.dot(x[i] - contact_point[i], n) - thickness
    if s < 0.0:
        x[i] = x[i] - s * n


@wp.kernel
def finalize(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    contact_point: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_vel: wp.array(dtype=wp.vec3),
    contact_flag: wp.array(dtype=wp.int32),
    thickness: float,
    friction: float,
    dt: float,
):
    """Final contact push-out, Coulomb friction relative to the skin, new velocities.

    Friction (positional, Macklin et al. 2014 "Unified particle physics", §6.1): the
    tangential displacement relative to the skin's, dx_t, is removed entirely when
    |dx_t| < mu * depth (static) and shortened by mu * depth otherwise (kinetic), where
    depth is this push-out's normal correction.
    """
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    p = x[i]
    if contact_flag[i] != 0:
        n = contact_normal[i]
        s = wp.dot(p - contact_point[i], n) - thickness
        if s < 0.0:
            p = p - s * n
            depth = -s
        else:
            depth = 0.0
        # Contacts within a small band above the shell also feel friction (resting cloth).
        if s < 0.25 * thickness:
            rel = (p - x_prev[i]) - contact_vel[i] * dt
            rel_t = rel - wp.dot(rel, n) * n
            lt = wp.length(rel_t)
            lim = friction * wp.max(depth, 0.05 * thickness)
            if lt > 0.0:
                if lt <= lim:
                    p = p - rel_t
                else:
                    p = p - rel_t * (lim / lt)
        x[i] = p
    v[i] = (p - x_prev[i]) / dt


@wp.kernel
def signed_distance(
    mesh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    max_dist: float,
    out: wp.array(dtype=wp.float32),  # (N,) signed distance, < 0 inside; max_dist if farther
):
    """Signed distance of points to a closed mesh (sign by the winding number)."""
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, x[i], max_dist)
    if not q.result:
        out[i] = max_dist
        return
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    out[i] = q.sign * wp.length(x[i] - cp)


@wp.kernel
def closest_point_signed(
    mesh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    max_dist: float,
    point: wp.array(dtype=wp.vec3),  # (N,) out: closest mesh point
    normal: wp.array(dtype=wp.vec3),  # (N,) out: outward unit normal there
    found: wp.array(dtype=wp.int32),  # (N,) out: 1 if a mesh point lies within max_dist
):
    """Closest point of a closed mesh within ``max_dist`` and the outward normal there: the
    direction from the point to x when x is outside (winding number), the face normal when x is
    inside or on the surface. (x - point) . normal is then x's signed distance outside, and inside
    too when the closest point lies within a face (at an edge or corner: smaller in magnitude)."""
    i = wp.tid()
    found[i] = 0
    q = wp.mesh_query_point_sign_winding_number(mesh, x[i], max_dist)
    if not q.result:
        return
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    d = x[i] - cp
    point[i] = cp
    normal[i] = outward_normal(mesh, q.face, q.sign, d, wp.length(d))
    found[i] = 1


@wp.kernel
def signed_distance_fast(
    mesh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    max_dist: float,
    out: wp.array(dtype=wp.float32),
):
    """As :func:`signed_distance` with the cheaper normal-based sign (solver monitoring)."""
    i = wp.tid()
    q = wp.mesh_query_point_sign_normal(mesh, x[i], max_dist)
    if not q.result:
        out[i] = max_dist
        return
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    out[i] = q.sign * wp.length(x[i] - cp)


# --------------------------------------------------------------------------------------
# Fused serial substep (CPU). Warp runs a CPU launch's threads one after another on one
# core, so a launch over the colour-sorted constraints *is* the colour-by-colour
# Gauss–Seidel sweep; fusing the whole substep after the body refit into one
# single-thread kernel gives the same updates in the same order as the per-colour
# launches above (bitwise, on the CPU), with 3 host calls per substep instead of ~40.
# Never use it on CUDA (one GPU thread).
@wp.kernel
def substep_serial(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    band_rest: wp.array(dtype=wp.vec3),
    band_bone: wp.array2d(dtype=wp.int32),
    band_w: wp.array2d(dtype=wp.float32),
    band_idx: wp.array(dtype=wp.int32),
    band_target: wp.array(dtype=wp.vec3),
    transforms: wp.array(dtype=wp.mat44),
    offset: int,
    mesh: wp.uint64,
    radius: float,
    gravity: wp.vec3,
    damping: float,
    dt: float,
    inv_dt2: float,
    ci: wp.array(dtype=wp.int32),
    cj: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=wp.float32),
    compliance: wp.array(dtype=wp.float32),
    lam: wp.array(dtype=wp.float32),
    anchor: wp.array(dtype=wp.int32),
    max_dist: wp.array(dtype=wp.float32),
    contact_point: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_vel: wp.array(dtype=wp.vec3),
    contact_flag: wp.array(dtype=wp.int32),
    thickness: float,
    friction: float,
    iterations: int,
    query_radius: float,
    max_move: wp.array(dtype=wp.float32),
    travel: wp.array(dtype=wp.float64),
    q_pos: wp.array(dtype=wp.vec3),
    q_clear: wp.array(dtype=wp.float32),
    q_travel: wp.array(dtype=wp.float64),
):
    """One substep after the body skinning + refit: steps 2-6 of the solver, serially.

    Contact queries are skipped where they provably find nothing: at each query at
    position q_pos[i] the particle's clearance (distance to the body, ``query_radius``
    when nothing is nearer, 0 inside) is stored; since then the particle has moved
    |x - q_pos| and no body surface point more than the summed per-substep maximum
    vertex displacement (``travel`` - q_travel[i]), so
        clearance >= q_clear - |x - q_pos| - (travel - q_travel)
    and the query (radius ``radius`` < ``query_radius``) runs only when that bound
    drops below ``radius``. Contacts are therefore the same as querying every particle.
    """
    V = x.shape[0]
    C = ci.shape[0]
    tr = travel[0] + wp.float64(max_move[0])
    travel[0] = tr
    max_move[0] = 0.0
    # 2. Band (kinematic) targets.
    for n in range(band_idx.shape[0]):
        p = band_rest[n]
        acc = wp.vec3(0.0, 0.0, 0.0)
        for k in range(band_bone.shape[1]):
            wk = band_w[n, k]
            if wk != 0.0:
                acc += wk * wp.transform_point(transforms[offset + band_bone[n, k]], p)
        band_target[band_idx[n]] = acc
    # 3. Prediction; 4. contacts.
    for i in range(V):
        x0 = x[i]
        x_prev[i] = x0
        contact_flag[i] = 0
        if inv_mass[i] == 0.0:
            x[i] = band_target[i]
            v[i] = (band_target[i] - x0) / dt
        else:
            vi = (v[i] + gravity * dt) * damping
            v[i] = vi
            p = x0 + vi * dt
            x[i] = p
            bound = q_clear[i] - wp.length(p - q_pos[i]) - float(tr - q_travel[i])
            if bound < radius:
                q_pos[i] = p
                q_travel[i] = tr
                q_clear[i] = query_radius
                q = wp.mesh_query_point_sign_normal(mesh, p, query_radius)
                if q.result:
                    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
                    d = p - cp
                    dist = wp.length(d)
                    if q.sign > 0.0:
                        q_clear[i] = dist
                    else:
                        q_clear[i] = 0.0
                    if dist < radius:
                        contact_point[i] = cp
                        contact_normal[i] = outward_normal(mesh, q.face, q.sign, d, dist)
                        contact_vel[i] = wp.mesh_eval_velocity(mesh, q.face, q.u, q.v)
                        contact_flag[i] = 1
    for c in range(C):
        lam[c] = 0.0
    # 5. Gauss–Seidel iterations.
    for it in range(iterations):
        for c in range(C):
            i = ci[c]
            j = cj[c]
            wi = inv_mass[i]
            wj = inv_mass[j]
            w = wi + wj
            if w > 0.0:
                d = x[i] - x[j]
                L = wp.length(d)
                if L >= 1.0e-9:
                    nn = d / L
                    Cv = L - rest[c]
                    at = compliance[c] * inv_dt2
                    dl = (-Cv - at * lam[c]) / (w + at)
                    lam[c] = lam[c] + dl
                    x[i] = x[i] + wi * dl * nn
                    x[j] = x[j] - wj * dl * nn
        for i in range(V):
            if inv_mass[i] != 0.0:
                a = anchor[i]
                if a >= 0:
                    d = x[i] - x[a]
                    L = wp.length(d)
                    m = max_dist[i]
                    if L > m:
                        x[i] = x[a] + d * (m / L)
        for i in range(V):
            if contact_flag[i] != 0:
                nrm = contact_normal[i]
                s = wp.dot(x[i] - contact_point[i], nrm) - thickness
                if s < 0.0:
                    x[i] = x[i] - s * nrm
    # 6. Friction, final push-out, velocities.
    for i in range(V):
        if inv_mass[i] != 0.0:
            p = x[i]
            if contact_flag[i] != 0:
                nrm = contact_normal[i]
                s = wp.dot(p - contact_point[i], nrm) - thickness
                depth = float(0.0)
                if s < 0.0:
                    p = p - s * nrm
                    depth = -s
                if s < 0.25 * thickness:
                    rel = (p - x_prev[i]) - contact_vel[i] * dt
                    rel_t = rel - wp.dot(rel, nrm) * nrm
                    lt = wp.length(rel_t)
                    lim = friction * wp.max(depth, 0.05 * thickness)
                    if lt > 0.0:
                        if lt <= lim:
                            p = p - rel_t
                        else:
                            p = p - rel_t * (lim / lt)
                x[i] = p
            v[i] = (p - x_prev[i]) / dt


@wp.kernel
def signed_distance_bounded(
    mesh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    max_dist: float,
    skip_above: float,
    travel: wp.array(dtype=wp.float64),
    q_pos: wp.array(dtype=wp.vec3),
    q_clear: wp.array(dtype=wp.float32),
    q_travel: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.float32),
):
    """As :func:`signed_distance_fast`, skipping (out = max_dist) particles whose
    clearance bound (see :func:`substep_serial`) exceeds ``skip_above``."""
    i = wp.tid()
    p = x[i]
    bound = q_clear[i] - wp.length(p - q_pos[i]) - float(travel[0] - q_travel[i])
    if bound > skip_above:
        out[i] = max_dist
        return
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if not q.result:
        out[i] = max_dist
        return
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    out[i] = q.sign * wp.length(p - cp)
