"""Stage fit on a tiny synthetic skirt scene (rig from its own ground truth, tests/fit/conftest.py), and the
garment_poses.npz reader/writer (anidress_core.io.garment_poses)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from anidress_core import fit
from tests.fit.conftest import ensemble, tiny_cloth

torch.set_num_threads(1)


def stored_loss_is_the_weighted_sum(gp) -> None:
    assert set(gp.terms) == set(fit.TERM_NAMES) and set(gp.weights) == set(fit.TERM_NAMES)
    total = sum(gp.weights[k] * gp.terms[k] for k in fit.TERM_NAMES)
    np.testing.assert_allclose(gp.loss, total, rtol=1e-12, atol=0)


def test_stage_fit_on_a_tiny_scene(tiny_skirt):
    pytest.importorskip("warp")  # L_collision's body planes
    from anidress_core.geometry import lbs
    from anidress_core.io.garment_poses import load_garment_poses, read_garment_poses
    from anidress_core.io.rig import read_rig
    from anidress_core.stages.fit import run_fit

    data, res = tiny_skirt
    seq = data / "walk"
    params = {"views": 3, "max_iters": 4, "max_iters_first": 6}
    args = (data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows")
    ens = {"sim_ensemble_npz": ensemble(res)}
    meta = run_fit(*args, seq / "normals", params, res / "walk" / "garment_poses.npz", progress=False, **ens)
    gp = read_garment_poses(res / "walk" / "garment_poses.npz", frames=4, bones=6)
    a = load_garment_poses(res / "walk" / "garment_poses.npz")[0]
    assert gp.transforms.shape == (4, 6, 4, 4) and gp.transforms.dtype == np.float32
    assert gp.verts.shape == (4, 500, 3) and np.isfinite(gp.verts).all()
    assert a["curve"].shape[0] == 4 and gp.iterations.shape == (4,) and (a["flow_targets"][1:] > 0).all()
    assert a["flow_targets"][0] == 0 and len(meta["cameras"]) == 3
    # the pipeline's loss by default, every weight stored as used, every minimised term stored
    assert meta["loss"] == "pipeline" and meta["weights"] == {k: float(v) for k, v in
                                                              fit.FitConfig.from_config({}).weights.__dict__.items()}
    assert gp.header["meta"]["weights"]["normal"] == 300.0
    stored_loss_is_the_weighted_sum(gp)
    assert gp.terms["anchor"][0] == 0 and (gp.terms["anchor"][1:] > 0).all()  # first-seen image references
    assert meta["anchor_reference"].startswith("images")
    assert (gp.terms["prior"] > 0).all()  # L_prior towards the ensemble's mean simulation, every frame
    followed = f"{ensemble(res)}: the mean of 2 simulations (bending stiffness [0.0001, 0.001] J, settle frames [4])"
    assert meta["followed_simulation"].startswith(followed) and meta["first_frame_start"].startswith(followed)
    assert "members' spread (prior_spread_floor 1)" in meta["followed_simulation"]  # L_prior's weight per vertex
    # the rig's own simulation instead (one stiffness, fit/prior_reference sim): no ensemble read
    meta = run_fit(*args, seq / "normals", dict(params, prior_reference="sim"), res / "walk" / "single.npz",
                   progress=False)
    assert meta["followed_simulation"] == "rig transforms of the simulated sequence seq-walk"
    assert meta["first_frame_start"].startswith("rig transforms of the simulated sequence seq-walk")
    # the ensemble asked for and missing: the error names it
    with pytest.raises(FileNotFoundError, match="sim_ensemble"):
        run_fit(*args, seq / "normals", params, res / "walk" / "x.npz", progress=False)
    # an ensemble written without its spread (before it was stored): the error names the file and the fix
    from anidress_core.io.files import ArtifactError
    from anidress_core.io.sim import read_sim, write_sim

    bare = res / "walk" / "no_spread.npz"
    write_sim(bare, dataclasses.replace(read_sim(ensemble(res)), spread=None))
    with pytest.raises(ArtifactError, match=r"no_spread\.npz: no 'spread'.*simulate_ensemble"):
        run_fit(*args, seq / "normals", params, res / "walk" / "x.npz", progress=False, sim_ensemble_npz=bare)
    # the fitted transforms reproduce the fitted vertices through the rig (the field stage's contract)
    art = read_rig(res / "rig.npz", dtype=torch.float64)
    x = lbs(art.model.rest, art.model.weights, torch.as_tensor(gp.transforms).double())
    assert float((x - torch.as_tensor(gp.verts).double()).abs().max()) < 1e-4
    # fit/loss: paper switches to the paper's loss; first-seen image references start at frame 1
    meta = run_fit(*args, seq / "normals", dict(params, loss="paper"), res / "walk" / "paper.npz", progress=False,
                   **ens)
    gp = read_garment_poses(res / "walk" / "paper.npz")
    assert meta["loss"] == "paper" and gp.weights["normal"] == 0.1 and (gp.terms["anchor"] == 0).all()
    stored_loss_is_the_weighted_sum(gp)
    run_fit(*args, seq / "normals", params, res / "walk" / "start_prior.npz", ablation="pipeline_no_sim_prior",
            progress=False)  # the earlier L_prior: frame 0 only
    gp = read_garment_poses(res / "walk" / "start_prior.npz")
    assert gp.terms["prior"][0] > 0 and (gp.terms["prior"][1:] == 0).all() and gp.weights["prior"] == 10.0
    texture = dict(params, anchor_reference="texture")
    run_fit(*args, seq / "normals", texture, res / "walk" / "texture.npz", ablation="pipeline_no_collision",
            progress=False, **ens)
    gp = read_garment_poses(res / "walk" / "texture.npz")
    assert gp.header["meta"]["loss"] == "pipeline_no_collision" and (gp.terms["collision"] == 0).all()
    assert (gp.terms["anchor"] > 0).all() and "texture.png" in gp.header["meta"]["anchor_reference"]  # frame 0 on
    # references from the garment texture without a texture: a clear error
    tex = data / "garment" / "texture.png"
    tex.rename(tex.with_suffix(".bak"))
    try:
        with pytest.raises(FileNotFoundError, match="texture"):
            run_fit(*args, seq / "normals", texture, res / "walk" / "x.npz", progress=False, **ens)
    finally:
        tex.with_suffix(".bak").rename(tex)
    # no normal maps: the normal weight is stored as 0
    run_fit(*args, None, params, res / "walk" / "no_flow.npz", ablation="paper_no_flow", progress=False, **ens)
    gp = read_garment_poses(res / "walk" / "no_flow.npz")
    assert gp.weights["normal"] == 0 and gp.weights["flow"] == 0
    # a missing mask is named in the error
    with pytest.raises(FileNotFoundError, match="mask"):
        run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "nope", None, None, params,
                res / "walk" / "x.npz", progress=False, **ens)


def test_garment_poses_reader_checks_the_caller_shapes(tmp_path):
    from anidress_core.io import files
    from anidress_core.io.garment_poses import read_garment_poses, save_garment_poses

    T, B, V = 3, 2, 5
    G = np.tile(np.eye(4, dtype=np.float32), (T, B, 1, 1))
    terms = {k: np.full(T, 0.5) for k in fit.TERM_NAMES}
    weights = {k: 2.0 for k in fit.TERM_NAMES}
    loss = np.full(T, float(len(fit.TERM_NAMES)))  # sum of 2.0 x 0.5
    p = tmp_path / "garment_poses.npz"
    save_garment_poses(p, G, np.zeros((T, V, 3)), np.zeros((1, 3), np.int64), loss, terms, weights,
                       np.ones(T), np.ones(T, bool), np.zeros(T), np.zeros(T), np.zeros((T, 2)), {}, {"loss": "x"})
    gp = read_garment_poses(p, frames=T, bones=B)
    assert gp.weights == weights and set(gp.terms) == set(fit.TERM_NAMES) and gp.header["meta"]["loss"] == "x"
    stored_loss_is_the_weighted_sum(gp)
    with pytest.raises(files.ArtifactError, match="to match the rig"):
        read_garment_poses(p, bones=B + 1)
    with pytest.raises(files.ArtifactError, match="frames of garment poses"):
        read_garment_poses(p, frames=T + 1)
    G[1, 0, 0, 0] = np.nan
    save_garment_poses(p, G, np.zeros((T, V, 3)), np.zeros((1, 3), np.int64), loss, terms, weights,
                       np.ones(T), np.ones(T, bool), np.zeros(T), np.zeros(T), np.zeros((T, 2)), {}, {})
    with pytest.raises(files.ArtifactError, match="NaN"):
        read_garment_poses(p)
    with pytest.raises(ValueError, match="without values"):
        save_garment_poses(p, G, np.zeros((T, V, 3)), np.zeros((1, 3), np.int64), np.full(T, 6.0), {}, weights,
                           np.ones(T), np.ones(T, bool), np.zeros(T), np.zeros(T), np.zeros((T, 2)), {}, {})


def test_stage_records_what_it_did_about_bad_cues(tiny_skirt, tmp_path):
    """An empty mask file (one camera, frame 2) and a missing flow file (frame 1): finite poses and
    losses, the view dropped and the missing flow said per frame in the header's frame_notes."""
    pytest.importorskip("warp")
    import shutil

    from anidress_core.io import files
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.stages.fit import run_fit, select_views

    data, res = tiny_skirt
    seq = data / "walk"
    masks, flows = tmp_path / "masks", tmp_path / "flows"
    shutil.copytree(seq / "gt" / "masks", masks)
    shutil.copytree(seq / "gt" / "flows", flows)
    from anidress_core.io.scene import read_scene

    cams = select_views(read_scene(data)["cameras"]["train"], 3)
    p = masks / cams[1] / "000002.png"
    files.write_mask(p, np.zeros_like(files.read_mask(p)))
    (flows / cams[0] / "000001.exr").unlink()
    meta = run_fit(data, "walk", res / "rig.npz", res / "template.npz", masks, flows, seq / "normals",
                   {"views": 3, "max_iters": 4, "max_iters_first": 6}, tmp_path / "gp.npz", progress=False,
                   sim_ensemble_npz=ensemble(res))
    gp = read_garment_poses(tmp_path / "gp.npz", frames=4, bones=6)
    assert np.isfinite(gp.transforms).all() and np.isfinite(gp.loss).all()
    assert all(np.isfinite(v).all() for v in gp.terms.values())
    assert gp.header["meta"]["frame_notes"] == meta["frame_notes"]
    notes = {t: dict(n) for t, n in meta["frame_notes"].items()}
    windows = {t: n.pop("window") for t, n in notes.items() if "window" in n}
    assert list(windows) == ["3"] and windows["3"]["frames"] == 4  # the default fit/window 5, four frames
    assert windows["3"]["loss"] <= windows["3"]["chain_loss"]
    assert {t: n for t, n in notes.items() if n} == {"1": {"no_flow": True}, "2": {"views_dropped": [1]}}


def test_stage_nearest_baseline_from_the_simulation_database(tiny_skirt, tmp_path):
    """Variant nearest: the database is the rig's simulated sequences with their body motions (motions_dir,
    rule motions' files); every frame records the candidate it kept, none is optimised; without motions_dir
    a clear error. (The tiny rig's only sequence is the observed one, so only its time offsets are candidates.)"""
    pytest.importorskip("warp")
    from anidress_core.io.body_motion import write_motion
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.io.scene import load_sequence_motion, read_scene
    from anidress_core.stages.fit import run_fit

    data, res = tiny_skirt
    seq = data / "walk"
    write_motion(tmp_path / "seq-walk.npz", load_sequence_motion(data, "walk", read_scene(data)["fps"]))
    params = {"views": 3, "max_iters": 4, "max_iters_first": 6}
    args = (data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
            seq / "normals", params, tmp_path / "gp.npz")
    meta = run_fit(*args, ablation="nearest", progress=False, motions_dir=tmp_path, sim_ensemble_npz=ensemble(res))
    gp = read_garment_poses(tmp_path / "gp.npz", frames=4, bones=6)
    assert np.isfinite(gp.transforms).all() and np.isfinite(gp.loss).all() and (gp.iterations == 0).all()
    assert meta["simulation_database"].startswith("4 simulated frames of ['seq-walk']")
    notes = meta["frame_notes"]
    # offsets -2..2 inside the 4 frames (0..3)
    assert [notes[str(t)]["nearest"]["candidates"] for t in range(4)] == [3, 4, 4, 3], notes
    assert all(notes[str(t)]["nearest"]["kept"].startswith("seq-walk:") for t in range(4))
    with pytest.raises(ValueError, match="motions_dir"):
        run_fit(*args, ablation="nearest", progress=False, sim_ensemble_npz=ensemble(res))


def test_the_ensemble_is_the_mean_of_its_members(tiny_skirt, tmp_path):
    """rule simulate_ensemble: the file holds the per-vertex mean of the simulations at each stiffness (each as
    rule simulate would make it) and their spread about it, its members in the header; an empty list of
    stiffnesses is an error."""
    pytest.importorskip("warp")
    from anidress_core.config import section_defaults
    from anidress_core.io.sim import read_sim
    from anidress_core.stages.simulate import run_simulate, run_simulate_ensemble

    data, res = tiny_skirt
    cloth = tiny_cloth({"simulate": section_defaults("simulate", {})})
    members = [run_simulate(res / "template.npz", res / "motions" / "seq-walk.npz", data,
                            {**cloth, "bend_stiffness": k}, tmp_path / f"{k:g}.npz", progress=False).frames
               for k in (1e-4, 1e-3)]
    ens = read_sim(ensemble(res))
    X = np.stack(members).astype(np.float64)
    np.testing.assert_allclose(ens.frames, X.mean(0), atol=1e-6)
    # and the members' spread about it, per frame and vertex (L_prior's weight with fit/prior_spread_floor)
    assert ens.spread.shape == ens.frames.shape[:2] and float(ens.spread.max()) > 0
    np.testing.assert_allclose(ens.spread, np.sqrt(((X - X.mean(0)) ** 2).sum(-1).mean(0)), atol=1e-6)
    assert [m["bend_stiffness"] for m in ens.meta["members"]] == [1e-4, 1e-3]
    np.testing.assert_allclose(ens.members, X, atol=1e-6)  # and every member's frames, in that order
    assert ens.max_stretch.shape == (4,) and np.isfinite(ens.frames).all()
    with pytest.raises(ValueError, match="ensemble_bend_stiffness"):
        run_simulate_ensemble(res / "template.npz", res / "motions" / "seq-walk.npz", data, cloth, [],
                              tmp_path / "e.npz", progress=False)


def test_the_ensemble_has_every_stiffness_at_every_settle_length(tiny_skirt, tmp_path):
    """simulate/ensemble_settle_frames: one member per stiffness and settle length (several garment states at
    frame 0), each as rule simulate makes it with that cloth/settle_frames; the header and the fit's note name
    them; a negative length is an error."""
    pytest.importorskip("warp")
    from anidress_core.config import section_defaults
    from anidress_core.io.sim import read_sim
    from anidress_core.fit.ensemble import ensemble_note
    from anidress_core.stages.simulate import run_simulate, run_simulate_ensemble

    data, res = tiny_skirt
    cloth = tiny_cloth({"simulate": section_defaults("simulate", {})})
    motion = res / "motions" / "seq-walk.npz"
    members = [run_simulate(res / "template.npz", motion, data, {**cloth, "bend_stiffness": 1e-3, "settle_frames": n},
                            tmp_path / f"{n}.npz", progress=False).frames for n in (2, 6)]
    assert not np.allclose(members[0], members[1], atol=1e-4)  # another start, another motion
    out = run_simulate_ensemble(res / "template.npz", motion, data, cloth, [1e-3], tmp_path / "e.npz",
                                progress=False, settle_frames=[2, 6])
    np.testing.assert_allclose(read_sim(tmp_path / "e.npz").frames, np.stack(members).astype(np.float64).mean(0),
                               atol=1e-6)
    assert [(m["bend_stiffness"], m["settle_frames"]) for m in out.meta["members"]] == [(1e-3, 2), (1e-3, 6)]
    assert ensemble_note(out.meta) == "the mean of 2 simulations (bending stiffness [0.001] J, settle frames [2, 6])"
    # [] (or None): the cloth's own settle length alone, as before
    assert [m["settle_frames"] for m in read_sim(ensemble(res)).meta["members"]] == [4, 4]
    with pytest.raises(ValueError, match="ensemble_settle_frames"):
        run_simulate_ensemble(res / "template.npz", motion, data, cloth, [1e-3], tmp_path / "f.npz", progress=False,
                              settle_frames=[-1])
