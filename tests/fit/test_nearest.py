"""anidress_core.fit.nearest: the nearest baseline's garment pose candidates from the simulation database,
scored by the loss."""
from __future__ import annotations

import pytest
import torch

from anidress_core import fit
from anidress_core.fit import nearest as P
from anidress_core.geometry import axis_angle_to_matrix, lbs, make_transform
from tests.fit.scenes import PAPER, config, pose, render, rmse, toy

torch.set_num_threads(1)


def rigid(g, rot, trans, n=None):
    shape = () if n is None else (n,)
    R = axis_angle_to_matrix(rot * torch.randn(*shape, 3, generator=g, dtype=torch.float64))
    return make_transform(R, trans * torch.randn(*shape, 3, generator=g, dtype=torch.float64))


def walk(g, T, J=4):
    """(T, J, 4, 4) joint transforms of a 'body' moving along x and swinging its joints."""
    t = torch.arange(T, dtype=torch.float64)
    root = make_transform(axis_angle_to_matrix(torch.stack([0 * t, 0 * t, 0.05 * t], -1)),
                          torch.stack([0.04 * t, 0 * t, 1.0 + 0 * t], -1))
    local = axis_angle_to_matrix(0.4 * torch.sin(0.3 * t[:, None, None] + torch.randn(1, J - 1, 3, generator=g,
                                                                                      dtype=torch.float64)))
    joints = root[:, None].repeat(1, J, 1, 1)
    joints[:, 1:, :3, :3] = root[:, None, :3, :3] @ local
    return joints


def test_body_features_do_not_see_the_root_and_carry_moves_with_it():
    """The pose feature and the velocity in the root frame are the same for a body moved rigidly in
    the world; a garment attached rigidly to the root is carried exactly onto the other body."""
    g = torch.Generator().manual_seed(1)
    joints = walk(g, 12)
    A = rigid(g, 1.0, 0.5)
    moved = A @ joints
    f, h = P.body_features(joints, 30.0), P.body_features(moved, 30.0)
    torch.testing.assert_close(f.pose, h.pose)
    torch.testing.assert_close(f.velocity, h.velocity)
    assert f.pose.shape == (12, 27) and f.velocity.shape == (12, 3)
    torch.testing.assert_close(f.velocity[5], joints[5, 0, :3, :3].t() @ (joints[6, 0, :3, 3] - joints[4, 0, :3, 3])
                               * 15.0)
    local = rigid(g, 0.3, 0.1, 5)  # (B, 4, 4): the garment's bones relative to the root
    G = joints[:, 0, None] @ local  # (T, B, 4, 4)
    torch.testing.assert_close(P.carry(G, joints[:, 0], moved[:, 0]), moved[:, 0, None] @ local)
    with pytest.raises(ValueError, match="J >= 2"):
        P.body_features(joints[:, :1], 30.0)


def test_nearest_frames_find_the_same_body_state_in_another_motion_and_place_it():
    """A database of a 'library' motion (the observed one, moved and time-shifted) and a
    distractor: the frame nearest to observed frame t is the library's frame of the same body
    state, its garment pose carried onto the observed root is the observed garment's pose; the
    observed motion's own simulation gives frames t + o with labels."""
    g = torch.Generator().manual_seed(2)
    T, shift = 20, 3
    obs = walk(g, T + shift)
    local = rigid(g, 0.3, 0.1, 4)
    A = rigid(g, 2.0, 1.0)
    lib = A @ obs[shift:]  # lib frame i = observed frame i + shift
    other = walk(torch.Generator().manual_seed(99), T)
    db = P.make_database({"lib-a": (lib[:, 0, None] @ local, lib, 30.0),
                          "lib-b": (other[:, 0, None] @ local, other, 30.0),
                          "seq-obs": (obs[:, 0, None] @ local, obs, 30.0)})
    assert db.transforms.shape == (2 * T + T + shift, 4, 4, 4) and db.names == ("lib-a", "lib-b", "seq-obs")
    q = P.body_features(obs, 30.0)
    t = 10
    idx = P.nearest_frames(db, q, t, 3, velocity_weight=0.01, exclude=("seq-obs",))
    assert db.names[int(db.sequence[idx[0]])] == "lib-a" and int(db.frame[idx[0]]) == t - shift
    assert "seq-obs" not in {db.names[int(s)] for s in db.sequence[idx]}
    props = P.frame_candidates(db, q, t, nearest=2, velocity_weight=0.01, own="seq-obs", offsets=2)
    assert props.labels[0] == f"lib-a:{t - shift}" and props.labels[2:] == ["seq-obs:+0", "seq-obs:-1", "seq-obs:+1",
                                                                           "seq-obs:-2", "seq-obs:+2"]
    truth = obs[t, 0, None] @ local
    torch.testing.assert_close(props.transforms[0], truth)
    torch.testing.assert_close(props.transforms[2], truth)
    # offsets past the end are skipped
    assert P.frame_candidates(db, q, T + shift - 1, 0, 0.01, own="seq-obs", offsets=2).labels == \
        ["seq-obs:+0", "seq-obs:-1", "seq-obs:-2"]


@pytest.mark.parametrize("weights", [PAPER, dict(PAPER, normal=300.0)], ids=["paper", "normal300"])
def test_scoring_picks_the_true_pose_out_of_a_set(weights):
    """The true frame's transforms hidden among eight others (perturbed by 2-9 cm at the hem):
    the lowest score is the truth's; the score is evaluate()'s loss, prior left out."""
    rig, views = toy(C=4, H=64, W=64)
    g = torch.Generator().manual_seed(3)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, fr = render(rig, views, Gt)
    others = [pose(rig, g, s, 0.3 * s, Gt) for s in (0.05, 0.08, 0.1, 0.12, 0.15, 0.2, 0.25, 0.3)]
    cand = torch.stack(others[:5] + [Gt] + others[5:])
    cfg = config(weights)
    s = P.score_poses(rig, views, cues, cand, cfg)
    assert int(torch.argmin(s)) == 5 and bool(torch.isfinite(s).all())
    assert min(rmse(lbs(rig.rest, rig.weights, c), xt) for c in others) > 0.005
    # the score is the loss of evaluate() on the frame's problem (whole images, no crop)
    pb = fit.make_problem(rig, views, cues, cfg.replace(weights={"prior": 0.0}))
    assert abs(float(s[2]) - fit.evaluate(pb, lbs(rig.rest, rig.weights, cand[2])).loss) < 1e-9 * float(s[2])


def test_nearest_method_picks_the_database_pose_and_does_not_optimise():
    """method 'nearest' (the baseline): every frame is the candidate with the lowest loss, as given
    (no iteration); without a database it refuses."""
    from tests.fit.scenes import textured_sequence

    T = 3
    rig, views, frames, ref, Gs, wrong, g = textured_sequence(T)
    cands = {t: torch.stack([pose(rig, g, 0.4, 0.08, Gs[t]), Gs[t], pose(rig, g, 0.2, 0.05, Gs[t])]) for t in range(T)}
    cfg = fit.apply_variant(config(dict(PAPER, normal=300.0, anchor=1e5, flow=0.0)), "nearest")
    plan = fit.FitPlan(cfg, rig, views, T, wrong, anchor_init=ref,
                       candidates_of=lambda t: P.Candidates(cands[t], ["far", "true", "mid"]))
    res = fit.fit_sequence(plan, lambda t: frames[t][0], lambda t: None, progress=False)
    for t, r in enumerate(res):
        assert r.notes["nearest"] == {"kept": "true", "candidates": 3}
        assert r.iterations == 0 and torch.equal(r.transforms, Gs[t].double())
    with pytest.raises(ValueError, match="candidates_of"):
        fit.fit_sequence(plan._replace(candidates_of=None), lambda t: frames[t][0], lambda t: None, progress=False)


def test_the_baseline_uses_the_settings_it_ran_with():
    """The candidates' defaults are the module's constants, the values of the settings the baseline ran with
    in benchmarks/fit.md (8 nearest frames, offsets +-2, velocity weight 0.05 s^2)."""
    import inspect

    sig = inspect.signature(P.frame_candidates).parameters
    assert (sig["nearest"].default, sig["velocity_weight"].default, sig["offsets"].default) == (8, 0.05, 2)
    assert (P.NEAREST, P.VELOCITY_WEIGHT, P.OFFSETS) == (8, 0.05, 2)
