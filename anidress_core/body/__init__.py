"""Body models (SMPL or a procedural mannequin), kinematics and a motion library.

Modules: :mod:`.kinematic` (SMPL joint tree, forward kinematics), :mod:`.mannequin`
(procedural rigged, UV-mapped body), :mod:`.model` (``BodyModel`` posing, SMPL
loading, EasyMocap/SMPL global-placement conversion), :mod:`.motions` (procedural
EasyMocap-convention motions, joint limits). File readers live in
:mod:`anidress_core.io.motion`.
"""
from .kinematic import NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, forward_kinematics
from .model import BodyModel, PosedBody, global_orient_to_rh_th, mannequin_model, rh_th_to_global_orient, smpl_model
from .motions import MOTIONS, Motion, clamp_to_joint_limits, concatenate, make_motion, resample

__all__ = [
    "NUM_JOINTS", "SMPL_JOINT_NAMES", "SMPL_PARENTS", "forward_kinematics",
    "BodyModel", "PosedBody", "global_orient_to_rh_th", "rh_th_to_global_orient", "mannequin_model", "smpl_model",
    "MOTIONS", "Motion", "clamp_to_joint_limits", "concatenate", "make_motion", "resample",
]
