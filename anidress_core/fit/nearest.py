"""The ``nearest`` baseline: per frame, the simulated garment pose that the loss scores lowest.

A baseline that fits nothing (variant ``nearest``): it measures how far the simulation database alone gets. The
database is the rig's bone transforms of every simulated frame (``rig.npz``: the library motions, the simulation
of the observed motion), each with the body state it was simulated on. For a frame t of the observed sequence:

1. the ``NEAREST`` nearest simulated frames (other motions than the observed one) by the body's pose
   relative to its root and the root's velocity in its own frame (:func:`body_features`,
   :func:`nearest_frames`), their bone transforms carried rigidly from the simulated body root to the
   observed one (:func:`carry`);
2. the simulation of the observed motion at frames t + o, |o| <= ``OFFSETS`` (its body is the observed
   one, so the carry only corrects the root motion between t + o and t);
3. every candidate scored by the loss (:func:`score_poses`: the frame's cues, flow targets and references,
   L_prior left out); the lowest is the frame's pose.

Shapes: N database frames, K candidates, B bones, J body joints (root = joint 0), T frames. Transforms are rest ->
world (column vectors), float64. Units: metres, seconds; the velocity weight is in s^2 (a velocity difference of
1 m/s costs as much as a pose feature distance of sqrt(weight)).
"""
from __future__ import annotations

from typing import Mapping, NamedTuple, Sequence

import torch
from torch import Tensor

from ..geometry import invert_transform, lbs
from .config import FitConfig
from .objective import evaluate, windowed_problem
from .problem import FlowTargets, FrameCues, RigParts, Views, cue_notes
from .terms import collision
from .terms.anchor import AnchorRef

__all__ = ["NEAREST", "OFFSETS", "VELOCITY_WEIGHT", "BodyFeatures", "SimDatabase", "Candidates", "body_features",
           "make_database", "carry", "nearest_frames", "frame_candidates", "score_poses"]

#: candidates per frame from other simulated motions: the nearest frames by body pose and root velocity
NEAREST = 8
#: candidates per frame from the simulation of the observed motion: its frames t + o, |o| <= this
OFFSETS = 2
#: weight (s^2) of the squared root-velocity difference (m/s) against the squared pose-feature distance
VELOCITY_WEIGHT = 0.05


class BodyFeatures(NamedTuple):
    """What the nearest-frame search compares of a body state, per frame."""

    pose: Tensor  # (T, 9 (J - 1)) rotations of joints 1..J-1 relative to the root (flattened 3x3)
    velocity: Tensor  # (T, 3) root velocity in the root's own frame (m/s)
    root: Tensor  # (T, 4, 4) the root joint's transform (world)


class SimDatabase(NamedTuple):
    """Simulated frames: the garment's rig pose and the body state it was simulated on (:func:`make_database`)."""

    transforms: Tensor  # (N, B, 4, 4) garment bone transforms, rest -> world
    body: BodyFeatures  # (N, ...) the body of each frame
    sequence: Tensor  # (N,) int64 index into ``names``
    frame: Tensor  # (N,) int64 frame within its sequence
    names: tuple  # sequence names (rig.npz ``sequences``: seq-<name>, lib-<motion>, amass-<stem>)


class Candidates(NamedTuple):
    """Candidate garment poses of one frame (:func:`frame_candidates`)."""

    transforms: Tensor  # (K, B, 4, 4)
    labels: list  # K strings: where each came from ('lib-walk:12', 'seq-walk:+2', ...)


def body_features(joints: Tensor, fps: float) -> BodyFeatures:
    """Pose and root velocity of joint transforms ``joints`` (T, J, 4, 4) (world, e.g.
    ``BodyModel.pose(...).transforms``) at ``fps`` frames per second.

    pose[t] = R_root[t]^T R_j[t] for j >= 1, flattened; velocity[t] = R_root[t]^T dp/dt with p the
    root position, central differences (one-sided at the ends; 0 for a single frame).
    """
    J = torch.as_tensor(joints).double()
    if J.ndim != 4 or J.shape[-2:] != (4, 4) or J.shape[1] < 2:
        raise ValueError(f"body_features: joints must be (T, J >= 2, 4, 4), got {tuple(J.shape)}")
    T = J.shape[0]
    R0 = J[:, 0, :3, :3]  # (T, 3, 3)
    rel = torch.einsum("tji,tkjl->tkil", R0, J[:, 1:, :3, :3])  # R0^T R_k (T, J-1, 3, 3)
    p = J[:, 0, :3, 3]
    if T == 1:
        dp = torch.zeros_like(p)
    else:
        dp = torch.empty_like(p)
        dp[1:-1] = (p[2:] - p[:-2]) / 2
        dp[0], dp[-1] = p[1] - p[0], p[-1] - p[-2]
    vel = torch.einsum("tji,tj->ti", R0, dp * float(fps))  # R0^T v
    return BodyFeatures(rel.reshape(T, -1), vel, J[:, 0].clone())


def make_database(sequences: Mapping[str, tuple[Tensor, Tensor, float]]) -> SimDatabase:
    """The database of simulated frames: name -> (garment transforms (T, B, 4, 4), body joint
    transforms (T, J, 4, 4), fps). Every sequence needs as many body frames as garment frames."""
    if not sequences:
        raise ValueError("make_database: no sequences")
    G, feats, seq, frame = [], [], [], []
    for i, (name, (tf, joints, fps)) in enumerate(sequences.items()):
        tf = torch.as_tensor(tf).double()
        if tf.ndim != 4 or tf.shape[-2:] != (4, 4) or torch.as_tensor(joints).shape[0] != tf.shape[0]:
            raise ValueError(f"make_database: sequence {name!r}: transforms (T, B, 4, 4) and joints (T, J, 4, 4) of "
                             f"the same T expected, got {tuple(tf.shape)} and {tuple(torch.as_tensor(joints).shape)}")
        G.append(tf)
        feats.append(body_features(joints, fps))
        seq.append(torch.full((tf.shape[0],), i, dtype=torch.int64))
        frame.append(torch.arange(tf.shape[0]))
    B = {g.shape[1] for g in G}
    if len(B) != 1:
        raise ValueError(f"make_database: sequences with different bone counts {sorted(B)}")
    body = BodyFeatures(*(torch.cat([getattr(f, k) for f in feats]) for k in BodyFeatures._fields))
    return SimDatabase(torch.cat(G), body, torch.cat(seq), torch.cat(frame), tuple(sequences))


def carry(transforms: Tensor, root_from: Tensor, root_to: Tensor) -> Tensor:
    """Garment transforms (..., B, 4, 4) moved rigidly with the body root: root_to @ root_from^-1 @ G.
    root_from (..., 4, 4) the simulated body's root, root_to (4, 4) or (..., 4, 4) the observed one."""
    A = root_to.double() @ invert_transform(root_from.double())  # (..., 4, 4)
    return A[..., None, :, :] @ transforms.double()


def nearest_frames(db: SimDatabase, query: BodyFeatures, t: int, k: int, velocity_weight: float,
                   exclude: Sequence[str] = ()) -> Tensor:
    """(k',) indices of the database frames nearest to frame ``t`` of ``query`` (k' = min(k, N
    allowed)), nearest first: squared distance of the pose features plus ``velocity_weight`` (s^2)
    times the squared velocity difference (m/s). Sequences named in ``exclude`` are left out."""
    d = ((db.body.pose - query.pose[t]).pow(2).sum(-1)
         + velocity_weight * (db.body.velocity - query.velocity[t]).pow(2).sum(-1))
    if exclude:
        out = torch.tensor([n in set(exclude) for n in db.names], dtype=torch.bool)[db.sequence]
        d = torch.where(out, torch.full_like(d, float("inf")), d)
    d = torch.where(torch.isfinite(d), d, torch.full_like(d, float("inf")))
    n_ok = int(torch.isfinite(d).sum())
    return torch.argsort(d)[:min(int(k), n_ok)]


def frame_candidates(db: SimDatabase, query: BodyFeatures, t: int, nearest: int = NEAREST,
                     velocity_weight: float = VELOCITY_WEIGHT, own: str | None = None, offsets: int = OFFSETS
                     ) -> Candidates:
    """Candidates for frame ``t`` of the observed body ``query``: the ``nearest`` database frames of
    other sequences than ``own`` (:func:`nearest_frames`) and, when ``own`` (the simulation of the
    observed motion, e.g. ``seq-walk``) is in the database, its frames t + o for 0 < |o| <= offsets
    and o = 0, each carried from its simulated root to the observed root at t."""
    idx = nearest_frames(db, query, t, nearest, velocity_weight, exclude=(own,) if own else ())
    labels = [f"{db.names[int(db.sequence[i])]}:{int(db.frame[i])}" for i in idx]
    if own is not None and own in db.names:
        s = db.names.index(own)
        rows = (db.sequence == s).nonzero().flatten()
        for o in sorted(range(-offsets, offsets + 1), key=abs):
            if 0 <= t + o < rows.numel():
                idx = torch.cat([idx, rows[t + o: t + o + 1]])
                labels.append(f"{own}:{o:+d}")
    G = carry(db.transforms[idx], db.body.root[idx], query.root[t])
    return Candidates(G, labels)


def score_poses(rig: RigParts, views: Views, cues: FrameCues, candidates: Tensor, cfg: FitConfig,
                flow: FlowTargets | None = None, anchor: AnchorRef | None = None) -> Tensor:
    """(K,) the loss of each candidate pose (K, B, 4, 4) on one frame: :func:`anidress_core.fit.evaluate`
    on one problem (the frame's cues as :func:`anidress_core.fit.problem.cue_notes` cleans them, flow
    targets, L_anchor's references; rendered in one window per view that holds every candidate),
    L_collision's planes taken at each candidate (as a fit started there would), L_prior left out."""
    G = torch.as_tensor(candidates, device=rig.rest.device).double()
    if G.ndim != 4 or G.shape[1:] != (rig.weights.shape[1], 4, 4):
        raise ValueError(f"score_poses: candidates must be (K, {rig.weights.shape[1]}, 4, 4), got {tuple(G.shape)}")
    cues, flow, _ = cue_notes(cues, flow)
    X = torch.stack([lbs(rig.rest, rig.weights, g) for g in G])  # (K, V, 3)
    body = cues.occluder_mesh
    cfg = cfg.replace(weights={"prior": 0.0})
    pb, _ = windowed_problem(rig, views, cues, cfg, X.reshape(-1, 3), flow, anchor=anchor)
    out = torch.empty(G.shape[0], dtype=torch.float64)
    for i, x in enumerate(X):
        p = pb
        if cfg.weights.collision > 0:
            if body is None:
                raise ValueError("score_poses: weights.collision > 0 needs the body mesh (FrameCues.occluder_mesh)")
            c = collision.body_contacts(x, body[0], body[1], cfg.collision_radius)
            p = pb._replace(states={**pb.states, "collision": collision.setup(pb, cues, c)})
        out[i] = evaluate(p, x).loss
    return out
