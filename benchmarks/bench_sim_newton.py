"""Reference for benchmarks.bench_sim: newton's SolverVBD cloth on the CPU, same scene.

Benchmark-only (``newton`` is never a runtime dependency of anidress_core).

Scene, matching ``anidress_core.sim.simulate`` as far as newton allows:
- the same garment mesh (rest state placed by frame 0's root transform, the same
  30 settle frames blending the body from the T-pose into frame 0, then the motion),
  cloth via ``ModelBuilder.add_cloth_mesh`` (area density 0.15 kg/m^2, particle
  radius = our 4 mm thickness), gravity -9.81 z;
- band (waist) particles kinematic: mass 0, their positions written every substep
  from the skinned band (same rigid bone interpolation across substeps as ours);
- the body as a *deforming* collider: a static mesh shape (identity transform) whose
  ``wp.Mesh`` points are re-skinned and refit every substep (our ``skin_body``
  kernel), and whose collision AABB (``model.shape_collision_aabb_lower/upper``) is
  overwritten every frame with the bounds of the posed body over the frame (+5 cm);
  newton treats the shape as static, so contact friction is against a motionless
  surface (the skin velocity is not passed);
- substeps x iterations = 10 x 5 (as in the shared notes).
Time per frame = wall time of the stepping loop (skinning, collision detection, VBD,
band update) / simulated frame steps (settle included), like ours.
"""
from __future__ import annotations

import time

import numpy as np
import torch

SUBSTEPS = 10
ITERATIONS = 5


def _keys(A: torch.Tensor, pivots: torch.Tensor, settle_frames: int):
    """Key poses exactly as ``simulate`` builds them (T-pose at frame 0's placement, blend, motion)."""
    from anidress_core.sim import setup as S

    A_T = A[0, :1].expand(A.shape[1], 4, 4).clone()
    keys = [A_T]
    for k in range(1, settle_frames + 1):
        wk = torch.tensor([S.smootherstep(k / settle_frames)], dtype=torch.float64)
        keys.append(S.interpolate_transforms(A_T, A[0], pivots, wk)[0])
    keys.extend(A[t] for t in range(1, A.shape[0]))
    return keys, A_T


def run_newton(verts, faces, band, gw, body_rest, body_faces, body_weights, transforms, fps: float,
               settle_frames: int = 30, substeps: int = SUBSTEPS, iterations: int = ITERATIONS,
               tri_ke: float = 1.0e4, tri_ka: float = 1.0e4, tri_kd: float = 1.0e-6, edge_ke: float = 1.0e-3,
               contact_ke: float = 1.0e4, contact_kd: float = 1.0e-6, mu: float = 0.3, thickness: float = 0.004,
               density: float = 0.15):
    """Simulate with newton SolverVBD on the CPU. Returns (frames (T, V, 3) float32, wall_s, frame_steps)."""
    import warp as wp

    import newton
    from anidress_core.sim import kernels as K
    from anidress_core.sim import setup as S

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    dev = "cpu"
    gr = np.asarray(verts, np.float64)
    br = np.asarray(body_rest, np.float64)
    bw = np.asarray(body_weights, np.float64)
    bf = np.asarray(body_faces, np.int64)
    A = torch.as_tensor(np.asarray(transforms, np.float64))
    T = A.shape[0]
    pivots = torch.from_numpy(S.joint_pivots(br, bw))
    keys, A_T = _keys(A, pivots, settle_frames)
    x0 = (gr @ A_T[0, :3, :3].numpy().T + A_T[0, :3, 3].numpy()).astype(np.float32)

    # Body mesh skinned to the first key (the collider's points are overwritten in place).
    bb, bwt = S.sparse_weights(bw)
    body_rest_w = wp.array(br.astype(np.float32), dtype=wp.vec3, device=dev)
    body_bone = wp.array2d(bb, dtype=wp.int32, device=dev)
    body_w = wp.array2d(bwt, dtype=wp.float32, device=dev)
    max_move = wp.zeros(1, dtype=wp.float32, device=dev)
    Vb = br.shape[0]

    def skin_np(M):
        Mw = torch.einsum("vj,jab->vab", torch.from_numpy(bw), M)
        return (torch.einsum("vab,vb->va", Mw[:, :3, :3], torch.from_numpy(br)) + Mw[:, :3, 3]).numpy()

    b0 = skin_np(keys[0]).astype(np.float32)

    builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -9.81))
    cfg = builder.default_shape_cfg.copy()
    cfg.mu = mu
    body_mesh = newton.Mesh(b0, bf.reshape(-1).astype(np.int32), compute_inertia=False)
    builder.add_shape_mesh(body=-1, mesh=body_mesh, cfg=cfg)
    builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                           vertices=[wp.vec3(*p) for p in x0], indices=np.asarray(faces, np.int64).reshape(-1).tolist(),
                           density=density, tri_ke=tri_ke, tri_ka=tri_ka, tri_kd=tri_kd, edge_ke=edge_ke,
                           particle_radius=thickness)
    band_idx = np.nonzero(band)[0]
    for i in band_idx:
        builder.particle_mass[int(i)] = 0.0
    builder.color(include_bending=True)
    model = builder.finalize(device=dev)
    model.soft_contact_ke = contact_ke
    model.soft_contact_kd = contact_kd
    model.soft_contact_mu = mu
    solver = newton.solvers.SolverVBD(model=model, iterations=iterations)
    s0, s1 = model.state(), model.state()
    control = model.control()
    pipeline = newton.CollisionPipeline(model, soft_contact_gap=0.02)
    contacts = pipeline.contacts()
    wmesh = body_mesh.mesh  # the wp.Mesh newton built (its id is in model.shape_source_ptr)
    pts = wmesh.points
    vel = wp.zeros(Vb, dtype=wp.vec3, device=dev)
    band_rest = np.asarray(gr[band_idx])
    band_w = torch.from_numpy(np.asarray(gw, np.float64)[band_idx])
    band_idx_w = wp.array(band_idx.astype(np.int32), dtype=wp.int32, device=dev)
    band_buf = wp.zeros(len(band_idx), dtype=wp.vec3, device=dev)

    @wp.kernel
    def scatter(src: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.int32), q: wp.array(dtype=wp.vec3),
                qd: wp.array(dtype=wp.vec3), inv_dt: float):
        n = wp.tid()
        i = idx[n]
        qd[i] = (src[n] - q[i]) * inv_dt
        q[i] = src[n]

    dt = 1.0 / fps / substeps
    frames = np.zeros((T, gr.shape[0], 3), np.float32)
    nsteps = len(keys) - 1
    t0 = time.perf_counter()
    for k in range(1, len(keys)):
        w = torch.arange(1, substeps + 1, dtype=torch.float64) / substeps
        Ms = S.interpolate_transforms(keys[k - 1], keys[k], pivots, w)  # (n, 24, 4, 4)
        Tarr = wp.array(Ms.reshape(-1, 4, 4).numpy().astype(np.float32), dtype=wp.mat44, device=dev)
        Mb = torch.einsum("bj,sjac->sbac", band_w, Ms)
        band_pos = (torch.einsum("sbac,bc->sba", Mb[..., :3, :3], torch.from_numpy(band_rest)) + Mb[..., :3, 3])
        band_pos = band_pos.numpy().astype(np.float32)
        # Collision AABB of the (static-at-identity) body shape: posed bounds over the frame + margin.
        pcur = pts.numpy()
        pend = skin_np(keys[k])
        lo = np.minimum(pcur.min(0), pend.min(0)) - 0.05
        hi = np.maximum(pcur.max(0), pend.max(0)) + 0.05
        model.shape_collision_aabb_lower.assign(lo[None].astype(np.float32))
        model.shape_collision_aabb_upper.assign(hi[None].astype(np.float32))
        for s in range(substeps):
            wp.launch(K.skin_body, Vb, inputs=[body_rest_w, body_bone, body_w, Tarr, s * 24, 1.0 / dt, pts, vel,
                                               max_move], device=dev)
            wmesh.refit()
            band_buf.assign(band_pos[s])
            wp.launch(scatter, len(band_idx), inputs=[band_buf, band_idx_w, s0.particle_q, s0.particle_qd, 1.0 / dt],
                      device=dev)
            s0.clear_forces()
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        f = k - settle_frames
        if f >= 0:
            frames[f] = s0.particle_q.numpy()
    wall = time.perf_counter() - t0
    run_newton.last_contacts = int(contacts.soft_contact_count.numpy()[0])
    if settle_frames == 0:
        frames[0] = x0
    return frames, wall, nsteps


if __name__ == "__main__":  # quick smoke run: python -m benchmarks.bench_sim_newton [frames] [vertices]
    import sys

    from anidress_core.body import make_motion, mannequin_model
    from anidress_core.garment import make_skirt
    from anidress_core.sim import edge_stretch, penetration_depth

    nfr = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    nv = int(sys.argv[2]) if len(sys.argv) > 2 else 3000
    body = mannequin_model()
    tpl = make_skirt(body, target_vertices=nv)
    m = make_motion("twirl", 300)
    posed = body.pose(m.poses[:nfr], m.Rh[:nfr], m.Th[:nfr])
    fr, wall, n = run_newton(tpl.verts, tpl.faces, tpl.band, tpl.body_weights, body.v_template.numpy(),
                             body.faces.numpy(), body.weights.numpy(), posed.transforms.numpy(), m.fps,
                             settle_frames=int(sys.argv[3]) if len(sys.argv) > 3 else 30)
    st = edge_stretch(fr, tpl.verts, tpl.faces)
    pen = penetration_depth(fr, posed.vertices, body.faces)[:, ~tpl.band]
    print(f"ms/frame {1000 * wall / n:.1f} p99 {np.nanmax(np.nanpercentile(st, 99, axis=1)):.3f} "
          f"max {np.nanmax(st):.3f} pen {pen.max() * 1000:.1f} mm nan {int((~np.isfinite(fr)).sum())} "
          f"soft contacts (last substep) {run_newton.last_contacts}")
