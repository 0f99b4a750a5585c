"""A procedural, rigged, UV-mapped mannequin body in the SMPL canonical frame.

One module (over 800 lines): one build, run once and cached, whose steps share the primitives table.

Stand-in for the SMPL body (Loper et al. 2015) when no licensed model file is
available. The body is an implicit surface: a smooth union (polynomial smooth-min,
Quilez, "Smooth minimum", iquilezles.org) of round cones and ellipsoids placed on a
rest skeleton with SMPL-like joint positions, polygonised by marching cubes
(Lewiner et al. 2003, ``skimage.measure.marching_cubes``) and then remeshed
(isotropic explicit remeshing, Botsch & Kobbelt 2004), decimated (quadric edge
collapse, Garland & Heckbert 1997) and Taubin-smoothed (Taubin 1995) with pymeshlab.

Frame: SMPL canonical T-pose, metres, y up, facing +z, x towards the body's left,
pelvis joint at the origin. Everything here is numpy (it is built once and cached);
:func:`anidress_core.body.model.mannequin_model` wraps it as a torch ``BodyModel``.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .kinematic import JOINT_INDEX, NUM_JOINTS, SMPL_PARENTS

__all__ = [
    "MANNEQUIN_VERSION",
    "REFERENCE_HEIGHT",
    "PART_NAMES",
    "PART_BONES",
    "MannequinData",
    "mannequin_joints",
    "build_mannequin",
    "load_or_build_mannequin",
    "cache_dir",
    "cache_path",
]

# Bump whenever the geometry, weights, labels or UVs change: it keys the cache.
MANNEQUIN_VERSION = "mannequin-v5"
# All shape constants below are in metres for a body of this height; a different
# height scales them uniformly.
REFERENCE_HEIGHT = 1.70

PART_NAMES: tuple[str, ...] = (
    "head", "neck", "torso",
    "left_upper_arm", "right_upper_arm", "left_lower_arm", "right_lower_arm",
    "left_hand", "right_hand",
    "left_upper_leg", "right_upper_leg", "left_lower_leg", "right_lower_leg",
    "left_foot", "right_foot",
)
_P = {n: i for i, n in enumerate(PART_NAMES)}

# Joints whose transform may move each part (the seeds of the skinning weights).
PART_BONES: dict[str, tuple[str, ...]] = {
    "head": ("head",),
    "neck": ("neck",),
    "torso": ("pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar"),
    "left_upper_arm": ("left_shoulder",),
    "right_upper_arm": ("right_shoulder",),
    "left_lower_arm": ("left_elbow",),
    "right_lower_arm": ("right_elbow",),
    "left_hand": ("left_wrist", "left_hand"),
    "right_hand": ("right_wrist", "right_hand"),
    "left_upper_leg": ("left_hip",),
    "right_upper_leg": ("right_hip",),
    "left_lower_leg": ("left_knee",),
    "right_lower_leg": ("right_knee",),
    "left_foot": ("left_ankle", "left_foot"),
    "right_foot": ("right_ankle", "right_foot"),
}

# Rest joints of the left side and the midline at REFERENCE_HEIGHT (SMPL-like
# proportions: SMPL's neutral template has the pelvis ~0.94 m above the soles and
# the crown ~0.77 m above the pelvis). Right-side joints mirror x.
_LEFT_AND_MID_JOINTS = {
    "pelvis": (0.000, 0.000, 0.000),
    "left_hip": (0.085, -0.075, 0.000),
    "spine1": (0.000, 0.105, -0.015),
    "left_knee": (0.095, -0.470, 0.010),
    "spine2": (0.000, 0.235, -0.010),
    "left_ankle": (0.090, -0.855, -0.030),
    "spine3": (0.000, 0.295, 0.000),
    "left_foot": (0.105, -0.915, 0.095),
    "neck": (0.000, 0.500, -0.025),
    "left_collar": (0.075, 0.420, -0.015),
    "head": (0.000, 0.575, 0.010),
    "left_shoulder": (0.175, 0.445, -0.020),
    "left_elbow": (0.440, 0.445, -0.035),
    "left_wrist": (0.690, 0.445, -0.030),
    "left_hand": (0.775, 0.440, -0.030),
}
# Free ends of the leaf bones (used for the skinning seeds of head, hands, toes).
_BONE_TIPS = {
    "head": (0.000, 0.740, 0.020),
    "left_hand": (0.860, 0.440, -0.030),
    "left_foot": (0.105, -0.910, 0.160),
}


def mannequin_joints(height: float = REFERENCE_HEIGHT) -> np.ndarray:
    """Rest joint positions (24, 3) of the mannequin skeleton (before the final exact
    height correction applied by :func:`build_mannequin`)."""
    s = height / REFERENCE_HEIGHT
    J = np.zeros((NUM_JOINTS, 3))
    for name, p in _LEFT_AND_MID_JOINTS.items():
        J[JOINT_INDEX[name]] = p
        if name.startswith("left_"):
            J[JOINT_INDEX["right_" + name[5:]]] = (-p[0], p[1], p[2])
    return J * s


def _mirror(p):
    return (-p[0], p[1], p[2])


# --------------------------------------------------------------------------- SDFs
def _sd_round_cone(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Exact signed distance (N,) to the convex hull of spheres (a, ra) and (b, rb)."""
    a = np.asarray(a, p.dtype)
    b = np.asarray(b, p.dtype)
    ab = b - a
    L = float(np.linalg.norm(ab))
    e = ab / L
    pa = p - a
    y = pa @ e  # axial coordinate
    x = np.sqrt(np.maximum((pa * pa).sum(-1) - y * y, 0.0))  # radial coordinate
    sin_a = (ra - rb) / L
    cos_a = np.sqrt(max(1.0 - sin_a * sin_a, 0.0))
    # Coordinate of q = (x, y) along the tangent line; the side is hit for 0 <= s <= L cos_a.
    s = -x * sin_a + y * cos_a
    d_side = x * cos_a + y * sin_a - ra
    d_a = np.sqrt(x * x + y * y) - ra
    d_b = np.sqrt(x * x + (y - L) ** 2) - rb
    return np.where(s < 0, d_a, np.where(s > L * cos_a, d_b, d_side))


def _sd_ellipsoid(p: np.ndarray, c, r) -> np.ndarray:
    """Approximate signed distance (N,) to an axis-aligned ellipsoid (Quilez's bound)."""
    q = (p - np.asarray(c, p.dtype)) / np.asarray(r, p.dtype)
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / np.asarray(r, p.dtype), axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum with blend radius k (Quilez)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


@dataclass(frozen=True)
class _Prim:
    part: str
    kind: str  # "cone" or "ellipsoid"
    args: tuple

    def sdf(self, p: np.ndarray, s: float) -> np.ndarray:
        if self.kind == "cone":
            a, b, ra, rb = self.args
            return _sd_round_cone(p, np.multiply(a, s), np.multiply(b, s), ra * s, rb * s)
        c, r = self.args
        return _sd_ellipsoid(p, np.multiply(c, s), np.multiply(r, s))

    def aabb(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        if self.kind == "cone":
            a, b, ra, rb = self.args
            lo = np.minimum(np.subtract(a, ra), np.subtract(b, rb))
            hi = np.maximum(np.add(a, ra), np.add(b, rb))
        else:
            c, r = self.args
            lo, hi = np.subtract(c, r), np.add(c, r)
        return lo * s, hi * s


def _primitives() -> dict[str, list[_Prim]]:
    """Shape primitives grouped by body part, at REFERENCE_HEIGHT."""
    J = {k: v for k, v in _LEFT_AND_MID_JOINTS.items()}
    P: dict[str, list[_Prim]] = {n: [] for n in PART_NAMES}
    P["torso"] += [
        _Prim("torso", "ellipsoid", ((0.0, -0.020, -0.005), (0.158, 0.120, 0.105))),  # hips
        _Prim("torso", "ellipsoid", ((0.0, -0.050, -0.040), (0.140, 0.090, 0.085))),  # seat
        _Prim("torso", "ellipsoid", ((0.0, 0.160, 0.000), (0.128, 0.150, 0.090))),  # waist
        _Prim("torso", "ellipsoid", ((0.0, 0.320, 0.005), (0.150, 0.140, 0.105))),  # chest
        _Prim("torso", "cone", ((0.03, 0.430, -0.025), J["left_shoulder"], 0.055, 0.052)),
        _Prim("torso", "cone", ((-0.03, 0.430, -0.025), _mirror(J["left_shoulder"]), 0.055, 0.052)),
    ]
    P["neck"] += [_Prim("neck", "cone", ((0.0, 0.440, -0.025), (0.0, 0.575, 0.000), 0.055, 0.050))]
    P["head"] += [
        _Prim("head", "ellipsoid", ((0.0, 0.668, 0.020), (0.078, 0.102, 0.095))),  # cranium
        _Prim("head", "ellipsoid", ((0.0, 0.605, 0.045), (0.058, 0.048, 0.062))),  # jaw
    ]
    for side, m in (("left", lambda q: q), ("right", _mirror)):
        j = lambda n: m(J[f"left_{n}"])  # noqa: E731
        P[f"{side}_upper_arm"] += [_Prim(f"{side}_upper_arm", "cone", (j("shoulder"), j("elbow"), 0.050, 0.040))]
        P[f"{side}_lower_arm"] += [_Prim(f"{side}_lower_arm", "cone", (j("elbow"), j("wrist"), 0.038, 0.028))]
        P[f"{side}_hand"] += [
            _Prim(f"{side}_hand", "ellipsoid", (m((0.770, 0.440, -0.028)), (0.085, 0.022, 0.046))),
            _Prim(f"{side}_hand", "cone", (m((0.715, 0.440, 0.005)), m((0.770, 0.435, 0.040)), 0.014, 0.011)),  # thumb
        ]
        P[f"{side}_upper_leg"] += [_Prim(f"{side}_upper_leg", "cone", (j("hip"), j("knee"), 0.080, 0.053))]
        P[f"{side}_lower_leg"] += [
            _Prim(f"{side}_lower_leg", "cone", (j("knee"), j("ankle"), 0.050, 0.036)),
            _Prim(f"{side}_lower_leg", "ellipsoid", (m((0.094, -0.600, -0.018)), (0.047, 0.120, 0.052))),  # calf
        ]
        P[f"{side}_foot"] += [
            _Prim(f"{side}_foot", "cone", (m((0.090, -0.893, -0.055)), m((0.102, -0.905, 0.150)), 0.036, 0.028)),
            _Prim(f"{side}_foot", "ellipsoid", (m((0.097, -0.900, 0.060)), (0.044, 0.030, 0.090))),
        ]
    return P


# Blend radii of the smooth unions (metres at REFERENCE_HEIGHT): between the
# primitives of one part, and where parts join.
_K_WITHIN = {"torso": 0.08, "neck": 0.03, "head": 0.02, "upper_arm": 0.03, "lower_arm": 0.03, "hand": 0.01,
             "upper_leg": 0.04, "lower_leg": 0.04, "foot": 0.03}
_K_NECK, _K_HEAD, _K_ARM, _K_HAND, _K_LEG, _K_FOOT = 0.03, 0.03, 0.03, 0.015, 0.04, 0.025


def _k_within(part: str) -> float:
    return _K_WITHIN[part.split("_", 1)[1] if part.startswith(("left_", "right_")) else part]


def _combine(part_vals: dict[str, np.ndarray], s: float) -> np.ndarray:
    """Body SDF from per-part SDF arrays (any common shape; each part already the
    smooth union of its own primitives)."""
    P = part_vals
    # 1. Torso, neck and head blend into one core.
    core = _smin(P["torso"], P["neck"], _K_NECK * s)
    core = _smin(core, P["head"], _K_HEAD * s)
    # 2. Each limb is a smooth chain blended into the core; limbs are joined to each
    #    other by a hard min so the thighs (or an arm and a leg) never web together.
    branches = []
    for side in ("left", "right"):
        arm = _smin(P[f"{side}_upper_arm"], P[f"{side}_lower_arm"], _K_ARM * s)
        arm = _smin(arm, P[f"{side}_hand"], _K_HAND * s)
        branches.append(_smin(core, arm, _K_ARM * s))
        leg = _smin(P[f"{side}_upper_leg"], P[f"{side}_lower_leg"], _K_LEG * s)
        leg = _smin(leg, P[f"{side}_foot"], _K_FOOT * s)
        branches.append(_smin(core, leg, _K_LEG * s))
    return np.minimum.reduce(branches)


def _part_sdf(prims: dict[str, list[_Prim]], p: np.ndarray, s: float) -> np.ndarray:
    """Per-part SDF (N, len(PART_NAMES)) at points p (N, 3): min over each part's primitives."""
    out = np.full((p.shape[0], len(PART_NAMES)), np.inf)
    for part, plist in prims.items():
        for pr in plist:
            out[:, _P[part]] = np.minimum(out[:, _P[part]], pr.sdf(p, s))
    return out


# ------------------------------------------------------------------ mesh building
@dataclass(frozen=True)
class MannequinData:
    """The built mannequin, numpy arrays in the canonical T-pose frame."""

    vertices: np.ndarray
    """(V, 3) float32 rest vertices, metres."""
    faces: np.ndarray
    """(F, 3) int64 triangles, counter-clockwise seen from outside."""
    weights: np.ndarray
    """(V, 24) float32 convex skinning weights."""
    joints_rest: np.ndarray
    """(24, 3) float32 rest joints (pelvis at the origin)."""
    parents: np.ndarray
    """(24,) int64 SMPL parents (-1 for the root)."""
    vertex_part: np.ndarray
    """(V,) int64 index into ``part_names``."""
    face_part: np.ndarray
    """(F,) int64 part (UV chart) of each face."""
    face_uv: np.ndarray
    """(F, 3, 2) float32 per-corner UVs in [0, 1] (one atlas chart per part)."""
    part_names: tuple[str, ...]
    """Names of the parts / charts."""
    height: float
    """Sole-to-crown height in metres (exact, after the final rescale)."""


def _grid_sdf(prims: dict[str, list[_Prim]], s: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Body SDF sampled on a regular grid of spacing h: (volume (X, Y, Z), origin (3,)).

    Each primitive is evaluated only on the sub-box of the grid inside its bounding
    box grown by a margin; outside it the true distance exceeds the margin, larger
    than every blend radius, so the constant stand-in leaves every smooth-min exact.
    """
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for plist in prims.values():
        for pr in plist:
            a, b = pr.aabb(s)
            lo, hi = np.minimum(lo, a), np.maximum(hi, b)
    lo -= 3 * h + 0.02 * s
    hi += 3 * h + 0.02 * s
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    margin = 0.1 * s
    part_vals: dict[str, np.ndarray] = {}
    for part, plist in prims.items():
        vol = None
        for pr in plist:
            a, b = pr.aabb(s)
            i0 = np.maximum(np.floor((a - margin - lo) / h).astype(int), 0)
            i1 = np.minimum(np.ceil((b + margin - lo) / h).astype(int) + 1, shape)
            axes = [lo[i] + h * np.arange(i0[i], i1[i]) for i in range(3)]
            X, Y, Z = np.meshgrid(*axes, indexing="ij")
            pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], -1)
            prim = np.full(shape, margin, dtype=np.float32)
            prim[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]] = np.minimum(pr.sdf(pts, s), margin).reshape(X.shape)
            vol = prim if vol is None else _smin(vol, prim, _k_within(part) * s)
        part_vals[part] = vol
    return _combine(part_vals, s), lo


def _polygonise(vol: np.ndarray, origin: np.ndarray, h: float):
    from skimage.measure import marching_cubes

    # The volume is a signed distance (negative inside), i.e. the exterior is
    # greater ("ascent"); with the (x, y, z) index order skimage's winding then comes
    # out inward, so the caller checks the signed volume and flips if needed.
    v, f, _, _ = marching_cubes(vol, level=0.0, spacing=(h, h, h), gradient_direction="ascent",
                                allow_degenerate=False)
    return v + origin, f.astype(np.int64)


def _isotropic_kwargs(L: float, iterations: int, split_collapse: bool = True) -> dict:
    """Every parameter of pymeshlab's isotropic remeshing, spelled out: pymeshlab
    (2025.7) remembers a filter's last-used arguments as the defaults of its next
    call, so relying on defaults makes results depend on call history."""
    import pymeshlab

    return dict(iterations=iterations, adaptive=False, selectedonly=False, targetlen=pymeshlab.PureValue(L),
                featuredeg=180.0, checksurfdist=False, maxsurfdist=pymeshlab.PureValue(L), splitflag=split_collapse,
                collapseflag=split_collapse, swapflag=True, smoothflag=True, reprojectflag=True)


def _remesh(v: np.ndarray, f: np.ndarray, target_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Clean, isotropically remesh and smooth a closed mesh to target_vertices.

    The count is exact when the remeshed surface has at least target_vertices (the
    usual case: the edge length aims 3% above); otherwise it is within a few percent.
    """
    import pymeshlab

    def isotropic(L: float, iterations: int) -> "pymeshlab.MeshSet":
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v.astype(np.float64), face_matrix=f.astype(np.int32)))
        ms.meshing_remove_duplicate_vertices()
        ms.meshing_remove_unreferenced_vertices()
        ms.meshing_remove_connected_component_by_face_number(mincomponentsize=100, removeunref=True)
        ms.meshing_isotropic_explicit_remeshing(**_isotropic_kwargs(L, iterations))
        return ms

    # 1. Isotropic remeshing of the marching-cubes surface (Botsch & Kobbelt 2004).
    #    A regular closed triangulation has V ~ A / (sqrt(3)/2 L^2); one short
    #    calibration run corrects the edge length for the remesher's bias.
    area = float(_mesh_area(v, f))
    goal = 1.03 * target_vertices
    L0 = float(np.sqrt(area / (np.sqrt(3) / 2 * goal)))
    trial = isotropic(L0, 3)  # keep the MeshSet alive while its mesh is read
    L = L0 * float(np.sqrt(trial.current_mesh().vertex_number() / goal))
    del trial
    if not (np.isfinite(L) and 0.5 * L0 < L < 2 * L0):
        raise RuntimeError(f"mannequin remeshing: calibrated edge length {L} far from the estimate {L0}")
    ms = isotropic(L, 8)
    # 2. Quadric edge-collapse decimation of the last few percent to the exact count
    #    (genus 0: F = 2 (V - 2)), then a relaxation pass (edge flips + tangential
    #    smoothing only, so the count stays) and a shrink-free Taubin smoothing.
    if ms.current_mesh().vertex_number() > target_vertices:
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=2 * (target_vertices - 2), targetperc=0.0, qualitythr=0.3, preserveboundary=False,
            boundaryweight=1.0, preservenormal=False, preservetopology=True, optimalplacement=True,
            planarquadric=False, planarweight=0.001, qualityweight=False, autoclean=True, selected=False)
    ms.meshing_isotropic_explicit_remeshing(**_isotropic_kwargs(L, 3, split_collapse=False))
    ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.53, stepsmoothnum=4, selected=False)
    ms.meshing_re_orient_faces_coherently()
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)


def _mesh_area(v: np.ndarray, f: np.ndarray) -> float:
    """Surface area of a triangle mesh (numpy only)."""
    t = v[f]
    return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def _adjacency(faces: np.ndarray, n: int):
    import scipy.sparse as sp

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    return A


def _label_parts(v: np.ndarray, faces: np.ndarray, prims, s: float) -> np.ndarray:
    """Per-vertex part: nearest part primitive, then a 3-pass majority filter."""
    lab = np.argmin(_part_sdf(prims, v, s), axis=1)
    A = _adjacency(faces, len(v))
    n_parts = len(PART_NAMES)
    for _ in range(3):
        onehot = np.eye(n_parts)[lab]
        votes = A @ onehot + onehot
        lab = np.argmax(votes, axis=1)
    return lab.astype(np.int64)


def _bone_segments(joints: np.ndarray, s: float) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Segment (a, b) of the bone driven by each joint (from the joint to its child)."""
    J = joints
    idx = JOINT_INDEX
    seg: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    child = {
        "pelvis": "spine1", "spine1": "spine2", "spine2": "spine3", "spine3": "neck",
        "neck": "head",
    }
    for side in ("left", "right"):
        child.update({
            f"{side}_hip": f"{side}_knee", f"{side}_knee": f"{side}_ankle",
            f"{side}_ankle": f"{side}_foot", f"{side}_collar": f"{side}_shoulder",
            f"{side}_shoulder": f"{side}_elbow", f"{side}_elbow": f"{side}_wrist",
            f"{side}_wrist": f"{side}_hand",
        })
    for a, b in child.items():
        seg[idx[a]] = (J[idx[a]], J[idx[b]])
    tips = {"head": _BONE_TIPS["head"], "left_hand": _BONE_TIPS["left_hand"],
            "left_foot": _BONE_TIPS["left_foot"]}
    seg[idx["head"]] = (J[idx["head"]], np.multiply(tips["head"], s))
    for side, m in (("left", lambda q: q), ("right", _mirror)):
        seg[idx[f"{side}_hand"]] = (J[idx[f"{side}_hand"]], np.multiply(m(tips["left_hand"]), s))
        seg[idx[f"{side}_foot"]] = (J[idx[f"{side}_foot"]], np.multiply(m(tips["left_foot"]), s))
    # The pelvis bone also spans the hip line so the lower belly and seat follow it.
    return seg


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _skinning_weights(v: np.ndarray, faces: np.ndarray, part: np.ndarray, joints: np.ndarray,
                      s: float, smoothness: float) -> np.ndarray:
    """Convex weights (V, 24) by graph diffusion of a hard bone assignment.

    1. Seed: each vertex takes the nearest bone segment among the bones allowed
       for its part (so an arm vertex never seeds to the torso, whatever the
       Euclidean distance).
    2. Diffuse the one-hot seeds over the mesh graph by heat flow for a time t
       (in squared edge lengths), as 4 implicit steps (D + t/4 (D - A)) W_k+1 = D W_k
       (D degrees, A adjacency): blending happens along the surface (geodesically),
       never across the air between body parts, and the split steps give a
       Gaussian-like rather than cusped profile across each seed boundary.
    3. Clip tiny values and renormalise rows to sum to one.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = len(v)
    seg = _bone_segments(joints, s)
    W0 = np.zeros((n, NUM_JOINTS))
    for pname, bones in PART_BONES.items():
        sel = np.nonzero(part == _P[pname])[0]
        if len(sel) == 0:
            continue
        ids = [JOINT_INDEX[b] for b in bones]
        d = np.stack([_point_segment_distance(v[sel], *seg[j]) for j in ids], axis=1)
        W0[sel, np.asarray(ids)[np.argmin(d, axis=1)]] = 1.0
    A = _adjacency(faces, n)
    deg = np.asarray(A.sum(1)).ravel()
    D = sp.diags(deg)
    steps = 4
    lu = spla.splu((D + (smoothness / steps) * (D - A)).tocsc())
    W = W0
    for _ in range(steps):
        W = lu.solve(D @ W)
    W = np.where(W < 1e-3, 0.0, W)
    return W / W.sum(1, keepdims=True)


# ---------------------------------------------------------------------- UV atlas
@dataclass(frozen=True)
class _Chart:
    kind: str  # "cylinder" or "disc"
    center: tuple
    axis: tuple  # cylinder axis / disc centre direction (the pole)
    ref: tuple  # direction of angle 0 (a cylinder's seam is opposite)


def _charts() -> dict[str, _Chart]:
    J = _LEFT_AND_MID_JOINTS
    c: dict[str, _Chart] = {
        "head": _Chart("disc", (0.0, 0.650, 0.020), (0, 1, 0), (0, 0, 1)),
        "neck": _Chart("cylinder", (0.0, 0.5, -0.015), (0, 1, 0), (0, 0, 1)),
        "torso": _Chart("cylinder", (0.0, 0.0, 0.0), (0, 1, 0), (0, 0, 1)),
    }
    for side, sx in (("left", 1.0), ("right", -1.0)):
        sh = J["left_shoulder"]
        c[f"{side}_upper_arm"] = _Chart("cylinder", (sx * sh[0], sh[1], sh[2]), (sx, 0, 0), (0, 1, 0))
        c[f"{side}_lower_arm"] = _Chart("cylinder", (sx * 0.44, 0.445, -0.035), (sx, 0, 0), (0, 1, 0))
        c[f"{side}_hand"] = _Chart("disc", (sx * 0.770, 0.440, -0.020), (sx, 0, 0), (0, 1, 0))
        hp = J["left_hip"]
        c[f"{side}_upper_leg"] = _Chart("cylinder", (sx * hp[0], hp[1], hp[2]), (0, -1, 0), (sx, 0, 0))
        c[f"{side}_lower_leg"] = _Chart("cylinder", (sx * 0.093, -0.47, 0.0), (0, -1, 0), (sx, 0, 0))
        c[f"{side}_foot"] = _Chart("disc", (sx * 0.097, -0.88, 0.050), (0, -1, 0), (0, 0, 1))
    return c


def _chart_coords(p: np.ndarray, ch: _Chart, s: float) -> tuple[np.ndarray, float | None]:
    """Chart coordinates (N, 2) in metres of points p (N, 3), and the u period
    (the circumference for a cylinder, None for a disc).

    cylinder: (angle about the axis * mean radius, height along the axis); the angle
        wraps at the seam (opposite ``ref``).
    disc: Lambert azimuthal equal-area projection about the pole ``axis``,
        r = 2 R sin(theta / 2) at angle phi: no seam, area-preserving; only the
        antipode of the pole (where the part attaches to its neighbour) is cut.
    """
    a = np.asarray(ch.axis, float)
    a = a / np.linalg.norm(a)
    r = np.asarray(ch.ref, float)
    r = r - (r @ a) * a
    r = r / np.linalg.norm(r)
    b = np.cross(a, r)
    d = p - np.multiply(ch.center, s)
    h = d @ a
    q = d - h[:, None] * a
    phi = np.arctan2(q @ b, q @ r)
    if ch.kind == "cylinder":
        R = float(np.mean(np.linalg.norm(q, axis=1)))
        return np.stack([phi * R, h], -1), 2 * np.pi * R
    dist = np.linalg.norm(d, axis=1)
    R = float(np.mean(dist))
    theta = np.arccos(np.clip(h / np.maximum(dist, 1e-12), -1, 1))
    rad = 2 * R * np.sin(theta / 2)
    # (cos, sin) of phi measured counter-clockwise about the outward pole keeps the
    # outward triangles counter-clockwise in the chart.
    return np.stack([rad * np.cos(phi), rad * np.sin(phi)], -1), None


def _boundary_loop(faces: np.ndarray) -> np.ndarray | None:
    """The single boundary loop (ordered vertex ids, patch on the left) of a triangle
    patch, or None if the patch is not a topological disc with a simple boundary."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = {(int(a), int(b)) for a, b in half}
    border = [(a, b) for a, b in key if (b, a) not in key]
    if not border:
        return None
    nxt: dict[int, int] = {}
    for a, b in border:
        if a in nxt:
            return None  # pinched boundary vertex
        nxt[a] = b
    start = border[0][0]
    loop = [start]
    while True:
        b = nxt[loop[-1]]
        if b == start:
            break
        loop.append(b)
        if len(loop) > len(border):
            return None
    if len(loop) != len(border):
        return None  # several boundary loops
    n_v = len(np.unique(faces))
    n_e = len({(min(a, b), max(a, b)) for a, b in key})
    if n_v - n_e + len(faces) != 1:
        return None  # not a disc (handles)
    return np.asarray(loop)


def _disc_parameterization(v: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """Per-corner chart coordinates (F, 3, 2) in metres of a disc-topology patch:
    Floater's mean-value parameterisation (Floater 2003) with the boundary on a
    circle of the patch's area (arc-length spaced). Bijective for any disc patch
    (positive weights, convex boundary: Tutte 1963, Floater 2003). None if the
    patch is not a disc."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    loop = _boundary_loop(faces)
    if loop is None:
        return None
    ids, local = np.unique(faces, return_inverse=True)
    f = local.reshape(-1, 3)
    p = v[ids]
    n = len(ids)
    # 1. Mean-value weights w_ij = (tan(a/2) + tan(b/2)) / |p_i - p_j|, a, b the
    #    angles at i of the two triangles along edge ij.
    rows, cols, vals = [], [], []
    for c in range(3):
        i, j, k = f[:, c], f[:, (c + 1) % 3], f[:, (c + 2) % 3]
        eij, eik = p[j] - p[i], p[k] - p[i]
        lij, lik = np.linalg.norm(eij, axis=1), np.linalg.norm(eik, axis=1)
        cosg = np.clip((eij * eik).sum(1) / np.maximum(lij * lik, 1e-15), -1, 1)
        t = np.tan(np.arccos(cosg) / 2)
        rows += [i, i]
        cols += [j, k]
        vals += [t / np.maximum(lij, 1e-15), t / np.maximum(lik, 1e-15)]
    W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    # 2. Boundary on a circle with the patch's area, counter-clockwise along the loop
    #    (the patch lies to the left of its boundary half-edges).
    b = np.searchsorted(ids, loop)
    seg = np.linalg.norm(p[np.roll(b, -1)] - p[b], axis=1)
    ang = 2 * np.pi * np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / seg.sum()
    tri = p[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    R = np.sqrt(area / np.pi)
    uv = np.zeros((n, 2))
    uv[b] = R * np.stack([np.cos(ang), np.sin(ang)], -1)
    # 3. Interior vertices are the weighted average of their neighbours: solve
    #    (diag(W 1) - W)_II u_I = W_IB u_B.
    interior = np.setdiff1d(np.arange(n), b)
    L = (sp.diags(np.asarray(W.sum(1)).ravel()) - W).tocsr()
    rhs = -(L[interior][:, b] @ uv[b])
    uv[interior] = spla.splu(L[interior][:, interior].tocsc()).solve(rhs)
    # 4. Undo the centre crowding of such maps with a monotone radial remap r -> g(r)
    #    making the disc within g(r) hold the surface area of the triangles within r
    #    (angles unchanged, so the map stays bijective).
    r = np.linalg.norm(uv, axis=1)
    tri_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    r_tri = r[f].max(1)
    order = np.argsort(r_tri)
    cum = np.cumsum(tri_area[order]) / area
    q = np.linspace(0.0, 1.0, 17)[1:-1]  # a few smooth knots: g must stay gentle
    knots_r = np.concatenate([[0.0], np.interp(q, cum, r_tri[order]), [R]])
    knots_g = R * np.sqrt(np.concatenate([[0.0], q, [1.0]]))
    knots_g = 0.8 * knots_g + 0.2 * knots_r  # keep g strictly increasing
    g = np.interp(r, knots_r, knots_g)
    uv = uv * (g / np.maximum(r, 1e-15))[:, None]
    return uv[f]


def _face_parts(faces: np.ndarray, vertex_part: np.ndarray) -> np.ndarray:
    """Majority part of each face's corners (first corner's part on a three-way tie)."""
    p = vertex_part[faces]
    fp = p[:, 0].copy()
    fp = np.where(p[:, 1] == p[:, 2], p[:, 1], fp)
    return fp


def _uv_atlas(v: np.ndarray, faces: np.ndarray, face_part: np.ndarray, s: float):
    """Per-corner UVs (F, 3, 2) in [0, 1]: one chart per part, shelf-packed.

    1. Each face is unwrapped with its part's chart, in metres so texel density is
       roughly uniform over the atlas: cylindrical (angle * mean radius, height)
       for the torso, neck and limb segments; a mean-value (Floater) disc
       parameterisation for the head, hands and feet, which are topological discs
       (no seam, no flipped triangle; the azimuthal equal-area projection of
       :func:`_chart_coords` is the fallback if a patch is not a disc).
    2. Cylinder faces straddling the wrap-around (corner u span > half the
       circumference) get one period added to their negative-u corners: seams are
       cut per corner, never mid-face.
    3. Charts are shelf-packed by decreasing height with a padding gutter and the
       atlas is scaled uniformly into [0, 1]^2.
    """
    charts = _charts()
    uv = np.zeros((len(faces), 3, 2))
    boxes = []
    for pi_, pname in enumerate(PART_NAMES):
        fsel = np.nonzero(face_part == pi_)[0]
        if len(fsel) == 0:
            boxes.append(None)
            continue
        ch = charts[pname]
        corners = v[faces[fsel]].reshape(-1, 3)
        c = _disc_parameterization(v, faces[fsel]) if ch.kind == "disc" else None
        period = None
        if c is None:  # cylinder, or a disc part that is not a topological disc
            c, period = _chart_coords(corners, ch, s)
            c = c.reshape(-1, 3, 2)
        if period is not None:
            u = c[..., 0]
            wrap = (u.max(1) - u.min(1)) > period / 2
            c[..., 0] = np.where(wrap[:, None] & (u < 0), u + period, u)
        lo = c.reshape(-1, 2).min(0)
        hi = c.reshape(-1, 2).max(0)
        uv[fsel] = c - lo
        boxes.append(hi - lo)
    # Shelf packing: find the narrowest square-ish strip width that fits.
    pad = 0.02 * s
    order = sorted([i for i, b in enumerate(boxes) if b is not None], key=lambda i: -boxes[i][1])
    total = sum((boxes[i][0] + pad) * (boxes[i][1] + pad) for i in order)
    widest = max(boxes[i][0] for i in order) + 2 * pad
    best = None
    for width in np.linspace(max(np.sqrt(total), widest), 3 * max(np.sqrt(total), widest), 200):
        x = y = pad
        row_h = 0.0
        place = {}
        for i in order:
            w_, h_ = boxes[i]
            if x + w_ + pad > width:
                x, y = pad, y + row_h + pad
                row_h = 0.0
            place[i] = (x, y)
            x += w_ + pad
            row_h = max(row_h, h_)
        side = max(width, y + row_h + pad)
        if best is None or side < best[0] - 1e-9:
            best = (side, place)
    side, place = best
    for i in order:
        fsel = face_part == i
        uv[fsel] = (uv[fsel] + np.asarray(place[i])) / side
    return np.clip(uv, 0.0, 1.0).astype(np.float32)


def build_mannequin(height: float = REFERENCE_HEIGHT, target_vertices: int = 6500,
                    voxel: float = 0.008, weight_smoothness: float = 25.0) -> MannequinData:
    """Build the mannequin from scratch (a few seconds); see :func:`load_or_build_mannequin`.

    height: sole-to-crown height in metres (the result matches it exactly).
    target_vertices: vertex count of the final mesh (met exactly for a genus-0 mesh).
    voxel: marching-cubes grid spacing at REFERENCE_HEIGHT, metres.
    weight_smoothness: diffusion time of the skinning weights, in squared edge lengths.
    """
    if not 0.5 <= height <= 2.5:
        raise ValueError(f"build_mannequin: height must be in [0.5, 2.5] m, got {height}")
    if not 1000 <= target_vertices <= 200_000:
        raise ValueError(f"build_mannequin: target_vertices must be in [1000, 200000], got {target_vertices}")
    s = height / REFERENCE_HEIGHT
    prims = _primitives()
    # 1. Sample the smooth-union SDF on a grid and polygonise it.
    h = voxel * s
    vol, origin = _grid_sdf(prims, s, h)
    v, f = _polygonise(vol, origin, h)
    # 2. Clean, remesh, decimate to the vertex target, smooth.
    v, f = _remesh(v, f, target_vertices)
    # 3. Orientation: outward normals give a positive signed volume.
    tri = v[f]
    vol6 = np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    if vol6 < 0:
        f = f[:, ::-1].copy()
    # 4. Exact height: rescale about the pelvis (origin).
    joints = mannequin_joints(height)
    k = height / float(v[:, 1].max() - v[:, 1].min())
    v = v * k
    joints = joints * k
    s_eff = s * k
    # 5. Parts, skinning weights, UV atlas.
    part = _label_parts(v, f, prims, s_eff)
    W = _skinning_weights(v, f, part, joints, s_eff, weight_smoothness)
    face_part = _face_parts(f, part)
    uv = _uv_atlas(v, f, face_part, s_eff)
    return MannequinData(
        vertices=v.astype(np.float32), faces=f.astype(np.int64), weights=W.astype(np.float32),
        joints_rest=joints.astype(np.float32), parents=np.asarray(SMPL_PARENTS, np.int64),
        vertex_part=part, face_part=face_part.astype(np.int64), face_uv=uv,
        part_names=PART_NAMES, height=float(v[:, 1].max() - v[:, 1].min()),
    )


# ----------------------------------------------------------------------- caching
def cache_dir() -> Path:
    """``$ANIDRESS_CACHE`` if set, else ``~/.cache/anidress``."""
    env = os.environ.get("ANIDRESS_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "anidress"


def cache_path(height: float, target_vertices: int) -> Path:
    """The npz file under :func:`cache_dir` that caches the mannequin of this height (metres) and vertex
    count (keyed with MANNEQUIN_VERSION too); :func:`load_or_build_mannequin` reads and writes it."""
    key = json.dumps({"v": MANNEQUIN_VERSION, "height": round(float(height), 6),
                      "target_vertices": int(target_vertices)}, sort_keys=True)
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    return cache_dir() / f"mannequin_{digest}.npz"


_FIELDS = ("vertices", "faces", "weights", "joints_rest", "parents", "vertex_part", "face_part", "face_uv")


def load_or_build_mannequin(height: float = REFERENCE_HEIGHT, target_vertices: int = 6500,
                            use_cache: bool = True) -> MannequinData:
    """The mannequin, read from the npz cache or built and cached (atomic write).

    The cache file is keyed by (height, target_vertices, MANNEQUIN_VERSION); an
    unreadable or stale file is rebuilt.
    """
    path = cache_path(height, target_vertices)
    if use_cache and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["version"]) == MANNEQUIN_VERSION:
                    arrays = {k: z[k] for k in _FIELDS}
                    return MannequinData(**arrays, part_names=tuple(str(x) for x in z["part_names"]),
                                         height=float(z["height"]))
        except Exception:  # noqa: BLE001 - a corrupt or foreign cache file (bad zip, missing key): rebuild
            pass
    data = build_mannequin(height, target_vertices)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp.npz")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **{k: getattr(data, k) for k in _FIELDS},
                         part_names=np.asarray(data.part_names), height=np.float64(data.height),
                         version=np.asarray(MANNEQUIN_VERSION), built_at=np.float64(time.time()))
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    return data
