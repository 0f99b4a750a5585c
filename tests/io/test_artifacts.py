"""Round trips and malformed files of the pipeline's artifact readers (anidress_core.io.{template, rig,
body_motion, sim, field}): what is written reads back equal, and a broken file is named with its field."""
import numpy as np
import pytest
import torch

from anidress_core.body.motions import Motion
from anidress_core.garment import GarmentTemplate
from anidress_core.io import files
from anidress_core.io.body_motion import read_motion, write_motion
from anidress_core.io.field import (FIELD_FORMAT, FieldCheckpoint, read_field_checkpoint, read_training_state,
                                    training_state_path, write_field_checkpoint, write_training_state)
from anidress_core.io.rig import (DemBonesRig, DemBonesSequence, RigArtifact, read_dembones_rig, read_dembones_sequence,
                                  read_rig, write_dembones_rig, write_dembones_sequence, write_rig)
from anidress_core.io.sim import SIM_STATS, SimSequence, read_sim, write_sim
from anidress_core.io.template import read_template, write_template
from anidress_core.rig import RigModel

RNG = np.random.default_rng(0)


def _template(V=6, F=4) -> GarmentTemplate:
    w = RNG.random((V, 24)).astype(np.float32)
    return GarmentTemplate(verts=RNG.normal(size=(V, 3)).astype(np.float32),
                           faces=RNG.integers(0, V, size=(F, 3)).astype(np.int64),
                           face_uv=RNG.random((F, 3, 2)).astype(np.float32), band=np.arange(V) < 2,
                           body_weights=w / w.sum(1, keepdims=True), kind="dress")


def _rig(V=6, B=3, sizes=(4, 2)) -> RigArtifact:
    N = sum(sizes)
    M = torch.eye(4).repeat(N, B, 1, 1)
    M[..., :3, 3] = torch.as_tensor(RNG.normal(size=(N, B, 3)), dtype=torch.float32)
    w = torch.as_tensor(RNG.random((V, B)), dtype=torch.float32)
    model = RigModel(rest=torch.as_tensor(RNG.normal(size=(V, 3)), dtype=torch.float32), weights=w / w.sum(1, True),
                     transforms=M, bone_centres=torch.as_tensor(RNG.normal(size=(B, 3)), dtype=torch.float32),
                     rmse=0.0025)
    off = np.concatenate([[0], np.cumsum(sizes)])
    names = [f"lib-m{i}" for i in range(len(sizes))]
    return RigArtifact(model=model, faces=RNG.integers(0, V, size=(5, 3)).astype(np.int64),
                       sequences={n: slice(int(off[i]), int(off[i + 1])) for i, n in enumerate(names)},
                       rmse_per_sequence={n: 0.001 * (i + 1) for i, n in enumerate(names)},
                       meta={"wall_s": 1.5, "history_m": [0.01, 0.0025]})


# --------------------------------------------------------------------------- template
def test_template_round_trip(tmp_path):
    tpl = _template()
    write_template(tmp_path / "template.npz", tpl, config={"k": 1}, meta={"source": "test"})
    back = read_template(tmp_path / "template.npz")
    for k in ("verts", "faces", "face_uv", "band", "body_weights"):
        np.testing.assert_array_equal(getattr(back, k), getattr(tpl, k))
        assert getattr(back, k).dtype == getattr(tpl, k).dtype
    assert back.kind == "dress"
    assert files.load_npz(tmp_path / "template.npz")[1]["meta"] == {"source": "test"}


def test_template_malformed_names_file_and_field(tmp_path):
    tpl = _template()
    p = tmp_path / "bad_template.npz"
    files.save_npz(p, {"verts": tpl.verts, "faces": tpl.faces, "face_uv": tpl.face_uv, "band": tpl.band,
                       "body_weights": tpl.body_weights[:, :10], "kind": np.asarray("dress")})
    with pytest.raises(files.ArtifactError, match=r"bad_template\.npz: .*body_weights"):
        read_template(p)
    files.save_npz(p, {"verts": tpl.verts, "faces": tpl.faces})
    with pytest.raises(files.ArtifactError, match=r"bad_template\.npz: missing arrays .*face_uv"):
        read_template(p)


# --------------------------------------------------------------------------- rig
def test_rig_round_trip(tmp_path):
    rig = _rig()
    write_rig(tmp_path / "rig.npz", rig, config={"bones": 3})
    back = read_rig(tmp_path / "rig.npz")
    for k in ("rest", "weights", "transforms", "bone_centres"):
        assert torch.equal(getattr(back.model, k), getattr(rig.model, k))
    assert back.model.rmse == rig.model.rmse
    np.testing.assert_array_equal(back.faces, rig.faces)
    assert back.sequences == rig.sequences and back.rmse_per_sequence == rig.rmse_per_sequence
    assert back.meta == rig.meta
    assert torch.equal(back.transforms_of("lib-m1"), rig.model.transforms[4:6])
    b64 = read_rig(tmp_path / "rig.npz", dtype=torch.float64)
    assert b64.model.weights.dtype == torch.float64


def test_rig_malformed_names_file_and_field(tmp_path):
    rig = _rig()
    write_rig(tmp_path / "rig.npz", rig)
    a, h = files.load_npz(tmp_path / "rig.npz")
    bad = tmp_path / "bad_rig.npz"
    files.save_npz(bad, {**a, "offsets": np.array([0, 4, 5])}, meta=h["meta"])
    with pytest.raises(files.ArtifactError, match=r"bad_rig\.npz: offsets \[0, 4, 5\] do not cover 6 frames"):
        read_rig(bad)
    files.save_npz(bad, {**a, "bone_centres": a["bone_centres"][:2]})
    with pytest.raises(files.ArtifactError, match=r"bad_rig\.npz: inconsistent shapes"):
        read_rig(bad)
    files.save_npz(bad, {k: v for k, v in a.items() if k != "weights"})
    with pytest.raises(files.ArtifactError, match=r"bad_rig\.npz: missing arrays \['weights'\]"):
        read_rig(bad)
    with pytest.raises(ValueError, match="do not tile"):
        write_rig(tmp_path / "x.npz", RigArtifact(rig.model, rig.faces, {"a": slice(0, 5)}, {"a": 0.0}, {}))


# --------------------------------------------------------------------------- body motion
def test_motion_round_trip(tmp_path):
    T = 5
    m = Motion(name="walk", fps=30.0, poses=torch.as_tensor(RNG.normal(size=(T, 72)), dtype=torch.float32),
               Rh=torch.as_tensor(RNG.normal(size=(T, 3)), dtype=torch.float32),
               Th=torch.as_tensor(RNG.normal(size=(T, 3)), dtype=torch.float32), shapes=torch.zeros(10))
    write_motion(tmp_path / "seq-walk.npz", m, config={"library": []}, meta={"name": "seq-walk", "frames": T})
    back = read_motion(tmp_path / "seq-walk.npz")
    assert back.name == "seq-walk" and back.fps == 30.0
    for k in ("poses", "Rh", "Th", "shapes"):
        assert torch.equal(getattr(back, k), getattr(m, k))
    write_motion(tmp_path / "plain.npz", m)
    assert read_motion(tmp_path / "plain.npz").name == "walk"


def test_motion_malformed_names_file_and_field(tmp_path):
    p = tmp_path / "bad_motion.npz"
    files.save_npz(p, {"poses": np.zeros((4, 69), np.float32), "Rh": np.zeros((4, 3), np.float32),
                       "Th": np.zeros((4, 3), np.float32), "shapes": np.zeros(10, np.float32), "fps": np.float64(30)})
    with pytest.raises(files.ArtifactError, match=r"bad_motion\.npz: .*poses \(T, 72\)"):
        read_motion(p)
    files.save_npz(p, {"poses": np.zeros((4, 72), np.float32)})
    with pytest.raises(files.ArtifactError, match=r"bad_motion\.npz: missing arrays \['Rh', 'Th', 'shapes', 'fps'\]"):
        read_motion(p)


# --------------------------------------------------------------------------- simulated sequence
def test_sim_round_trip(tmp_path):
    T, V = 4, 7
    stats = {k: RNG.random(T) for k in SIM_STATS}
    seq = SimSequence(frames=RNG.normal(size=(T, V, 3)).astype(np.float32),
                      faces=RNG.integers(0, V, size=(6, 3)).astype(np.int64), fps=25.0,
                      meta={"motion": "lib-twirl", "recoveries": [{"frame": 2, "reason": "stretch"}], "wall_s": 1.0},
                      spread=RNG.random((T, V)).astype(np.float32),
                      members=RNG.normal(size=(2, T, V, 3)).astype(np.float32), **stats)
    write_sim(tmp_path / "lib-twirl.npz", seq, config={"stretch": 1.0})
    back = read_sim(tmp_path / "lib-twirl.npz")
    np.testing.assert_array_equal(back.frames, seq.frames)
    np.testing.assert_array_equal(back.faces, seq.faces)
    np.testing.assert_array_equal(back.spread, seq.spread)
    np.testing.assert_array_equal(back.members, seq.members)
    assert back.fps == 25.0 and back.meta == seq.meta and back.num_frames == T
    for k in SIM_STATS:
        np.testing.assert_array_equal(getattr(back, k), stats[k])
    # members=False: the members left unread, every other field as stored
    light = read_sim(tmp_path / "lib-twirl.npz", members=False)
    assert light.members is None
    np.testing.assert_array_equal(light.frames, seq.frames)
    np.testing.assert_array_equal(light.spread, seq.spread)
    assert light.meta == seq.meta
    # only the frames: the other fields read as None
    write_sim(tmp_path / "bare.npz", SimSequence(frames=seq.frames))
    bare = read_sim(tmp_path / "bare.npz")
    assert bare.faces is None and bare.fps is None and bare.spread is None and bare.members is None
    assert all(getattr(bare, k) is None for k in SIM_STATS)


def test_sim_malformed_names_file_and_field(tmp_path):
    p = tmp_path / "bad_sim.npz"
    files.save_npz(p, {"frames": np.zeros((3, 5), np.float32)})
    with pytest.raises(files.ArtifactError, match=r"bad_sim\.npz: frames must be \(T, V, 3\)"):
        read_sim(p)
    files.save_npz(p, {"frames": np.zeros((3, 5, 3), np.float32), "max_stretch": np.ones(2)})
    with pytest.raises(files.ArtifactError, match=r"bad_sim\.npz: max_stretch must be \(3,\)"):
        read_sim(p)
    files.save_npz(p, {"frames": np.zeros((3, 5, 3), np.float32), "spread": np.ones((3, 4))})
    with pytest.raises(files.ArtifactError, match=r"bad_sim\.npz: spread must be \(3, 5\)"):
        read_sim(p)
    files.save_npz(p, {"frames": np.zeros((3, 5, 3), np.float32), "members": np.ones((2, 3, 4, 3))})
    with pytest.raises(files.ArtifactError, match=r"bad_sim\.npz: members must be \(M, 3, 5, 3\)"):
        read_sim(p)
    files.save_npz(p, {"faces": np.zeros((2, 3), np.int64)})
    with pytest.raises(files.ArtifactError, match=r"bad_sim\.npz: missing arrays \['frames'\]"):
        read_sim(p)


# --------------------------------------------------------------------------- field checkpoint
def test_field_checkpoint_round_trip(tmp_path):
    sd = {"canonical.box": torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), "weights.log_prior": torch.randn(2, 3, 4),
          "mlp.0.weight": torch.randn(5, 3)}
    meta = {"format": FIELD_FORMAT, "variant": "full", "field_config": {"grid": {"levels": 2}}, "history": [{"loss": 1}]}
    write_field_checkpoint(tmp_path / "field.pt", FieldCheckpoint(meta=meta, state_dict=sd))
    back = read_field_checkpoint(tmp_path / "field.pt")
    assert back.meta == meta and list(back.state_dict) == list(sd)
    assert all(torch.equal(back.state_dict[k], sd[k]) for k in sd)
    state = {"step": 8, "model": sd, "config_hash": "abc"}
    ck = training_state_path(tmp_path / "field.pt")
    assert ck.name == "field.pt.ckpt"
    write_training_state(ck, state)
    st = read_training_state(ck)
    assert st["step"] == 8 and st["config_hash"] == "abc" and torch.equal(st["model"]["mlp.0.weight"], sd["mlp.0.weight"])


def test_field_checkpoint_malformed_names_file_and_field(tmp_path):
    bad = tmp_path / "bad_field.pt"
    torch.save({"format": "something else"}, bad)
    with pytest.raises(files.ArtifactError, match=r"bad_field\.pt: not an AniDress field"):
        read_field_checkpoint(bad)
    torch.save({"format": FIELD_FORMAT, "field_config": {}}, bad)
    with pytest.raises(files.ArtifactError, match=r"bad_field\.pt: missing entries \['state_dict'\]"):
        read_field_checkpoint(bad)
    torch.save({"format": FIELD_FORMAT, "field_config": {}, "state_dict": {"canonical.box": torch.zeros(2, 3)}}, bad)
    with pytest.raises(files.ArtifactError, match=r"bad_field\.pt: state_dict lacks \['weights.log_prior'\]"):
        read_field_checkpoint(bad)
    bad.write_bytes(b"garbage")
    with pytest.raises(files.ArtifactError, match=r"bad_field\.pt: not a readable torch file"):
        read_field_checkpoint(bad)
    with pytest.raises(files.ArtifactError, match=r"bad_field\.pt: not a readable torch file"):
        read_training_state(bad)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        read_field_checkpoint(tmp_path / "missing.pt")


# --------------------------------------------------------------------------- rig-decompose files (Dem Bones layout)
def test_dembones_files_round_trip(tmp_path):
    seq = DemBonesSequence(rest=RNG.normal(size=(5, 3)), frames=RNG.normal(size=(3, 5, 3)), faces=np.array([[0, 1, 2]]))
    write_dembones_sequence(tmp_path / "seq.npz", seq)
    back = read_dembones_sequence(tmp_path / "seq.npz")
    assert all(np.array_equal(a, b) for a, b in zip(back, seq))
    write_dembones_sequence(tmp_path / "nofaces.npz", seq._replace(faces=None))
    assert read_dembones_sequence(tmp_path / "nofaces.npz").faces is None
    rig = DemBonesRig(weights=RNG.random((2, 5)), transforms=np.tile(np.eye(4), (3, 2, 1, 1)),
                      bone_centres=RNG.normal(size=(2, 3)), rmse=0.5)
    write_dembones_rig(tmp_path / "out.npz", rig)
    got = read_dembones_rig(tmp_path / "out.npz")
    assert got.rmse == 0.5 and all(np.array_equal(a, b) for a, b in zip(got[:3], rig[:3]))


def test_dembones_files_malformed_name_file_and_field(tmp_path):
    np.savez(tmp_path / "bad_seq.npz", rest=np.zeros((5, 3)))
    with pytest.raises(files.ArtifactError, match=r"bad_seq\.npz: missing arrays \['frames'\]"):
        read_dembones_sequence(tmp_path / "bad_seq.npz")
    np.savez(tmp_path / "bad_out.npz", weights=np.zeros((2, 5)), transforms=np.zeros((3, 3, 4, 4)),
             bone_centres=np.zeros((2, 3)), rmse=0.0)
    with pytest.raises(files.ArtifactError, match=r"bad_out\.npz: inconsistent shapes: .*transforms \(3, 3, 4, 4\)"):
        read_dembones_rig(tmp_path / "bad_out.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(files.ArtifactError, match=r"junk\.npz: not a readable npz"):
        read_dembones_sequence(tmp_path / "junk.npz")
