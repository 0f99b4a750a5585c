"""Procedural motion library in the EasyMocap convention, with joint limits.

A :class:`Motion` holds SMPL pose parameters per frame: ``poses`` (T, 72) axis-angle
(``poses[:, :3]`` = 0), ``Rh`` (T, 3) and ``Th`` (T, 3) placing the posed canonical
body (y up, facing +z) in the z-up world: ``x_world = R(Rh) x_posed + Th``
(zju3dv/EasyMocap, doc/02_output.md). ``Rh`` = R_z^world(heading) R_x(+90 deg) R_root:
the +90 deg turn about x takes canonical y-up to world z-up (canonical +z, the
facing direction, becomes world -y), heading turns about world z, R_root is the
pelvis tilt in the canonical frame. At heading 0 the body faces world -y.

Every motion starts from the rest standing pose (arms down) and eases in with a
quintic smootherstep envelope (C2); all curves are sums of smooth functions of time.
``Th`` puts the lowest sole vertex on the ground z = 0 (temporally smoothed so Th
stays smooth when support switches feet), plus the flight height of a jump.

Joint limits are boxes on Euler angles: for every joint, (theta_x, theta_y, theta_z)
with ``R = R_x(theta_x) R_z(theta_z) R_y(theta_y)`` (intrinsic X-Z'-Y''; the middle,
z, angle always has |theta_z| < 90 deg so the decomposition is unique). Axes are the
canonical ones (all SMPL joint frames are aligned with the body frame at rest):
for the legs and spine x is flexion/extension, z abduction / lateral bend, y twist;
for the arms (along +-x in the T-pose) z raises/lowers, y swings forward/back, x twists.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from ..geometry import (
    axis_angle_to_matrix,
    lbs,
    make_transform,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    quaternion_to_matrix,
)
from .kinematic import JOINT_INDEX, NUM_JOINTS, SMPL_JOINT_NAMES, forward_kinematics

__all__ = [
    "Motion",
    "MotionSpec",
    "JointLimit",
    "MOTIONS",
    "JOINT_LIMITS",
    "EULER_ORDER",
    "make_motion",
    "joint_limit_bounds",
    "clamp_to_joint_limits",
    "joint_limit_violation",
    "euler_to_matrix",
    "matrix_to_euler",
    "resample",
    "concatenate",
    "transform_motion",
]

EULER_ORDER = "XZY"
"""Composition order of the joint-limit Euler angles: R = R_x R_z R_y (intrinsic)."""

_D = math.pi / 180.0


# ------------------------------------------------------------------ Euler angles
def euler_to_matrix(angles: Tensor) -> Tensor:
    """(..., 3) angles (theta_x, theta_y, theta_z) -> (..., 3, 3) R = R_x R_z R_y."""
    if angles.shape[-1] != 3:
        raise ValueError(f"euler_to_matrix: angles must be (..., 3), got {tuple(angles.shape)}")
    c, s = torch.cos(angles), torch.sin(angles)
    o, i = torch.zeros_like(c[..., 0]), torch.ones_like(c[..., 0])

    def mat(*rows):
        return torch.stack(rows, -1).reshape(*angles.shape[:-1], 3, 3)

    Rx = mat(i, o, o, o, c[..., 0], -s[..., 0], o, s[..., 0], c[..., 0])
    Ry = mat(c[..., 1], o, s[..., 1], o, i, o, -s[..., 1], o, c[..., 1])
    Rz = mat(c[..., 2], -s[..., 2], o, s[..., 2], c[..., 2], o, o, o, i)
    return Rx @ Rz @ Ry


def matrix_to_euler(R: Tensor) -> Tensor:
    """(..., 3, 3) -> (..., 3) angles (theta_x, theta_y, theta_z) with R = R_x R_z R_y.

    theta_z in [-pi/2, pi/2]; theta_x, theta_y in (-pi, pi].
    Derivation: R[0] = (cz cy, -sz, cz sy); R[1, 1] = cx cz; R[2, 1] = sx cz.
    """
    tz = torch.asin((-R[..., 0, 1]).clamp(-1.0, 1.0))
    tx = torch.atan2(R[..., 2, 1], R[..., 1, 1])
    ty = torch.atan2(R[..., 0, 2], R[..., 0, 0])
    return torch.stack([tx, ty, tz], dim=-1)


# ------------------------------------------------------------------ joint limits
# Bounds in degrees per axis (x, y, z) for the left side and the midline; the right
# side mirrors them (x -> -x reflection negates the y and z angles). None: no limit.
_LIMITS_DEG: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]] | None] = {
    "pelvis": None,  # global orientation lives in Rh
    "left_hip": ((-120, 35), (-40, 40), (-30, 50)),  # x<0 flexes the thigh forward
    "spine1": ((-25, 45), (-30, 30), (-30, 30)),  # x>0 bends forward
    "left_knee": ((0, 150), (-10, 10), (-5, 5)),  # x>0 flexes
    "spine2": ((-20, 30), (-25, 25), (-25, 25)),
    "left_ankle": ((-30, 50), (-20, 20), (-25, 25)),  # x<0 dorsiflexes (toes up)
    "spine3": ((-20, 30), (-25, 25), (-25, 25)),
    "left_foot": ((-45, 20), (-5, 5), (-5, 5)),
    "neck": ((-40, 45), (-50, 50), (-35, 35)),
    "left_collar": ((-20, 20), (-25, 15), (-20, 30)),
    "head": ((-40, 40), (-50, 50), (-30, 30)),
    "left_shoulder": ((-100, 60), (-60, 45), (-85, 85)),  # z<0 lowers, x<0 swings a lowered arm forward
    "left_elbow": ((-60, 60), (-150, 0), (-10, 10)),  # y<0 flexes
    "left_wrist": ((-60, 60), (-30, 30), (-70, 70)),
    "left_hand": ((-20, 20), (-20, 20), (-20, 20)),
}


@dataclass(frozen=True)
class JointLimit:
    """Euler-angle box of one joint, radians, axes (x, y, z), order :data:`EULER_ORDER`."""

    lower: tuple[float, float, float]
    """Lower bounds of (theta_x, theta_y, theta_z)."""
    upper: tuple[float, float, float]
    """Upper bounds of (theta_x, theta_y, theta_z)."""


def _build_limits() -> dict[str, JointLimit | None]:
    out: dict[str, JointLimit | None] = {}
    for name, lim in _LIMITS_DEG.items():
        if lim is None:
            out[name] = None
            continue
        lo = tuple(b[0] * _D for b in lim)
        hi = tuple(b[1] * _D for b in lim)
        out[name] = JointLimit(lo, hi)
        if name.startswith("left_"):
            # Mirror: theta_y, theta_z change sign, so their bounds swap and negate.
            out["right_" + name[5:]] = JointLimit((lo[0], -hi[1], -hi[2]), (hi[0], -lo[1], -lo[2]))
    return {n: out[n] for n in SMPL_JOINT_NAMES}


JOINT_LIMITS: Mapping[str, JointLimit | None] = _build_limits()
"""Per-joint Euler box (see module docstring); None = unlimited (the root)."""


def joint_limit_bounds(dtype=torch.float32) -> tuple[Tensor, Tensor]:
    """(lower (24, 3), upper (24, 3)) radians, +-inf for unlimited joints."""
    lo = torch.full((NUM_JOINTS, 3), -math.inf, dtype=dtype)
    hi = torch.full((NUM_JOINTS, 3), math.inf, dtype=dtype)
    for j, n in enumerate(SMPL_JOINT_NAMES):
        lim = JOINT_LIMITS[n]
        if lim is not None:
            lo[j] = torch.tensor(lim.lower, dtype=dtype)
            hi[j] = torch.tensor(lim.upper, dtype=dtype)
    return lo, hi


def _check_poses(poses: Tensor, fn: str) -> None:
    if poses.shape[-1] != 3 * NUM_JOINTS:
        raise ValueError(f"{fn}: poses must be (..., {3 * NUM_JOINTS}), got {tuple(poses.shape)}")


def joint_limit_violation(poses: Tensor) -> Tensor:
    """(..., 72) axis-angle -> (..., 24) largest excess beyond the joint's box, radians."""
    _check_poses(poses, "joint_limit_violation")
    e = matrix_to_euler(axis_angle_to_matrix(poses.reshape(*poses.shape[:-1], NUM_JOINTS, 3)))
    lo, hi = joint_limit_bounds(e.dtype)
    return torch.maximum(lo - e, e - hi).clamp_min(0).amax(-1)


def clamp_to_joint_limits(poses: Tensor) -> Tensor:
    """Project each joint rotation into its Euler box. (..., 72) -> (..., 72).

    1. axis-angle -> R -> (theta_x, theta_y, theta_z) for R = R_x R_z R_y;
    2. clamp each angle to its bounds (unlimited joints pass through unchanged);
    3. back to axis-angle.
    """
    _check_poses(poses, "clamp_to_joint_limits")
    aa = poses.reshape(*poses.shape[:-1], NUM_JOINTS, 3)
    e = matrix_to_euler(axis_angle_to_matrix(aa))
    lo, hi = joint_limit_bounds(e.dtype)
    ec = torch.minimum(torch.maximum(e, lo), hi)
    changed = (ec != e).any(-1, keepdim=True)
    out = torch.where(changed, matrix_to_axis_angle(euler_to_matrix(ec)), aa)
    return out.reshape(poses.shape)


# ------------------------------------------------------------------------ motion
@dataclass(frozen=True, eq=False)
class Motion:
    """A body motion in the EasyMocap convention (float32 tensors)."""

    name: str
    """Library name or a free-form label."""
    fps: float
    """Frames per second."""
    poses: Tensor
    """(T, 72) axis-angle joint rotations, ``poses[:, :3]`` zero."""
    Rh: Tensor
    """(T, 3) global rotation (axis-angle, angle in [0, pi]) about the world origin,
    applied after posing. The axis flips when a turn passes pi: interpolate Rh as
    rotations (see :func:`resample`), not as vectors."""
    Th: Tensor
    """(T, 3) global translation, metres."""
    shapes: Tensor
    """(10,) SMPL betas (zero for the mannequin)."""

    def __post_init__(self):
        T = self.poses.shape[0]
        if self.poses.shape != (T, 3 * NUM_JOINTS) or self.Rh.shape != (T, 3) or self.Th.shape != (T, 3):
            raise ValueError(
                f"Motion '{self.name}': expected poses (T, 72), Rh (T, 3), Th (T, 3); got "
                f"{tuple(self.poses.shape)}, {tuple(self.Rh.shape)}, {tuple(self.Th.shape)}"
            )
        if self.shapes.ndim != 1:
            raise ValueError(f"Motion '{self.name}': shapes must be (S,), got {tuple(self.shapes.shape)}")
        if self.fps <= 0:
            raise ValueError(f"Motion '{self.name}': fps must be > 0, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return self.poses.shape[0]

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) / self.fps


def _smootherstep(x: np.ndarray) -> np.ndarray:
    """Quintic 6x^5 - 15x^4 + 10x^3 on [0, 1] (zero 1st and 2nd derivatives at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _bump(x: np.ndarray, a: float, m: float, b: float) -> np.ndarray:
    """C2 bump: 0 before a, rises to 1 at m, falls back to 0 at b."""
    return np.where(x < m, _smootherstep((x - a) / (m - a)), _smootherstep((b - x) / (b - m)))


@dataclass
class _Curves:
    """What a motion generator returns (numpy, degrees / radians / metres)."""

    joints_deg: np.ndarray  # (T, 24, 3) Euler (x, y, z) per joint, degrees
    root_deg: np.ndarray  # (T, 3) pelvis tilt in the canonical frame, Euler (x, y, z), degrees
    heading: np.ndarray  # (T,) radians about world z
    path_xy: np.ndarray  # (T, 2) world xy of the anchor
    anchor: str = "feet"  # "feet": mid-ankles follow path_xy; "root": the pelvis does
    lift: np.ndarray | None = None  # (T,) extra height above the ground placement, metres


@dataclass(frozen=True)
class _Ctx:
    t: np.ndarray  # (T,) seconds
    rng: np.random.Generator
    leg_length: float  # hip joint to sole, metres

    def env(self, ease: float = 0.5) -> np.ndarray:
        """Ease-in envelope 0 -> 1 over ``ease`` seconds (C2)."""
        return _smootherstep(self.t / ease)

    def jitter(self, lo: float = 0.9, hi: float = 1.1) -> float:
        return float(self.rng.uniform(lo, hi))


def _set(E: np.ndarray, joint: str, x=0.0, y=0.0, z=0.0, mirror: bool = True) -> None:
    """Set a joint's Euler angles (degrees); for a ``left_`` joint also set the mirrored
    right one (y, z negated) unless mirror is False."""
    E[:, JOINT_INDEX[joint], 0] = x
    E[:, JOINT_INDEX[joint], 1] = y
    E[:, JOINT_INDEX[joint], 2] = z
    if mirror and joint.startswith("left_"):
        r = JOINT_INDEX["right_" + joint[5:]]
        E[:, r, 0] = x
        E[:, r, 1] = -np.asarray(y)
        E[:, r, 2] = -np.asarray(z)


def _add(E: np.ndarray, joint: str, x=0.0, y=0.0, z=0.0) -> None:
    j = JOINT_INDEX[joint]
    E[:, j, 0] += x
    E[:, j, 1] += y
    E[:, j, 2] += z


_SHOULDER_DOWN = -68.0  # degrees: arms lowered from the T-pose to the standing rest pose
_ELBOW_REST = -12.0


def _standing(T: int) -> np.ndarray:
    """Rest standing pose (T, 24, 3) degrees: arms down, elbows slightly bent."""
    E = np.zeros((T, NUM_JOINTS, 3))
    _set(E, "left_shoulder", z=_SHOULDER_DOWN)
    _set(E, "left_elbow", y=_ELBOW_REST)
    return E


def _zeros2(T):
    return np.zeros((T, 2))


def _gait(c: _Ctx, freq: float, hip_amp: float, knee_amp: float, knee_base: float, arm_amp: float,
          elbow_extra: float, lean: float, pelvis_yaw: float) -> _Curves:
    T = len(c.t)
    e = c.env(0.6)
    a = c.jitter()
    f = freq * c.jitter(0.95, 1.05)
    phi = 2 * np.pi * f * c.t
    s, co = np.sin(phi), np.cos(phi)
    E = _standing(T)
    hip = hip_amp * a * e
    # Legs: thigh swing, knee flexion peaking mid-swing, small ankle roll-off.
    E[:, JOINT_INDEX["left_hip"], 0] = -hip * s - 2 * e
    E[:, JOINT_INDEX["right_hip"], 0] = hip * s - 2 * e
    E[:, JOINT_INDEX["left_knee"], 0] = e * (knee_base + knee_amp * (0.5 + 0.5 * co) ** 2)
    E[:, JOINT_INDEX["right_knee"], 0] = e * (knee_base + knee_amp * (0.5 - 0.5 * co) ** 2)
    E[:, JOINT_INDEX["left_ankle"], 0] = e * 8 * np.sin(phi - 0.6)
    E[:, JOINT_INDEX["right_ankle"], 0] = -e * 8 * np.sin(phi - 0.6)
    # Arms swing against the legs; elbows bend more on the forward swing.
    _add(E, "left_shoulder", x=arm_amp * a * e * s)
    _add(E, "right_shoulder", x=-arm_amp * a * e * s)
    _add(E, "left_elbow", y=-e * (elbow_extra + 10 * (0.5 - 0.5 * s)))
    _add(E, "right_elbow", y=e * (elbow_extra + 10 * (0.5 + 0.5 * s)))
    # Trunk: forward lean, counter-rotation of the chest against the pelvis.
    _add(E, "spine1", x=lean * e)
    _add(E, "spine2", y=0.6 * pelvis_yaw * e * s)
    _add(E, "spine3", y=0.4 * pelvis_yaw * e * s)
    root = np.zeros((T, 3))
    root[:, 1] = -pelvis_yaw * e * s
    root[:, 2] = 2.0 * e * co
    # Speed from the stance foot: it sweeps 2 L sin(A) per half cycle.
    speed = 4 * c.leg_length * f * math.sin(hip_amp * a * _D)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(c.t))]) * speed
    heading = np.zeros(T)
    forward = np.array([0.0, -1.0])  # canonical +z after R_x(90 deg), heading 0
    return _Curves(E, root, heading, dist[:, None] * forward, anchor="root")


def _walk(c: _Ctx) -> _Curves:
    return _gait(c, freq=0.9, hip_amp=22, knee_amp=55, knee_base=5, arm_amp=16, elbow_extra=3, lean=3,
                 pelvis_yaw=5)


def _run(c: _Ctx) -> _Curves:
    cur = _gait(c, freq=1.4, hip_amp=34, knee_amp=90, knee_base=12, arm_amp=30, elbow_extra=70, lean=10,
                pelvis_yaw=8)
    return cur


def _twirl(c: _Ctx) -> _Curves:
    T = len(c.t)
    D = max(float(c.t[-1]), 1e-6)
    turns = float(c.rng.uniform(1.25, 1.75))
    e = c.env(0.6)
    E = _standing(T)
    _add(E, "left_shoulder", z=38 * e)  # arms float out (to -30 deg below horizontal)
    _add(E, "right_shoulder", z=-38 * e)
    _add(E, "left_elbow", y=-8 * e)
    _add(E, "right_elbow", y=8 * e)
    _add(E, "spine2", z=0.0, x=2 * e)
    _add(E, "head", x=-5 * e)
    for side in ("left", "right"):
        _add(E, f"{side}_knee", x=6 * e)
        _add(E, f"{side}_hip", x=-3 * e)
        _add(E, f"{side}_ankle", x=-3 * e)
    heading = 2 * np.pi * turns * _smootherstep(c.t / D)
    return _Curves(E, np.zeros((T, 3)), heading, _zeros2(T))


def _sway(c: _Ctx) -> _Curves:
    T = len(c.t)
    e = c.env(0.8)
    a = c.jitter()
    w = 2 * np.pi * 0.5 * c.jitter(0.9, 1.1) * c.t
    rho = 5 * a * e * np.sin(w)  # pelvis roll
    lam = 4 * a * e * np.sin(w)  # legs lean: the pelvis slides over the feet
    E = _standing(T)
    for side in ("left", "right"):
        _add(E, f"{side}_hip", z=-rho - lam)
    _add(E, "left_ankle", z=lam)
    _add(E, "right_ankle", z=lam)
    _add(E, "left_knee", x=e * 8 * (0.5 + 0.5 * np.sin(w)))
    _add(E, "right_knee", x=e * 8 * (0.5 - 0.5 * np.sin(w)))
    _add(E, "spine1", z=0.8 * rho)
    _add(E, "spine3", z=0.5 * rho)
    _add(E, "head", z=-0.5 * rho)
    lag = np.sin(w - 0.8)
    _add(E, "left_shoulder", z=6 * e * lag, x=8 * e * np.sin(0.5 * w))
    _add(E, "right_shoulder", z=6 * e * lag, x=-8 * e * np.sin(0.5 * w))
    root = np.zeros((T, 3))
    root[:, 2] = rho
    return _Curves(E, root, np.zeros(T), _zeros2(T))


def _dance(c: _Ctx) -> _Curves:
    T = len(c.t)
    e = c.env(0.6)
    a = c.jitter()
    w = 2 * np.pi * 1.0 * c.jitter(0.95, 1.05) * c.t
    E = _standing(T)
    # Bounce: knees bend twice per beat, hips and ankles keep the feet flat.
    k = e * (6 + 10 * (0.5 - 0.5 * np.cos(2 * w)))
    for side in ("left", "right"):
        _add(E, f"{side}_knee", x=k)
        _add(E, f"{side}_hip", x=-0.5 * k)
        _add(E, f"{side}_ankle", x=-0.5 * k)
    roll = 6 * a * e * np.sin(w)
    for side in ("left", "right"):
        _add(E, f"{side}_hip", z=-roll)
    _add(E, "spine1", z=0.7 * roll)
    _add(E, "spine2", y=12 * a * e * np.sin(0.5 * w))
    _add(E, "spine3", y=8 * a * e * np.sin(0.5 * w), z=-0.3 * roll)
    _add(E, "head", y=-10 * e * np.sin(0.5 * w))
    # Arms wave in antiphase between low and just above horizontal.
    _add(E, "left_shoulder", z=e * (50 + 40 * a * np.sin(w)), x=-e * (20 + 20 * np.sin(0.5 * w)))
    _add(E, "right_shoulder", z=-e * (50 - 40 * a * np.sin(w)), x=-e * (20 - 20 * np.sin(0.5 * w)))
    _add(E, "left_elbow", y=-e * 30 * (0.5 + 0.5 * np.sin(w)))
    _add(E, "right_elbow", y=e * 30 * (0.5 - 0.5 * np.sin(w)))
    _add(E, "left_wrist", z=20 * e * np.sin(w + 1.0))
    _add(E, "right_wrist", z=20 * e * np.sin(w + 1.0))
    root = np.zeros((T, 3))
    root[:, 2] = roll
    heading = 0.5 * e * np.sin(0.25 * w)
    return _Curves(E, root, heading, _zeros2(T))


def _arms_up(c: _Ctx) -> _Curves:
    T = len(c.t)
    P = float(np.clip(c.t[-1], 2.0, 4.0)) * c.jitter(0.95, 1.0)
    b = _raise_hold_lower(np.mod(c.t, P) / P)
    E = _standing(T)
    _add(E, "left_shoulder", z=(70 - _SHOULDER_DOWN) * b)
    _add(E, "right_shoulder", z=-(70 - _SHOULDER_DOWN) * b)
    _add(E, "left_collar", z=12 * b)
    _add(E, "right_collar", z=-12 * b)
    _add(E, "left_elbow", y=7 * b)
    _add(E, "right_elbow", y=-7 * b)
    _add(E, "spine3", x=-5 * b)
    _add(E, "head", x=-10 * b)
    return _Curves(E, np.zeros((T, 3)), np.zeros(T), _zeros2(T))


def _raise_hold_lower(x: np.ndarray) -> np.ndarray:
    """0 -> 1 over [0, 0.4], hold, 1 -> 0 over [0.6, 1] (C2)."""
    return np.where(x < 0.5, _smootherstep(x / 0.4), _smootherstep((1.0 - x) / 0.4))


def _jump(c: _Ctx) -> _Curves:
    T = len(c.t)
    P = 1.8 * c.jitter(0.95, 1.05)
    x = np.mod(c.t, P) / P
    crouch = _bump(x, 0.0, 0.30, 0.45) + 0.6 * _bump(x, 0.68, 0.78, 0.95)
    swing = _bump(x, 0.38, 0.52, 0.72)  # arms forward-up at take-off
    flight = _bump(x, 0.42, 0.56, 0.70)
    E = _standing(T)
    for side in ("left", "right"):
        _add(E, f"{side}_knee", x=75 * crouch + 15 * flight)
        _add(E, f"{side}_hip", x=-60 * crouch - 10 * flight)
        _add(E, f"{side}_ankle", x=-28 * crouch + 30 * flight)
    _add(E, "spine1", x=12 * crouch)
    _add(E, "spine2", x=6 * crouch)
    _add(E, "head", x=-10 * crouch)
    _add(E, "left_shoulder", x=40 * crouch - 60 * swing, z=35 * swing)
    _add(E, "right_shoulder", x=40 * crouch - 60 * swing, z=-35 * swing)
    _add(E, "left_elbow", y=-20 * swing)
    _add(E, "right_elbow", y=20 * swing)
    lift = 0.22 * c.jitter() * flight
    return _Curves(E, np.zeros((T, 3)), np.zeros(T), _zeros2(T), anchor="feet", lift=lift)


@dataclass(frozen=True)
class MotionSpec:
    """A library entry."""

    name: str
    description: str
    generator: Callable[[_Ctx], _Curves]


MOTIONS: Mapping[str, MotionSpec] = {
    s.name: s
    for s in (
        MotionSpec("walk", "walk forward (0.9 Hz gait), arms swinging", _walk),
        MotionSpec("run", "run forward (1.4 Hz gait), elbows bent", _run),
        MotionSpec("twirl", "spin in place 1.25-1.75 turns, arms floating out", _twirl),
        MotionSpec("sway", "side-to-side weight shift over planted feet", _sway),
        MotionSpec("dance", "bouncing, hip roll, waving arms, turning +-30 deg", _dance),
        MotionSpec("arms_up", "raise both arms overhead, hold, lower", _arms_up),
        MotionSpec("jump", "crouch, vertical jump (~0.2 m), land; repeats every ~1.8 s", _jump),
    )
}


def _euler_deg_to_aa(E: np.ndarray) -> Tensor:
    """(T, 24, 3) degrees -> (T, 72) axis-angle (float64)."""
    R = euler_to_matrix(torch.from_numpy(E * _D))
    return matrix_to_axis_angle(R).reshape(E.shape[0], -1)


def _rot_x(angle: float) -> Tensor:
    return axis_angle_to_matrix(torch.tensor([angle, 0.0, 0.0], dtype=torch.float64))


def _sole_vertices(body) -> tuple[Tensor, Tensor]:
    """Rest positions (N, 3) and weights (N, 24) of the vertices within 2 cm of the sole."""
    v = body.v_template.double()
    y = v[:, 1]
    sel = y < y.min() + 0.02 * (float(y.max() - y.min()) / 1.7)
    if getattr(body, "vertex_part", None) is not None and body.part_names:
        feet = [i for i, n in enumerate(body.part_names) if n.endswith("_foot")]
        if feet:
            sel = sel & torch.isin(body.vertex_part, torch.tensor(feet))
    return v[sel], body.weights[sel].double()


def _place(curves: _Curves, body, poses: Tensor, fps: float) -> tuple[Tensor, Tensor]:
    """Rh (T, 3) and Th (T, 3) (float64) from the curves and the body.

    1. Rh = R_z(heading) R_x(90 deg) R_root (R_z about world z == R_y about canonical y
       conjugated by R_x(90 deg), so it is composed as R_x(90) R_y(heading) R_root).
    2. Pose the sole vertices and the joints with Th = 0.
    3. Th_xy moves the anchor (mid-ankles or pelvis) onto path_xy.
    4. Th_z puts the lowest sole vertex on z = 0 (through :func:`_ground_height`,
       smooth in time, within a few mm), plus the lift.
    """
    T = poses.shape[0]
    R_root = euler_to_matrix(torch.from_numpy(curves.root_deg * _D))
    hd = torch.from_numpy(curves.heading)
    R_head = axis_angle_to_matrix(torch.stack([torch.zeros_like(hd), hd, torch.zeros_like(hd)], -1))
    R = _rot_x(math.pi / 2) @ R_head @ R_root  # (T, 3, 3)
    Rh = matrix_to_axis_angle(R)
    Rm = axis_angle_to_matrix(poses.reshape(T, NUM_JOINTS, 3))
    fk = forward_kinematics(Rm, body.joints_rest.double(), body.parents)
    M = make_transform(R, torch.zeros(T, 3, dtype=torch.float64))
    A = M[:, None] @ fk.transforms
    joints = torch.einsum("tij,tnj->tni", R, fk.joints)
    sole_rest, sole_w = _sole_vertices(body)
    z = lbs(sole_rest, sole_w, A)[..., 2]  # (T, N) sole heights
    ground = _ground_height(z, sole_rest[:, 0] > 0, fps)
    if curves.anchor == "root":
        anchor = joints[:, 0, :2]
    else:
        anchor = 0.5 * (joints[:, JOINT_INDEX["left_ankle"], :2] + joints[:, JOINT_INDEX["right_ankle"], :2])
    Th = torch.zeros(T, 3, dtype=torch.float64)
    Th[:, :2] = torch.from_numpy(curves.path_xy) - anchor
    Th[:, 2] = -ground + (0.0 if curves.lift is None else torch.from_numpy(curves.lift))
    return Rh, Th


def _soft_min_lse(z: Tensor, tau: float) -> Tensor:
    """-tau log sum exp(-z / tau) over the last axis (<= min, smooth)."""
    zmin = z.amin(-1, keepdim=True)
    return (zmin - tau * torch.log(torch.exp(-(z - zmin) / tau).sum(-1, keepdim=True)))[..., 0]


def _smin_cubic(a: Tensor, b: Tensor, k: float) -> Tensor:
    """C2 smooth minimum with blend width k (Quilez): min - k h^3 / 6."""
    h = (k - (a - b).abs()).clamp(min=0) / k
    return torch.minimum(a, b) - h**3 * k / 6


def _ground_height(z: Tensor, left: Tensor, fps: float) -> Tensor:
    """Smooth stand-in (T,) for the lowest sole height min_n z[t, n].

    The exact minimum kinks in time whenever the lowest point jumps to another
    vertex or to the other foot. 1. Per foot, a 1.5 mm log-sum-exp soft-min over
    its sole vertices; 2. a cubic smooth-min (k = 3 cm) between the feet; 3. the
    (slowly varying, <= 1 cm) gap to the exact minimum is added back after a
    0.1 s Gaussian in time. Result within a few mm of the exact minimum.
    """
    hard = z.amin(-1)
    if left.all() or not left.any():
        soft = _soft_min_lse(z, 0.0015)
    else:
        soft = _smin_cubic(_soft_min_lse(z[:, left], 0.0015), _soft_min_lse(z[:, ~left], 0.0015), 0.03)
    bias = (hard - soft).numpy()
    sigma = 0.1 * fps
    if sigma >= 0.3 and len(bias) >= 3:
        from scipy.ndimage import gaussian_filter1d

        bias = gaussian_filter1d(bias, sigma, mode="nearest", truncate=4.0)
    return soft + torch.from_numpy(bias)


def make_motion(name: str, num_frames: int, fps: float = 30.0, seed: int = 0, body=None) -> Motion:
    """A library motion (see :data:`MOTIONS`) for a body (default: the mannequin).

    num_frames: T >= 2; fps: frames per second; seed: small random variations
    (amplitudes, frequencies, number of turns), deterministic per seed.
    The body only matters through its skeleton and soles (ground contact, stride).
    """
    if name not in MOTIONS:
        raise ValueError(f"make_motion: unknown motion '{name}', choose from {sorted(MOTIONS)}")
    if num_frames < 2 or fps <= 0:
        raise ValueError(f"make_motion: need num_frames >= 2 and fps > 0, got {num_frames}, {fps}")
    if body is None:
        from .model import mannequin_model

        body = mannequin_model()
    J = body.joints_rest.double()
    leg = float(J[JOINT_INDEX["left_hip"], 1] - body.v_template[:, 1].min())
    ctx = _Ctx(t=np.arange(num_frames) / float(fps), rng=np.random.default_rng(seed), leg_length=leg)
    curves = MOTIONS[name].generator(ctx)
    curves.joints_deg[:, 0] = 0.0  # the root rotation lives in Rh
    poses = clamp_to_joint_limits(_euler_deg_to_aa(curves.joints_deg))
    Rh, Th = _place(curves, body, poses, float(fps))
    return Motion(name=name, fps=float(fps), poses=poses.float(), Rh=Rh.float(), Th=Th.float(),
                  shapes=torch.zeros(10))


# ------------------------------------------------------------- edit operations
def _slerp(q0: Tensor, q1: Tensor, w: Tensor) -> Tensor:
    """Quaternion slerp (wxyz), batched: q0, q1 (..., 4); w (...) or broadcastable."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    w = w[..., None] if w.ndim == q0.ndim - 1 else w
    theta = torch.acos(dot)
    s = torch.sin(theta)
    near = s < 1e-6
    s_safe = torch.where(near, torch.ones_like(s), s)
    a = torch.where(near, 1 - w, torch.sin((1 - w) * theta) / s_safe)
    b = torch.where(near, w, torch.sin(w * theta) / s_safe)
    q = a * q0 + b * q1
    return q / q.norm(dim=-1, keepdim=True)


def _interp_rot(aa: Tensor, i0: Tensor, i1: Tensor, w: Tensor) -> Tensor:
    """Slerp axis-angle rotations aa (T, K, 3) between frames i0 and i1 (N,), weights w (N,)."""
    q = matrix_to_quaternion(axis_angle_to_matrix(aa.double()))
    q = _slerp(q[i0], q[i1], w[:, None].double())
    return matrix_to_axis_angle(quaternion_to_matrix(q))


def resample(motion: Motion, fps: float) -> Motion:
    """Re-time a motion to a new frame rate over the same duration.

    Joint rotations and Rh are slerped, Th is linearly interpolated; the new frames
    sit at k / fps for k = 0 .. floor(duration * fps).
    """
    if fps <= 0:
        raise ValueError(f"resample: fps must be > 0, got {fps}")
    n = int(math.floor(motion.duration * fps + 1e-9)) + 1
    src = torch.arange(n, dtype=torch.float64) / fps * motion.fps  # fractional source frame
    i0 = src.floor().long().clamp(0, motion.num_frames - 1)
    i1 = (i0 + 1).clamp(max=motion.num_frames - 1)
    w = (src - i0.double()).clamp(0, 1)
    poses = _interp_rot(motion.poses.reshape(-1, NUM_JOINTS, 3), i0, i1, w).reshape(n, -1)
    Rh = _interp_rot(motion.Rh[:, None], i0, i1, w)[:, 0]
    Th = (1 - w)[:, None] * motion.Th[i0].double() + w[:, None] * motion.Th[i1].double()
    return replace(motion, fps=float(fps), poses=poses.float(), Rh=Rh.float(), Th=Th.float())


def transform_motion(motion: Motion, R: Tensor, t: Tensor) -> Motion:
    """Apply a world rigid transform x -> R x + t: Rh' = R Rh, Th' = R Th + t
    (EasyMocap, doc/02_output.md). R: (3, 3), t: (3,)."""
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"transform_motion: R must be (3, 3) and t (3,), got {tuple(R.shape)}, {tuple(t.shape)}")
    R = R.double()
    Rh = matrix_to_axis_angle(R @ axis_angle_to_matrix(motion.Rh.double()))
    Th = motion.Th.double() @ R.T + t.double()
    return replace(motion, Rh=Rh.float(), Th=Th.float())


def _yaw(Rh: Tensor) -> Tensor:
    """Heading (radians about world z) of the canonical facing direction +z."""
    f = axis_angle_to_matrix(Rh.double())[..., :, 2]
    return torch.atan2(f[..., 1], f[..., 0])


def concatenate(motions: Sequence[Motion], blend: int = 8, name: str | None = None) -> Motion:
    """Chain motions: each one is turned about world z and shifted in xy so that its
    first frame continues the previous motion (heading and Th xy of the frame where
    the blend starts), then the ``blend`` overlapping frames are cross-faded with a
    C2 ramp (slerp for rotations, lerp for Th). All motions are resampled to the
    first one's fps. Th xy stands for the pelvis position (exact for the mannequin,
    whose pelvis is the canonical origin). The cross-fade does not re-solve the
    ground contact, so feet may dip ~1-2 cm during a blend between unlike poses.
    """
    if not motions:
        raise ValueError("concatenate: need at least one motion")
    fps = motions[0].fps
    out = motions[0]
    for m in motions[1:]:
        if abs(m.fps - fps) > 1e-9:
            m = resample(m, fps)
        b = int(min(max(blend, 0), out.num_frames - 1, m.num_frames - 1))
        k = out.num_frames - b if b > 0 else out.num_frames - 1  # frame that m's frame 0 continues
        dpsi = _yaw(out.Rh[k]) - _yaw(m.Rh[0])
        c, s = math.cos(float(dpsi)), math.sin(float(dpsi))
        Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        m = transform_motion(m, Rz, torch.zeros(3, dtype=torch.float64))
        shift = torch.zeros(3, dtype=torch.float64)
        shift[:2] = out.Th[k, :2].double() - m.Th[0, :2].double()
        m = transform_motion(m, torch.eye(3, dtype=torch.float64), shift)
        if b > 0:
            w = torch.from_numpy(_smootherstep((np.arange(b) + 1) / (b + 1)))
            ia = torch.arange(out.num_frames - b, out.num_frames)
            both_p = torch.stack([out.poses[ia], m.poses[:b]]).reshape(2, b, NUM_JOINTS, 3)
            qp = matrix_to_quaternion(axis_angle_to_matrix(both_p.double()))
            pb = matrix_to_axis_angle(quaternion_to_matrix(_slerp(qp[0], qp[1], w[:, None, None]))).reshape(b, -1)
            qr = matrix_to_quaternion(axis_angle_to_matrix(torch.stack([out.Rh[ia], m.Rh[:b]]).double()))
            rb = matrix_to_axis_angle(quaternion_to_matrix(_slerp(qr[0], qr[1], w[:, None])))
            tb = (1 - w)[:, None] * out.Th[ia].double() + w[:, None] * m.Th[:b].double()
            mid = (pb.float(), rb.float(), tb.float())
        else:
            mid = (out.poses[:0], out.Rh[:0], out.Th[:0])
        keep = out.num_frames - b
        out = Motion(
            name=name or f"{out.name}+{m.name}", fps=fps,
            poses=torch.cat([out.poses[:keep], mid[0], m.poses[b:]]),
            Rh=torch.cat([out.Rh[:keep], mid[1], m.Rh[b:]]),
            Th=torch.cat([out.Th[:keep], mid[2], m.Th[b:]]),
            shapes=out.shapes,
        )
    return out
