"""XPBD cloth simulation of a garment template on a moving skinned body (Warp kernels).

Design (measured on the project machine, see shared notes "cloth-solvers"): XPBD
(Macklin et al. 2016) with Gauss–Seidel over a graph colouring of the distance
constraints, long-range attachments to the band (Kim et al. 2012), body collision
against the skinned body mesh through ``wp.Mesh`` closest-point queries once per
substep, push-out to a thickness, friction relative to the skin velocity.

Per substep (dt = time_scale / (fps * substeps)):
 1. skin the body with the bone transforms interpolated to the substep's end,
    write mesh points and velocities, refit the BVH;
 2. skin the band (kinematic) particles the same way;
 3. predict x* = x + dt (v + dt g), v damped by exp(-damping dt);
 4. query the closest body point of each particle within ``collision_radius``;
 5. ``iterations`` times: every colour group of distance constraints (stretch edges,
    bending cross-edges), then long-range attachments, then contact push-out;
 6. final push-out with friction relative to the skin, v = (x - x_prev) / dt.
After each frame the state is checked (NaN/inf, stretch, penetration); a failed
frame is redone from its start state with twice the substeps (see ``simulate``).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from . import setup as S

log = logging.getLogger("anidress.sim")

__all__ = ["ClothParams", "SimStats", "SimResult", "SimulationError", "simulate"]


class SimulationError(RuntimeError):
    """The solver still failed its stability checks after every allowed refinement."""


@dataclass(frozen=True)
class ClothParams:
    """Material and solver settings of :func:`simulate` (SI units)."""

    substep_dt: float = 1.0 / 900.0
    """Target simulated seconds per substep; substeps per frame =
    ceil(time_scale / (fps * substep_dt)) (30 at 30 fps). Ignored if ``substeps`` is set."""
    substeps: int | None = None
    """Fixed number of substeps per captured frame (overrides ``substep_dt``)."""
    iterations: int = 2
    """Constraint iterations (Gauss–Seidel sweeps over all colours) per substep."""
    stretch_compliance: float = 0.0
    """XPBD compliance of each edge's distance constraint C = |x_i - x_j| - L0, in m/N
    (0: inextensible up to convergence)."""
    bend_stiffness: float = 1e-4
    """Bending stiffness k_b in joules (paper / Houdini Vellum: 1e-4, a soft fabric).
    Each interior edge gets a cross-edge constraint between the two opposite vertices
    with the normalised strain C = (d - d0) / d0 and energy 1/2 k_b C^2, i.e. XPBD
    compliance alpha = 1 / k_b on C, applied as alpha = d0^2 / k_b on d - d0. 0 turns
    bending off."""
    area_density: float = 0.15
    """Fabric mass per area, kg/m^2 (cotton/viscose dress fabric ~0.1-0.2)."""
    damping: float = 0.5
    """Velocity damping rate, 1/s: v <- v exp(-damping dt) each substep."""
    friction: float = 0.3
    """Coulomb friction coefficient against the body (relative to the skin velocity)."""
    thickness: float = 0.004
    """Collision thickness, m: particles are pushed out to this distance from the skin."""
    collision_radius: float = 0.02
    """Closest-point query radius, m (> thickness + the body's travel in one substep)."""
    query_margin: float = 0.02
    """Fused CPU path: queries look this much farther than ``collision_radius`` so that a
    particle found clear of the body can skip its queries until its clearance bound
    (own motion + the body's largest vertex travel since) drops below the radius; the
    contacts are the same as querying every particle every substep."""
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    """m/s^2, world z-up."""
    time_scale: float = 1.0
    """Simulated seconds per captured second (Houdini's time scale). The body covers
    one captured frame in time_scale / fps simulated seconds: > 1 makes the garment's
    own dynamics (falling, swinging, settling) faster relative to the body motion
    (the body looks slower to the cloth), < 1 slower. Substeps scale with it so the
    substep dt stays at ``substep_dt``."""
    settle_frames: int = 30
    """Frames (at the motion's fps) before frame 0 during which the body blends from
    the T-pose placed by frame 0's root transform into frame 0's pose (C2 ease),
    starting from the garment's rest state; 0 starts from the garment skinned to
    frame 0 with zero velocity. Not part of the output."""
    max_stretch: float = 1.5
    """Blow-up bound on edge length / rest length (edges with a free particle)."""
    max_penetration: float = 0.03
    """Blow-up bound on the depth of a free particle inside the body, m."""
    max_refinements: int = 3
    """How many times a failed frame may be redone with twice the substeps."""
    fused_cpu: bool | None = None
    """CPU only: run each substep after the body refit as one fused serial kernel with
    recorded launches (same Gauss–Seidel order and results as the per-colour launches,
    ~3 host calls per substep instead of ~40). None: on whenever the device is the CPU;
    False: the per-colour launch path (the one used on CUDA)."""
    graph_capture: bool = True
    """Per-kernel path (CUDA, or the CPU with fused_cpu False): capture a frame's launches once per
    substep count as a Warp graph (a CUDA graph on the GPU) and replay it, one launch per frame
    instead of ~30 per substep whose host-side cost bounds that path (benchmarks/cuda.md).
    False: launch kernel by kernel. Same kernels in the same order either way."""
    device: str | None = None
    """Warp device ("cpu", "cuda", "cuda:0"); None: CUDA when available, else CPU."""


class SimStats(NamedTuple):
    """Per output frame (T,) arrays and run information."""

    max_stretch: np.ndarray  # (T,) max edge length / rest length
    p99_stretch: np.ndarray  # (T,) 99th percentile of edge length / rest length
    max_penetration_m: np.ndarray  # (T,) deepest free particle inside the body, m (0 if none)
    nan_count: np.ndarray  # (T,) non-finite vertex coordinates
    substeps: np.ndarray  # (T,) substeps used for the frame (after refinements)
    recoveries: list  # dicts: frame (-settle_frames..T-1), reason, substeps tried
    wall_s: float  # wall-clock seconds of the whole call


class SimResult(NamedTuple):
    frames: np.ndarray  # (T, V, 3) float32 garment vertices, world
    stats: SimStats


def _np(a, dtype) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=dtype)


def _device(name: str | None) -> str:
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    if name is not None:
        return name
    return "cuda" if wp.is_cuda_available() else "cpu"


class _Solver:
    """Warp state and launches of one garment on one body (internal)."""

    def __init__(self, g_rest, g_faces, band, g_weights, b_rest, b_faces, b_weights, pivots, params, device):
        import warp as wp

        from . import kernels as K

        self.wp, self.K, self.p, self.device = wp, K, params, device
        V = g_rest.shape[0]
        self.V = V
        # 1. Constraints, colouring, masses, attachments (numpy, once).
        topo = S.build_topology(g_rest, g_faces)
        self.topo = topo
        comp = np.where(
            topo.is_bend,
            topo.rest ** 2 / params.bend_stiffness if params.bend_stiffness > 0 else np.inf,
            params.stretch_compliance,
        )
        keep_c = np.isfinite(comp)
        if not keep_c.all():  # bending off: drop those constraints, keep colour order
            starts = np.searchsorted(np.nonzero(keep_c)[0], topo.color_starts)
            topo = topo._replace(pairs=topo.pairs[keep_c], rest=topo.rest[keep_c], is_bend=topo.is_bend[keep_c],
                                 color_starts=starts)
            comp = comp[keep_c]
        self.groups = [(int(a), int(b - a)) for a, b in zip(topo.color_starts[:-1], topo.color_starts[1:]) if b > a]
        mass = S.vertex_masses(g_rest, g_faces, params.area_density)
        inv_mass = np.where(band | (mass <= 0), 0.0, 1.0 / np.maximum(mass, 1e-12))
        anchor, max_dist = S.long_range_attachments(g_rest, topo.edges, band)
        gb, gw = S.sparse_weights(g_weights[band])
        bb, bw = S.sparse_weights(b_weights)
        # Edges checked for blow-ups: the ones with a free particle.
        e = topo.edges
        self.check_edges = e[~(band[e[:, 0]] & band[e[:, 1]])]
        self.check_rest = np.linalg.norm(g_rest[self.check_edges[:, 0]] - g_rest[self.check_edges[:, 1]], axis=1)
        self.free = ~band
        te = topo.edges
        self._rest_len = np.linalg.norm(g_rest[te[:, 0]] - g_rest[te[:, 1]], axis=1)
        self._check_sel = ~(band[te[:, 0]] & band[te[:, 1]])
        self.pivots = pivots

        d = device
        f32, i32, v3 = wp.float32, wp.int32, wp.vec3
        arr = lambda a, t: wp.array(a, dtype=t, device=d)  # noqa: E731
        self.x = wp.zeros(V, dtype=v3, device=d)
        self.v = wp.zeros(V, dtype=v3, device=d)
        self.x_prev = wp.zeros(V, dtype=v3, device=d)
        self.inv_mass = arr(inv_mass.astype(np.float32), f32)
        self.band_target = wp.zeros(V, dtype=v3, device=d)
        self.ci = arr(topo.pairs[:, 0].astype(np.int32), i32)
        self.cj = arr(topo.pairs[:, 1].astype(np.int32), i32)
        self.c_rest = arr(topo.rest.astype(np.float32), f32)
        self.c_comp = arr(comp.astype(np.float32), f32)
        self.lam = wp.zeros(len(topo.rest), dtype=f32, device=d)
        self.anchor = arr(anchor.astype(np.int32), i32)
        self.max_dist = arr(max_dist.astype(np.float32), f32)
        self.band_rest = arr(g_rest[band].astype(np.float32), v3)
        self.band_idx = arr(np.nonzero(band)[0].astype(np.int32), i32)
        self.band_bone = wp.array2d(gb, dtype=i32, device=d)
        self.band_w = wp.array2d(gw, dtype=f32, device=d)
        self.n_band = int(band.sum())
        self.body_rest = arr(b_rest.astype(np.float32), v3)
        self.body_bone = wp.array2d(bb, dtype=i32, device=d)
        self.body_w = wp.array2d(bw, dtype=f32, device=d)
        self.Vb = b_rest.shape[0]
        self.body_pts = arr(b_rest.astype(np.float32), v3)
        self.body_vel = wp.zeros(self.Vb, dtype=v3, device=d)
        self.body_idx = arr(b_faces.reshape(-1).astype(np.int32), i32)
        self.mesh = None  # built by set_body, on posed points (refit keeps the tree's topology)
        self.cp = wp.zeros(V, dtype=v3, device=d)
        self.cn = wp.zeros(V, dtype=v3, device=d)
        self.cv = wp.zeros(V, dtype=v3, device=d)
        self.cf = wp.zeros(V, dtype=i32, device=d)
        self.sd = wp.zeros(V, dtype=f32, device=d)
        self.gravity = wp.vec3(*[float(g) for g in params.gravity])
        is_cpu = wp.get_device(d).is_cpu
        self.serial = is_cpu if params.fused_cpu is None else (bool(params.fused_cpu) and is_cpu)
        self.graphs = bool(params.graph_capture) and not self.serial
        self._plans: dict = {}
        # Contact-query skipping (fused CPU path, see kernels.substep_serial).
        self.max_move = wp.zeros(1, dtype=f32, device=d)
        self.travel = wp.zeros(1, dtype=wp.float64, device=d)
        self.q_pos = wp.zeros(V, dtype=v3, device=d)
        self.q_clear = wp.full(V, -1.0, dtype=f32, device=d)
        self.q_travel = wp.zeros(V, dtype=wp.float64, device=d)

    # -- state ---------------------------------------------------------------
    def set_body(self, M: np.ndarray) -> None:
        """Skin the body to transforms (24, 4, 4) with zero velocity, refit."""
        wp, K = self.wp, self.K
        T = wp.array(M.astype(np.float32), dtype=wp.mat44, device=self.device)
        wp.launch(K.skin_body, self.Vb, inputs=[self.body_rest, self.body_bone, self.body_w, T, 0, 0.0,
                                                self.body_pts, self.body_vel, self.max_move], device=self.device)
        self.body_vel.zero_()
        self.max_move.zero_()
        self.q_clear.fill_(-1.0)
        self.mesh = wp.Mesh(points=self.body_pts, velocities=self.body_vel, indices=self.body_idx)
        self._plans = {}  # recorded launches hold the mesh id

    def get_state(self):
        return self.x.numpy().copy(), self.v.numpy().copy(), self.body_pts.numpy().copy()

    def set_state(self, st) -> None:
        self.x.assign(st[0])
        self.v.assign(st[1])
        self.body_pts.assign(st[2])
        self.body_vel.zero_()
        self.max_move.zero_()
        self.q_clear.fill_(-1.0)  # forget the clearance bounds: query every particle next substep
        self.mesh.refit()

    # -- one frame -----------------------------------------------------------
    def _plan(self, n: int, frame_time: float):
        """Recorded launches of a frame with ``n`` substeps (CPU fused path), cached per n."""
        plan = self._plans.get(n)
        if plan is not None:
            return plan
        wp, K, p, d = self.wp, self.K, self.p, self.device
        dt = frame_time / n
        Tarr = wp.zeros(n * 24, dtype=wp.mat44, device=d)
        skin, step = [], []
        for s in range(n):
            skin.append(wp.launch(K.skin_body, self.Vb, inputs=[self.body_rest, self.body_bone, self.body_w, Tarr,
                                                                s * 24, 1.0 / dt, self.body_pts, self.body_vel,
                                                                self.max_move],
                                  device=d, record_cmd=True))
            step.append(wp.launch(K.substep_serial, 1, inputs=[
                self.x, self.v, self.x_prev, self.inv_mass, self.band_rest, self.band_bone, self.band_w,
                self.band_idx, self.band_target, Tarr, s * 24, self.mesh.id, p.collision_radius, self.gravity,
                math.exp(-p.damping * dt), dt, 1.0 / (dt * dt), self.ci, self.cj, self.c_rest, self.c_comp,
                self.lam, self.anchor, self.max_dist, self.cp, self.cn, self.cv, self.cf, p.thickness,
                p.friction, p.iterations, p.collision_radius + max(p.query_margin, 0.0), self.max_move, self.travel,
                self.q_pos, self.q_clear, self.q_travel], device=d, record_cmd=True))
        plan = self._plans[n] = (Tarr, skin, step)
        return plan

    def step_frame(self, A0: torch.Tensor, A1: torch.Tensor, n: int, frame_time: float) -> None:
        """Advance one frame in ``n`` substeps while the bones go from A0 to A1 (24, 4, 4)."""
        wp, K, p, d = self.wp, self.K, self.p, self.device
        dt = frame_time / n
        w = torch.arange(1, n + 1, dtype=torch.float64) / n
        Ms = S.interpolate_transforms(A0, A1, self.pivots, w)  # (n, 24, 4, 4)
        Ms = Ms.reshape(-1, 4, 4).numpy().astype(np.float32)
        if self.serial:
            # CPU: per substep one skinning launch, the refit and one fused serial launch,
            # all recorded once per substep count (no argument packing per substep).
            Tarr, skin, step = self._plan(n, frame_time)
            Tarr.assign(Ms)
            refit = self.mesh.refit
            for s in range(n):
                skin[s].launch()
                refit()
                step[s].launch()
            return
        if self.graphs:
            Tarr, graph = self._graph(n, frame_time)
            Tarr.assign(Ms)
            wp.capture_launch(graph)
            return
        self._substeps(wp.array(Ms, dtype=wp.mat44, device=d), n, frame_time)

    def _graph(self, n: int, frame_time: float):
        """(bone transforms array, graph) of a frame with ``n`` substeps, captured once per (n, frame
        time); the graph holds the mesh id and the array, so set_body clears it with the recorded launches."""
        key = ("graph", n, frame_time)
        plan = self._plans.get(key)
        if plan is None:
            wp = self.wp
            wp.load_module(self.K, device=self.device)  # compile before the capture, and only this module
            Tarr = wp.zeros(n * 24, dtype=wp.mat44, device=self.device)
            with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                self._substeps(Tarr, n, frame_time)
            plan = self._plans[key] = (Tarr, cap.graph)
        return plan

    def _substeps(self, Tarr, n: int, frame_time: float) -> None:
        """The per-kernel launches of ``n`` substeps (bone transforms ``Tarr``: n x 24 mat44)."""
        wp, K, p, d = self.wp, self.K, self.p, self.device
        dt = frame_time / n
        damp = math.exp(-p.damping * dt)
        inv_dt2 = 1.0 / (dt * dt)
        V = self.V
        for s in range(n):
            # 1-2. Skinned body (mesh points + velocities) and band targets.
            wp.launch(K.skin_body, self.Vb, inputs=[self.body_rest, self.body_bone, self.body_w, Tarr, s * 24,
                                                    1.0 / dt, self.body_pts, self.body_vel, self.max_move],
                      device=d)
            self.mesh.refit()
            if self.n_band:
                wp.launch(K.skin_points, self.n_band, inputs=[self.band_rest, self.band_bone, self.band_w, Tarr,
                                                              s * 24, self.band_idx, self.band_target], device=d)
            # 3. Prediction.
            wp.launch(K.integrate, V, inputs=[self.x, self.v, self.x_prev, self.inv_mass, self.band_target,
                                              self.gravity, damp, dt], device=d)
            # 4. Contacts, once per substep.
            wp.launch(K.collide_query, V, inputs=[self.mesh.id, self.x, self.x_prev, self.inv_mass,
                                                  p.collision_radius, self.cp, self.cn, self.cv, self.cf], device=d)
            # 5. Gauss–Seidel over colour groups, attachments, contacts.
            self.lam.zero_()
            for _ in range(p.iterations):
                for start, count in self.groups:
                    wp.launch(K.solve_distance, count, inputs=[self.x, self.inv_mass, self.ci, self.cj, self.c_rest,
                                                               self.c_comp, self.lam, start, inv_dt2], device=d)
                wp.launch(K.solve_attachments, V, inputs=[self.x, self.inv_mass, self.anchor, self.max_dist], device=d)
                wp.launch(K.solve_contacts, V, inputs=[self.x, self.cp, self.cn, self.cf, p.thickness], device=d)
            # 6. Friction, final push-out, velocities.
            wp.launch(K.finalize, V, inputs=[self.x, self.x_prev, self.v, self.inv_mass, self.cp, self.cn, self.cv,
                                             self.cf, p.thickness, p.friction, dt], device=d)

    def check(self) -> tuple[np.ndarray, dict]:
        """Positions (V, 3) and the frame's metrics."""
        wp, K = self.wp, self.K
        x = self.x.numpy().copy()
        nan = int((~np.isfinite(x)).sum())
        with np.errstate(invalid="ignore"):
            r_all = np.linalg.norm(x[self.topo.edges[:, 0]] - x[self.topo.edges[:, 1]], axis=1) / self._rest_len
            r_chk = r_all[self._check_sel]
        depth_cap = 2.0 * max(self.p.max_penetration, self.p.collision_radius)
        if self.serial:  # particles with a positive clearance bound are outside: skip their query
            wp.launch(K.signed_distance_bounded, self.V, inputs=[self.mesh.id, self.x, depth_cap, 0.0, self.travel,
                                                                 self.q_pos, self.q_clear, self.q_travel, self.sd],
                      device=self.device)
        else:
            wp.launch(K.signed_distance_fast, self.V, inputs=[self.mesh.id, self.x, depth_cap, self.sd],
                      device=self.device)
        sd = self.sd.numpy()
        pen = float(np.clip(-sd[self.free], 0, None).max()) if self.free.any() else 0.0
        m = {
            "nan": nan,
            "max_stretch": float(np.nanmax(r_all)) if r_all.size else 1.0,
            "p99_stretch": (float(np.percentile(r_all, 99)) if nan == 0 else float(np.nanpercentile(r_all, 99)))
            if r_all.size else 1.0,
            "check_stretch": float(np.max(r_chk)) if r_chk.size else 1.0,
            "penetration": pen,
        }
        return x, m


def _check_inputs(gr, gf, band, gw, br, bf, bw, A):
    V = gr.shape[0]
    if gr.ndim != 2 or gr.shape[1] != 3:
        raise ValueError(f"simulate: garment_rest must be (V, 3), got {gr.shape}")
    if gf.ndim != 2 or gf.shape[1] != 3 or (gf.size and (gf.min() < 0 or gf.max() >= V)):
        raise ValueError(f"simulate: garment_faces must be (F, 3) indices into {V} vertices, got {gf.shape}")
    if band.shape != (V,):
        raise ValueError(f"simulate: band must be ({V},) bool, got {band.shape}")
    if gw.ndim != 2 or gw.shape[0] != V:
        raise ValueError(f"simulate: garment_body_weights must be ({V}, J), got {gw.shape}")
    if br.ndim != 2 or br.shape[1] != 3:
        raise ValueError(f"simulate: body_rest must be (Vb, 3), got {br.shape}")
    if bf.ndim != 2 or bf.shape[1] != 3 or (bf.size and (bf.min() < 0 or bf.max() >= br.shape[0])):
        raise ValueError(f"simulate: body_faces must be (Fb, 3) indices into {br.shape[0]} vertices, got {bf.shape}")
    J = gw.shape[1]
    if bw.shape != (br.shape[0], J):
        raise ValueError(f"simulate: body_weights must be ({br.shape[0]}, {J}), got {bw.shape}")
    if A.ndim != 4 or A.shape[1:] != (J, 4, 4) or A.shape[0] < 1:
        raise ValueError(f"simulate: body_transforms must be (T, {J}, 4, 4), got {A.shape}")
    for name, a in (("garment_rest", gr), ("body_rest", br), ("body_transforms", A)):
        S._check_finite(name, a)


def simulate(garment_rest, garment_faces, band, garment_body_weights, body_rest, body_faces, body_weights,
             body_transforms, fps: float, params: ClothParams = ClothParams(), progress: bool = False) -> SimResult:
    """Simulate a garment on a skinned body moving through ``body_transforms``.

    garment_rest: (V, 3) garment in the body's rest (canonical) space;
    garment_faces: (F, 3); band: (V,) bool, vertices that follow the body skinning
    (waist band, shoulder straps): x_band(t) = LBS(garment_rest, garment_body_weights,
    A(t)); garment_body_weights: (V, J); body_rest: (Vb, 3); body_faces: (Fb, 3)
    closed, outward oriented; body_weights: (Vb, J); body_transforms: (T, J, 4, 4)
    rest -> world per frame (``BodyModel.pose(...).transforms``); fps: frames per
    captured second. numpy arrays or torch tensors.

    The run starts with the garment rest state placed rigidly by frame 0's root
    transform A[0, 0] (the T-pose at frame 0's Rh/Th), blends the body into frame 0
    over ``params.settle_frames`` frames, then follows frames 1..T-1; bone transforms
    are interpolated rigidly across substeps (see setup.interpolate_transforms).

    Stability: after every frame (settle included) the state is checked for
    NaN/inf, edge stretch > ``max_stretch`` and penetration > ``max_penetration``;
    a failing frame is restored to its start state and redone with twice the
    substeps, up to ``max_refinements`` times (each logged as a warning on logger
    ``anidress.sim``), then :class:`SimulationError` is raised.

    Returns SimResult(frames (T, V, 3) float32 world, stats SimStats).
    """
    t_start = time.perf_counter()
    p = params
    gr = _np(garment_rest, np.float64)
    gf = _np(garment_faces, np.int64)
    bd = _np(band, bool)
    gw = _np(garment_body_weights, np.float64)
    br = _np(body_rest, np.float64)
    bf = _np(body_faces, np.int64)
    bw = _np(body_weights, np.float64)
    A = _np(body_transforms, np.float64)
    _check_inputs(gr, gf, bd, gw, br, bf, bw, A)
    if fps <= 0 or p.time_scale <= 0:
        raise ValueError(f"simulate: fps and time_scale must be > 0, got {fps}, {p.time_scale}")
    if p.iterations < 1 or p.settle_frames < 0 or p.max_refinements < 0:
        raise ValueError("simulate: need iterations >= 1, settle_frames >= 0, max_refinements >= 0")
    if p.substeps is not None and p.substeps < 1:
        raise ValueError(f"simulate: substeps must be >= 1, got {p.substeps}")
    device = _device(p.device)
    T = A.shape[0]
    frame_time = p.time_scale / fps
    n_base = p.substeps if p.substeps is not None else S.substeps_for(fps, p.time_scale, p.substep_dt)

    At = torch.from_numpy(A)
    pivots = torch.from_numpy(S.joint_pivots(br, bw))
    sol = _Solver(gr, gf, bd, gw, br, bf, bw, pivots, p, device)

    # Key poses: T-pose at frame 0's placement, the settle blend, then the motion.
    if p.settle_frames > 0:
        A_T = At[0, :1].expand(At.shape[1], 4, 4).clone()
        keys = [A_T]
        for k in range(1, p.settle_frames + 1):
            wk = torch.tensor([S.smootherstep(k / p.settle_frames)], dtype=torch.float64)
            keys.append(S.interpolate_transforms(A_T, At[0], pivots, wk)[0])
        x0 = (torch.einsum("ab,vb->va", A_T[0, :3, :3], torch.from_numpy(gr)) + A_T[0, :3, 3]).numpy()
    else:
        keys = [At[0]]
        from ..geometry import lbs

        x0 = lbs(torch.from_numpy(gr), torch.from_numpy(gw), At[0]).numpy()
    keys.extend(At[t] for t in range(1, T))
    sol.x.assign(x0.astype(np.float32))
    sol.set_body(keys[0].numpy())

    frames = np.zeros((T, gr.shape[0], 3), np.float32)
    st = {k: np.zeros(T) for k in ("max_stretch", "p99_stretch", "penetration", "nan", "substeps")}
    recoveries: list[dict] = []
    settle = len(keys) - T  # index of frame 0 in keys

    def record(t, x, m, n):
        frames[t] = x
        st["max_stretch"][t] = m["max_stretch"]
        st["p99_stretch"][t] = m["p99_stretch"]
        st["penetration"][t] = m["penetration"]
        st["nan"][t] = m["nan"]
        st["substeps"][t] = n

    if settle == 0:
        x, m = sol.check()
        record(0, x, m, 0)
    it = range(1, len(keys))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="simulate", unit="frame")
    for k in it:
        frame = k - settle  # negative during the settle phase
        start = sol.get_state()
        n = n_base
        for attempt in range(p.max_refinements + 1):
            sol.step_frame(keys[k - 1], keys[k], n, frame_time)
            x, m = sol.check()
            reason = None
            if m["nan"] > 0:
                reason = f"{m['nan']} non-finite coordinates"
            elif m["check_stretch"] > p.max_stretch:
                reason = f"edge stretch {m['check_stretch']:.3f} > {p.max_stretch}"
            elif m["penetration"] > p.max_penetration:
                reason = f"penetration {m['penetration'] * 1000:.1f} mm > {p.max_penetration * 1000:.1f} mm"
            if reason is None:
                break
            recoveries.append({"frame": frame, "reason": reason, "substeps": n, "attempt": attempt})
            if attempt == p.max_refinements:
                raise SimulationError(
                    f"simulate: frame {frame} still unstable with {n} substeps after {attempt} refinements: {reason}"
                )
            log.warning("frame %d: %s with %d substeps; redoing it with %d substeps", frame, reason, n, 2 * n)
            sol.set_state(start)
            n *= 2
        if frame >= 0:
            record(frame, x, m, n)
    stats = SimStats(
        max_stretch=st["max_stretch"], p99_stretch=st["p99_stretch"], max_penetration_m=st["penetration"],
        nan_count=st["nan"].astype(np.int64), substeps=st["substeps"].astype(np.int64), recoveries=recoveries,
        wall_s=time.perf_counter() - t_start,
    )
    return SimResult(frames, stats)
