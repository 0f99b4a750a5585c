"""Stage `rig` (anidress_core.stages.rig) and the `anidress rig` / `rig-decompose` commands."""
import numpy as np
import pytest
import torch

from anidress_core import geometry as g
from anidress_core.cli import main
from anidress_core.io import files
from anidress_core.io.rig import read_rig
from anidress_core.stages.rig import run_rig

from .test_rig import known_rig


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _write_template(path, rest, faces):
    V, F = rest.shape[0], faces.shape[0]
    files.save_npz(path, {"verts": rest.numpy().astype(np.float32), "faces": faces.numpy().astype(np.int64),
                          "face_uv": np.zeros((F, 3, 2), np.float32), "band": np.zeros(V, bool),
                          "body_weights": np.full((V, 24), 1 / 24, np.float32), "kind": np.asarray("skirt")})


def _two_sequences(tmp_path):
    rest, faces, W, M, X = known_rig(T=20, B=4, seed=0)
    _, _, _, M2, _ = known_rig(T=7, B=4, seed=1)
    X2 = g.lbs(rest, W, M2)
    tpl = tmp_path / "template.npz"
    _write_template(tpl, rest, faces)
    sims = [tmp_path / "sim" / "lib-walk.npz", tmp_path / "sim" / "seq-dance.npz"]
    for p, x in zip(sims, (X, X2)):
        files.save_npz(p, {"frames": x.numpy().astype(np.float32), "faces": faces.numpy()})
    return tpl, sims, rest, faces, (X, X2)


def test_run_rig_writes_and_reads_back(tmp_path):
    tpl, sims, rest, faces, (X, X2) = _two_sequences(tmp_path)
    out = tmp_path / "rig.npz"
    art = run_rig(tpl, sims, {"bones": 4, "iters": 60, "nnz": 4, "smooth": 0.0}, out, device="cpu")
    again = read_rig(out)
    assert again.model.weights.shape == (rest.shape[0], art.model.num_bones)
    assert again.sequences == {"lib-walk": slice(0, 20), "seq-dance": slice(20, 27)}
    assert again.model.transforms.shape == (27, art.model.num_bones, 4, 4)
    assert torch.allclose(again.model.weights.sum(-1), torch.ones(rest.shape[0]), atol=1e-5)
    # the rig reproduces each simulated sequence from its own transforms (float32 data)
    for name, x in (("lib-walk", X), ("seq-dance", X2)):
        rec = g.lbs(again.model.rest, again.model.weights, again.transforms_of(name))
        err = float(((rec - x.float()) ** 2).sum(-1).mean().sqrt())
        assert err == pytest.approx(again.rmse_per_sequence[name], rel=1e-3, abs=1e-6)
        assert err < 1e-3  # 1.5 m tube, exact rig: converged to well under a millimetre
    assert again.meta["params"]["bones"] == 4
    with pytest.raises(KeyError, match="no simulated sequence"):
        again.transforms_of("lib-run")


def test_run_rig_names_the_bad_file(tmp_path):
    tpl, sims, rest, faces, _ = _two_sequences(tmp_path)
    bad = tmp_path / "sim" / "lib-bad.npz"
    files.save_npz(bad, {"frames": np.zeros((3, rest.shape[0] + 1, 3), np.float32)})
    with pytest.raises(files.ArtifactError, match="lib-bad.npz"):
        run_rig(tpl, [sims[0], bad], {"bones": 2, "iters": 1, "nnz": 2}, tmp_path / "rig.npz")
    nan = tmp_path / "sim" / "lib-nan.npz"
    x = np.zeros((3, rest.shape[0], 3), np.float32)
    x[1, 2, 0] = np.nan
    files.save_npz(nan, {"frames": x})
    with pytest.raises(files.ArtifactError, match="lib-nan.npz.*NaN"):
        run_rig(tpl, [nan], {"bones": 2, "iters": 1, "nnz": 2}, tmp_path / "rig.npz")
    assert not (tmp_path / "rig.npz").exists()


def test_rig_decompose_command_uses_dem_bones_layout(tmp_path, capsys):
    rest, faces, W, M, X = known_rig(T=10, B=3)
    seq = tmp_path / "seq.npz"
    np.savez(seq, rest=rest.numpy(), faces=faces.numpy(), frames=X.numpy())
    out = tmp_path / "out.npz"
    assert main(["rig-decompose", str(seq), "--bones", "3", "--iters", "40", "--nnz", "3", "-o", str(out)]) == 0
    z = np.load(out)
    Wb, Mt = z["weights"], z["transforms"]
    B = Wb.shape[0]
    assert Wb.shape == (B, rest.shape[0]) and Mt.shape == (10, B, 4, 4)
    # x[t,i] = sum_b W[b,i] (M[t,b,:3,:3] rest[i] + M[t,b,:3,3])
    rec = np.einsum("bi,tbjk,ik->tij", Wb, Mt[:, :, :3, :], np.c_[rest.numpy(), np.ones(rest.shape[0])])
    assert np.sqrt(((rec - X.numpy()) ** 2).sum(-1).mean()) == pytest.approx(float(z["rmse"]), rel=1e-6, abs=1e-12)
    assert float(z["rmse"]) < 1e-3
    np.savez(tmp_path / "bad.npz", rest=rest.numpy())
    assert main(["rig-decompose", str(tmp_path / "bad.npz"), "-o", str(tmp_path / "x.npz")]) == 2
    assert "frames" in capsys.readouterr().err
