"""Stage undistort end to end (issue 24 item 2): a captured sequence with lens distortion.

A tiny synthetic skirt scene is turned into a distorted capture (images, shipped masks, normal maps and
gt masks warped through OpenCV's lens model, non-zero dist_<cam> in intri.yml without H_/W_). Then:
validate_scene says what will be done; the stages refuse the raw sequence, naming rule undistort;
run_undistort writes the pinhole working sequence, which is the original pinhole data again; cues, fit,
field train / render and evaluate run on it.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from anidress_core.io import easymocap, files
from anidress_core.io.scene import distorted_cameras, scene_cameras, sequence_source

from tests.io.test_scene_cameras import H, W, build_tiny_skirt

torch.set_num_threads(1)

DIST = {"01": [-0.35, 0.1, 4e-4, -3e-4, 0.0],  # barrel
        "02": [0.3, 0.05, 0.0, 5e-4, 0.0]}    # pincushion; 03, 04 stay pinholes
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def _distort_folder(d, K, D, kind):
    """Warp every file of d (a pinhole camera's images / masks / normals) into the distorted camera K, D."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    # the distorted pixel p shows the pinhole pixel q = undistortPoints(p) (same K)
    q = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K, D, None, K, criteria=CRIT).reshape(H, W, 2)
    mx, my = q[..., 0].astype(np.float32), q[..., 1].astype(np.float32)
    for p in sorted(d.iterdir()):
        if kind == "images":
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(p), cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        elif kind == "masks":
            files.write_mask(p, cv2.remap(files.read_mask(p), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE))
        else:
            n = cv2.remap(files.read_exr(p), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            files.write_exr(p, n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6))


def build_distorted_capture(root):
    """(data, results, pinhole copy of walk/) of the distorted capture (shared with tests/test_undistort_workflow.py)."""
    import shutil

    data, res = build_tiny_skirt(root)
    seq = data / "walk"
    shutil.copytree(seq / "gt" / "masks", seq / "masks")  # shipped masks (the pipeline then estimates none)
    pinhole = root / "pinhole"
    shutil.copytree(seq, pinhole)
    raw = easymocap.read_intri(seq / "intri.yml")
    for cam, d in DIST.items():
        K, D = raw[cam]["K"], np.asarray(d)
        for kind, sub in (("images", "images"), ("masks", "masks"), ("masks", "gt/masks"), ("normals", "normals")):
            _distort_folder(seq / sub / cam, K, D, kind)
        raw[cam]["dist"] = D
    easymocap.write_intri(seq / "intri.yml", raw)  # no H_/W_, as EasyMocap writes it
    return data, res, pinhole


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return build_distorted_capture(tmp_path_factory.mktemp("distorted"))


def test_validate_reports_the_undistortion_and_stages_refuse_the_raw_sequence(capture, tmp_path):
    from anidress_core.fit import Views
    from anidress_core.stages.cues import run_masks
    from anidress_core.stages.validate import format_summary, validate_scene

    data, res, _ = capture
    s = validate_scene(data)
    assert s["sequences"]["walk"]["distorted_cameras"] == ["01", "02"]
    assert any("cameras 01, 02 have lens distortion: images, masks and normals will be undistorted to pinhole "
               "working cameras by rule undistort" in n for n in s["notes"])
    assert "note: " in format_summary(s)
    assert distorted_cameras(data, "walk") == ["01", "02"]
    with pytest.raises(ValueError, match=r"intri.yml: cameras 01, 02 have lens distortion: .*rule undistort"
                                         r".*command line: --undistorted DIR"):
        run_masks(data, "walk", tmp_path / "m", {}, res / "template.npz", progress=False)
    with pytest.raises(FileNotFoundError, match="undistort.json: not found"):
        sequence_source(data, "walk", tmp_path / "nothing")
    # the fit's own guard names the distorted cameras only, with their count of non-zero coefficients
    with pytest.raises(ValueError, match=r"cameras 01 \(4 non-zero coefficients\), 02 \(3 non-zero coefficients\) "
                                         r"have lens distortion"):
        Views.from_cameras(scene_cameras(data, "walk", ["01", "02", "03"]))


def test_undistort_stage_restores_the_pinhole_images_of_a_pattern(tmp_path):
    """Exact captures of a pattern fixed to the camera rays: undistorted, they are its pinhole images."""
    from anidress_core.camera import ring_cameras, save_cameras
    from anidress_core.stages.undistort import run_undistort

    h, w = 60, 80
    cams = ring_cameras(2, 3.0, 1.0, (0, 0, 0.9), focal_px=45.0, image_height=h, image_width=w, dtype=torch.float64)
    D = np.array([[-0.3, 0.08, 1e-3, -5e-4, 0.0], [0.25, 0.03, 0.0, 0.0, 0.0]])
    cams.dist = torch.as_tensor(D)
    seq = tmp_path / "s" / "cap"
    save_cameras(cams, seq / "intri.yml", seq / "extri.yml")
    (tmp_path / "s" / "scene.yaml").write_text("fps: 30\nsequences: [{name: cap}]\nbody_model: {type: mannequin, "
                                               "file: none.npz}\ncameras: {train: ['01'], test: ['02']}\n")
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([u, v], -1)

    def pattern(xy):  # (..., 2) normalised ray coordinates -> colour, label
        rgb = 0.5 + 0.45 * np.stack([np.sin(9 * xy[..., 0]), np.cos(7 * xy[..., 1]), np.sin(6 * (xy[..., 0] - xy[..., 1]))], -1)
        return rgb, np.where(np.sin(9 * xy[..., 0]) * np.sin(9 * xy[..., 1]) > 0, 2, 1).astype(np.uint8)

    truth = {}
    for c, cam in enumerate(cams.names):
        K = cams.K[c].numpy()
        ray_of_capture = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, D[c], None, None, criteria=CRIT).reshape(h, w, 2)
        for f in range(2):
            rgb, lab = pattern(ray_of_capture + 0.05 * f)
            files.write_png(seq / "images" / cam / f"{f:06d}.png", rgb)
            files.write_mask(seq / "masks" / cam / f"{f:06d}.png", lab)
        truth[cam] = pattern((pix - K[:2, 2]) / np.diag(K)[:2] + 0.05)  # frame 1 through the pinhole
    rec = run_undistort(tmp_path / "s", "cap", tmp_path / "und", threads=1, progress=False)
    assert rec["distorted"] == ["01", "02"] and rec["undistorted"] == ["images", "masks"] and rec["frames"] == 2
    for cam in cams.names:
        rgb, lab = truth[cam]
        got = files.read_image(tmp_path / "und" / "images" / cam / "000001.png")
        raw = files.read_image(seq / "images" / cam / "000001.png")
        ok = np.abs(got).sum(-1) > 0
        err, before = np.abs(got - rgb)[ok].mean(), np.abs(raw - rgb)[ok].mean()
        assert err < 0.01 and err < 0.1 * before  # bilinear + 8-bit; the capture itself is far off
        m = files.read_mask(tmp_path / "und" / "masks" / cam / "000001.png")
        m_raw = files.read_mask(seq / "masks" / cam / "000001.png")
        inside = m > 0
        wrong, wrong_before = (m[inside] != lab[inside]).mean(), (m_raw[inside] != lab[inside]).mean()
        assert wrong < 0.06 and wrong < 0.25 * wrong_before  # nearest neighbour: along the label edges only


def test_undistort_restores_the_pinhole_sequence_and_the_stages_run_on_it(capture, tmp_path):
    pytest.importorskip("warp")  # the fit's L_collision
    from anidress_core.cli import main
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.stages import cues as sc
    from anidress_core.stages.evaluate import read_metrics_csv, run_evaluate
    from anidress_core.stages.field import run_render, run_train
    from anidress_core.stages.fit import run_fit

    data, res, pinhole = capture
    und = tmp_path / "walk" / "undistorted"
    assert main(["undistort", str(data), "walk", "-o", str(und), "--threads", "1", "--quiet"]) == 0
    rec = files.read_json(und / "undistort.json")
    assert rec["distorted"] == ["01", "02"] and sorted(rec["cameras"]) == ["01", "02", "03", "04"] and rec["frames"] == 3
    assert rec["undistorted"] == ["images", "masks", "normals", "gt/masks", "backgrounds"]
    assert rec["valid_fraction"]["01"] == 1.0 and rec["valid_fraction"]["03"] == 1.0  # barrel, pinhole
    assert 0.5 < rec["valid_fraction"]["02"] < 1.0  # pincushion: the corners are not in the capture
    assert sequence_source(data, "walk", und) == und
    # the working cameras: pinholes with the image size written, the original intrinsics kept
    work = scene_cameras(data, "walk", None, seq_dir=und)
    assert float(work.dist.abs().max()) == 0 and "H_01" in (und / "intri.yml").read_text()
    assert torch.equal(work.K, scene_cameras(data, "walk").K)
    assert easymocap.read_intri(und / "original_intri.yml")["02"]["dist"].tolist() == DIST["02"]
    # the files: the image size, labels kept, unit normals (zero outside the capture)
    for cam in ("01", "02"):
        assert files.read_image(und / "images" / cam / "000001.png").shape == (H, W, 3)
        assert set(np.unique(files.read_mask(und / "masks" / cam / "000001.png"))) <= {0, 1, 2}
        n = files.read_exr(und / "normals" / cam / "000001.exr")
        ln = np.linalg.norm(n, axis=-1)
        assert np.allclose(ln[ln > 0], 1, atol=1e-4)
    # pinhole cameras are copied as they are
    assert (und / "images" / "03" / "000002.png").read_bytes() == (data / "walk" / "images" / "03" / "000002.png").read_bytes()
    # cues on the undistorted sequence: masks (one camera), flows, normals record
    tpl, rig = res / "template.npz", res / "rig.npz"
    ms = sc.run_masks(data, "walk", tmp_path / "masks", {}, tpl, cameras=["01"], threads=1, progress=False,
                      undistorted_dir=und)
    assert ms["cameras"] == 1 and files.read_mask(tmp_path / "masks" / "01" / "000000.png").shape == (H, W)
    sc.run_flows(data, "walk", und / "masks", tmp_path / "flows", {"method": "dis_ultrafast", "margin_px": 4}, tpl,
                 threads=1, progress=False, undistorted_dir=und)
    nrec = sc.run_normals(data, "walk", und / "normals", tmp_path / "normals.json", undistorted_dir=und)
    assert nrec["skipped"] is False and nrec["frames"] == 3
    # fit on the undistorted shipped masks and normals, the estimated flows
    meta = run_fit(data, "walk", rig, tpl, und / "masks", tmp_path / "flows", und / "normals",
                   {"views": 3, "max_iters": 2, "max_iters_first": 2, "prior_reference": "sim"},  # no ensemble here
                   tmp_path / "garment_poses.npz", progress=False, undistorted_dir=und)
    assert sorted(meta["cameras"]) == ["01", "02", "04"]  # the training cameras
    assert np.isfinite(read_garment_poses(tmp_path / "garment_poses.npz", frames=3, bones=4).verts).all()
    # field: train, render the test camera, evaluate against the undistorted ground truth
    params = {"model": {"hash_levels": 2, "hash_log2_size": 10, "hash_max_resolution": 32, "width": 16, "volume_res": 8},
              "priors": {}, "sampler": {"occupancy_res": 16, "step_m": 0.03},
              "train": {"steps": 2, "rays_per_step": 64, "images_per_step": 1, "checkpoint_every": 100},
              "render": {"background": [0.0, 0.0, 0.0]}}
    kw = {"template_npz": tpl, "rig_npz": rig, "garment_poses_npz": tmp_path / "garment_poses.npz"}
    run_train(data, "walk", "full", und / "masks", tmp_path / "field.pt", params, progress=False, undistorted_dir=und,
              **kw)
    rr = run_render(tmp_path / "field.pt", data, tmp_path / "nv", params, seq="walk", cameras=["03"], progress=False,
                    undistorted_dir=und, **kw)
    assert rr["images"] == 3
    run_evaluate(data, [("novel_view", "walk", tmp_path / "nv")], tmp_path / "metrics.csv", tmp_path / "summary.json",
                 {}, progress=False, undistorted={"walk": und})
    rows = read_metrics_csv(tmp_path / "metrics.csv")
    assert len(rows) == 3 and all(np.isfinite(r["psnr_db"]) for r in rows)
