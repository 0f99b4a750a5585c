"""anidress_core.fit.proposals: garment pose candidates from the simulation database, scored by the loss."""
from __future__ import annotations

import math

import pytest
import torch

from anidress_core import fit
from anidress_core.fit import proposals as P
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
    props = P.frame_proposals(db, q, t, nearest=2, velocity_weight=0.01, own="seq-obs", offsets=2)
    assert props.labels[0] == f"lib-a:{t - shift}" and props.labels[2:] == ["seq-obs:+0", "seq-obs:-1", "seq-obs:+1",
                                                                           "seq-obs:-2", "seq-obs:+2"]
    truth = obs[t, 0, None] @ local
    torch.testing.assert_close(props.transforms[0], truth)
    torch.testing.assert_close(props.transforms[2], truth)
    # offsets past the end are skipped
    assert P.frame_proposals(db, q, T + shift - 1, 0, 0.01, own="seq-obs", offsets=2).labels == \
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
    pb = fit.make_problem(rig, views, cues, None, cfg.replace(weights={"prior": 0.0}))
    assert abs(float(s[2]) - fit.evaluate(pb, lbs(rig.rest, rig.weights, cand[2])).loss) < 1e-9 * float(s[2])


def test_best_of_refines_the_lowest_and_keeps_the_start_when_nothing_beats_it():
    """A chained start in a wrong place and proposals around the truth: best_of refines the
    lowest-scored and keeps it (lower loss, nearer the truth than the refined start); with only
    bad proposals the start is kept."""
    rig, views = toy(C=4, H=64, W=64)
    g = torch.Generator().manual_seed(4)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, _ = render(rig, views, Gt)
    cfg = config(PAPER, max_iters=10, smooth_passes=0)
    wrong = pose(rig, g, 0.3, 0.06, Gt)
    start = fit.fit_frame(rig, views, cues, wrong, cfg)
    near = pose(rig, g, 0.02, 0.005, Gt)
    far = [pose(rig, g, 0.4, 0.08, Gt) for _ in range(3)]
    props = P.Proposals(torch.stack(far[:2] + [near] + far[2:]), ["a", "b", "near", "c"])
    best, rec = P.best_of(rig, views, cues, props, cfg, refine=2, start=start)
    assert rec["kept"] == "near" and "near" in rec["refined"] and len(rec["refined"]) == 2
    assert P.data_loss(best, cfg) < P.data_loss(start, cfg)
    assert rmse(best.verts, xt) < rmse(start.verts, xt)
    bad = P.Proposals(torch.stack(far), ["a", "b", "c"])
    kept, rec = P.best_of(rig, views, cues, bad, cfg, refine=1, start=best)
    assert kept is best and rec["kept"] == "start"
    assert all(math.isfinite(v) for v in rec["scores"])


def test_fit_sequence_takes_proposals_at_keyframes():
    """proposal_every = 3 on 6 frames: frames 0 and 3 are keyframes (notes['proposal']), the others
    are not asked; a start far from the truth is replaced at frame 0 by the proposal near it, so the
    whole sequence is near the truth; settings out of range are refused."""
    from tests.fit.scenes import textured_sequence

    T = 6
    rig, views, frames, ref, Gs, wrong, g = textured_sequence(T)
    asked = []

    def proposals_of(t):
        asked.append(t)
        return P.Proposals(torch.stack([pose(rig, g, 0.4, 0.08, Gs[t]), pose(rig, g, 0.01, 0.003, Gs[t])]),
                           ["far", "near"])

    cfg = config(dict(PAPER, normal=300.0, anchor=1e5, flow=0.0), max_iters=2, max_iters_first=2, smooth_passes=0,
                 proposal_every=3, proposal_refine=1)
    res = fit.fit_sequence(rig, views, T, lambda t: frames[t][0], lambda t: None, wrong, cfg, progress=False,
                           anchor_init=ref, proposals_of=proposals_of)
    assert asked == [0, 3]
    assert [("proposal" in r.notes) for r in res] == [True, False, False, True, False, False]
    assert res[0].notes["proposal"]["kept"] == "near" and res[0].notes["proposal"]["candidates"] == 2
    assert res[0].notes["proposal"]["loss"] < res[0].notes["proposal"]["chained_loss"]
    plain = fit.fit_sequence(rig, views, T, lambda t: frames[t][0], lambda t: None, wrong,
                             cfg.replace(proposal_every=0), progress=False, anchor_init=ref)
    err = [rmse(r.verts, frames[t][1]) for t, r in enumerate(res)]
    err_plain = [rmse(r.verts, frames[t][1]) for t, r in enumerate(plain)]
    assert max(err) < 0.02 < err_plain[0], (err, err_plain)
    for bad in ({"proposal_every": -1}, {"proposal_offsets": -2}, {"proposal_velocity_weight": float("nan")}):
        with pytest.raises(ValueError):
            config(**bad)


def test_nearest_method_picks_the_database_pose_and_does_not_optimise():
    """method 'nearest' (the baseline): every frame is the candidate with the lowest loss, as given
    (no iteration); without a database it refuses."""
    from tests.fit.scenes import textured_sequence

    T = 3
    rig, views, frames, ref, Gs, wrong, g = textured_sequence(T)
    cands = {t: torch.stack([pose(rig, g, 0.4, 0.08, Gs[t]), Gs[t], pose(rig, g, 0.2, 0.05, Gs[t])]) for t in range(T)}
    cfg = fit.apply_variant(config(dict(PAPER, normal=300.0, anchor=1e5, flow=0.0)), "nearest")
    res = fit.fit_sequence(rig, views, T, lambda t: frames[t][0], lambda t: None, wrong, cfg, progress=False,
                           anchor_init=ref, proposals_of=lambda t: P.Proposals(cands[t], ["far", "true", "mid"]))
    for t, r in enumerate(res):
        assert r.notes["nearest"] == {"kept": "true", "candidates": 3}
        assert r.iterations == 0 and torch.equal(r.transforms, Gs[t].double())
    with pytest.raises(ValueError, match="proposals_of"):
        fit.fit_sequence(rig, views, 1, lambda t: frames[t][0], lambda t: None, wrong, cfg, progress=False)


def test_sim_delta_start_follows_the_simulated_motion():
    """start 'sim_delta': frame t starts from frame t-1's result moved by the simulation's own change
    t-1 -> t. With a simulation that is the truth and a correct frame 0, every start is the truth, so
    one LM iteration per frame stays near it (the loss minimum is a few mm off the truth); started from the previous result instead, fast motion is
    not caught up in one iteration. Without the simulated transforms it refuses."""
    from anidress_core.fit.images import chromaticity
    from tests.fit.scenes import cone_colour, textured, toy

    rig, views = toy(C=4, H=64, W=64)
    ref = fit.AnchorRef(chromaticity(cone_colour(rig.rest)), torch.ones(rig.rest.shape[0], dtype=torch.bool))
    g = torch.Generator().manual_seed(3)
    Gs = [pose(rig, g, 0.1, 0.02)]
    Gs += [pose(rig, g, 0.12, 0.03, Gs[-1]) for _ in range(3)]  # fast: ~7 deg and 3 cm per frame and bone
    frames = [textured(rig, views, G, cone_colour) for G in Gs]
    cfg = config(dict(PAPER, normal=300.0, anchor=1e5, flow=0.0), max_iters=1, max_iters_first=1, smooth_passes=0)
    run = lambda c, **kw: fit.fit_sequence(rig, views, 4, lambda t: frames[t][0], lambda t: None,  # noqa: E731
                                           Gs[0], c, progress=False, anchor_init=ref, **kw)
    sim = run(cfg.replace(start="sim_delta"), sim_transforms=torch.stack(Gs))
    prev = run(cfg)
    err_sim = [rmse(r.verts, frames[t][1]) for t, r in enumerate(sim)]
    err_prev = [rmse(r.verts, frames[t][1]) for t, r in enumerate(prev)]
    assert max(err_sim) < 0.005 and err_prev[-1] > 5 * err_sim[-1], (err_sim, err_prev)  # 2.6 vs 30 mm
    with pytest.raises(ValueError, match="sim_delta"):
        run(cfg.replace(start="sim_delta"))
