"""anidress export-capture (issue 24 item 4): a synthetic scene written as a user's capture would be.

On the tiny skirt scene of tests/io/test_scene_cameras.py (4 cameras, 3 frames, 40 x 48 images): the
exported scene validates and reads back through the scene readers; it holds no gt/, no texture and
no background plates; intri.yml has no H_/W_ and non-zero dist; a world point projected through the
exported camera with cv2.projectPoints lands where the warped image shows it; the body noise has the
requested magnitude; the output is a function of the seed; malformed inputs are named.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from anidress_core.body.model import mannequin_model
from anidress_core.body.motions import make_motion
from anidress_core.camera import project, ring_cameras
from anidress_core.cli import main
from anidress_core.io import easymocap, files
from anidress_core.io.motion import read_easymocap_smpl_dir
from anidress_core.io.scene import load_body, load_sequence_motion, scene_cameras
from anidress_core.stages.export_capture import (camera_distortions, default_image_size, exported_cameras,
                                                 fold_root_pose, noisy_body, parse_image_size, parser_labels,
                                                 pose_errors, run_export_capture, warp_image, warp_maps)
from anidress_core.stages.undistort import run_undistort
from anidress_core.stages.validate import validate_scene

from tests.io.test_scene_cameras import H, W, build_tiny_skirt

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    data, _ = build_tiny_skirt(root)
    out = root / "cap" / "s"
    rec = run_export_capture(data, out, masks="parser", seed=3, threads=1)
    return data, out, rec


def _all_files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_exported_scene_validates_without_crutches(tiny):
    data, out, rec = tiny
    s = validate_scene(out)
    assert s["sequences"]["walk"]["frames"] == 3 and s["sequences"]["walk"]["masks"]
    info = yaml.safe_load((out / "scene.yaml").read_text())
    H2, W2 = info["image_size"]
    assert info["synthetic"] is False and (H2, W2) == (H, 64) and H2 != W2  # width padded to 4:3
    assert "ground_truth" not in info and all("motion" not in q for q in info["sequences"])
    names = {p.name for p in out.rglob("*")}
    assert not {"gt", "backgrounds", "texture.png", "body_texture.png", "meshes.npz"} & names
    assert not any("truth" in p.name for p in out.rglob("*"))
    # the truth, beside the scene
    truth = Path(rec["truth_dir"])
    assert truth == out.parent / "s.truth"
    assert (truth / "walk" / "gt" / "meshes.npz").is_file() and (truth / "export.json").is_file()
    assert files.read_mask(truth / "walk" / "gt" / "masks" / "03" / "000001.png").shape == (H2, W2)
    # calibration as EasyMocap's write_intri writes it: no H_/W_, distortion in every camera
    text = (out / "walk" / "intri.yml").read_text()
    assert "H_" not in text and "W_" not in text
    intri = easymocap.read_intri(out / "walk" / "intri.yml")
    assert list(intri) == easymocap.read_names(data / "walk" / "intri.yml")
    assert all(abs(v["dist"][0]) > 0.1 and np.all(v["dist"][:4] != 0) for v in intri.values())
    # EasyMocap >= 0.2 body files: poses of 69 numbers, root in Rh
    person = json.loads((out / "walk" / "smpl" / "000000.json").read_text())[0]
    assert len(person["poses"][0]) == 69 and len(person["Rh"][0]) == 3
    # the readers
    cams = scene_cameras(out, "walk")
    assert (cams.height, cams.width) == (H2, W2) and (cams.dist.abs() > 0).any()
    assert load_sequence_motion(out, "walk", 30.0).poses.shape == (3, 72)
    assert rec["config_entry"]["synthetic"] is False and rec["config_entry"]["image_size"] == [H2, W2]


def _blob(shape, centre, sigma=1.0):
    v, u = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    return np.exp(-0.5 * ((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / sigma ** 2)


def _projection_check(src, dst, pts: np.ndarray) -> tuple[int, float, float]:
    """(points checked, largest lens displacement, largest error) of blobs drawn at the source pinhole
    projections, warped, against cv2.projectPoints with the exported K and dist."""
    maps = warp_maps(src, dst)
    uv_o = project(torch.as_tensor(pts), src).uv.numpy()  # (C, N, 2) pinhole pixels in the source images
    uv_p = project(torch.as_tensor(pts), dst, distort=False).uv.numpy()  # the same without the lens
    worst, checked, moved = 0.0, 0, 0.0
    for c in range(len(dst)):
        rvec = cv2.Rodrigues(dst.R[c].numpy())[0]
        uv_d = cv2.projectPoints(pts, rvec, dst.T[c].numpy(), dst.K[c].numpy(), dst.dist[c].numpy())[0][:, 0]
        for n in range(len(pts)):
            u, v = uv_d[n]
            if not (4 <= u <= dst.width - 5 and 4 <= v <= dst.height - 5):
                continue
            if not (4 <= uv_o[c, n, 0] <= src.width - 5 and 4 <= uv_o[c, n, 1] <= src.height - 5):
                continue  # in the padding: the source image does not show it
            img = warp_image(_blob((src.height, src.width), uv_o[c, n]).astype(np.float32), maps, c)
            r = 3
            iu, iv = int(round(u)), int(round(v))
            win = img[iv - r: iv + r + 1, iu - r: iu + r + 1].astype(np.float64)
            gv, gu = np.mgrid[iv - r: iv + r + 1, iu - r: iu + r + 1]
            cu, cv_ = (win * gu).sum() / win.sum(), (win * gv).sum() / win.sum()
            worst = max(worst, float(np.hypot(cu - u, cv_ - v)))
            moved = max(moved, float(np.hypot(*(uv_d[n] - uv_p[c, n]))))
            checked += 1
    return checked, moved, worst


def test_projection_through_exported_camera_matches_the_warped_image(tiny):
    """A world point: its pinhole projection in the source image, carried by the image warp, lands where
    cv2.projectPoints puts it with the exported K and dist (< 0.5 px); on the tiny scene's cameras as
    written to intri.yml and on the demo's camera (256 x 256 -> 342 x 256, 38 degree field of view)."""
    data, out, _ = tiny
    src = scene_cameras(data, "walk")
    dst = scene_cameras(out, "walk")
    pts = np.random.default_rng(0).uniform([-1.2, -1.2, -0.2], [1.2, 1.2, 2.2], (300, 3))  # filling the views
    checked, moved, worst = _projection_check(src, dst, pts)
    assert checked > 100 and moved > 0.5 and worst < 0.1, (checked, moved, worst)
    f = 128 / np.tan(np.deg2rad(19.0))
    demo = ring_cameras(n=3, radius=3.5, height=1.2, target=(0.0, 0.0, 0.9), focal_px=f, image_height=256,
                        image_width=256)
    demo = demo.to(dtype=torch.float64)
    demo2, _ = exported_cameras(demo, default_image_size(256, 256), camera_distortions(3, seed=0))
    pts = np.random.default_rng(1).uniform([-1.5, -1.5, -0.3], [1.5, 1.5, 2.3], (120, 3))
    checked, moved, worst = _projection_check(demo, demo2, pts)
    # the lens moves some points by more than 5 px: a warp without it would be far off
    assert checked > 60 and moved > 5 and worst < 0.5, (checked, moved, worst)
    maps = warp_maps(src, dst)
    # the written images are that warp of the source images
    im = files.read_image(out / "walk" / "images" / "02" / "000001.png")
    ref = warp_image(files.read_image(data / "walk" / "images" / "02" / "000001.png"), maps, dst.names.index("02"))
    assert np.abs(im - ref).max() <= 1 / 255 + 1e-6


def test_undistort_stage_recovers_the_padded_source(tiny, tmp_path):
    """The pipeline's rule undistort on the exported scene gives back the source image, padded (the camera
    models of exporter and pipeline agree)."""
    data, out, rec = tiny
    run_undistort(out, "walk", tmp_path / "u", threads=1, progress=False)
    ox, oy = rec["sequences"]["walk"]["offset_px"]
    for cam in ("01", "03"):
        und = files.read_image(tmp_path / "u" / "images" / cam / "000002.png")[oy: oy + H, ox: ox + W]
        orig = files.read_image(data / "walk" / "images" / cam / "000002.png")
        inner = (slice(3, -3), slice(3, -3))  # away from the border the distortion pulls in
        assert np.abs(und[inner] - orig[inner]).mean() < 0.02


def test_body_noise_has_the_requested_magnitude(tiny):
    data, out, rec = tiny
    body = load_body(data)
    true = read_easymocap_smpl_dir(data / "walk" / "smpl")
    noisy = read_easymocap_smpl_dir(out / "walk" / "smpl")
    e = pose_errors(body, {k: true[k] for k in ("poses", "Rh", "Th")}, {k: noisy[k] for k in ("poses", "Rh", "Th")})
    assert abs(e["joint_error_cm"] - 2.0) < 0.05 and e["jitter_cm"] > 0.2 and 0.3 < e["joint_angle_deg"] < 6
    assert e == pytest.approx({k: v for k, v in rec["sequences"]["walk"]["body_noise"].items() if k != "scale"},
                              rel=1e-6)
    # a longer motion: each target reached within 2 %, the angles a few degrees, drift and jitter both present
    b = mannequin_model(1.7, 1500)
    m = make_motion("walk", num_frames=60, fps=30.0, seed=5, body=b)
    P, R, T = m.poses.double().numpy(), m.Rh.double().numpy(), m.Th.double().numpy()
    for target in (1.0, 2.0, 4.0):
        nz = noisy_body(b, P, R, T, None, target, 30.0, seed=1)
        assert abs(nz.errors["joint_error_cm"] - target) <= 0.02 * target
        assert 0.2 * target < nz.errors["joint_angle_deg"] < 3 * target
        assert 0.1 * target < nz.errors["jitter_cm"] < target
    zero = noisy_body(b, P, R, T, None, 0.0, 30.0, seed=1)
    assert zero.errors["joint_error_cm"] == 0.0 and np.array_equal(zero.poses, P)


def test_fold_root_pose_keeps_the_body(tmp_path):
    import dataclasses

    b = mannequin_model(1.7, 1500)
    shift = torch.tensor([0.02, -0.3, 0.05])
    b = dataclasses.replace(b, v_template=b.v_template + shift, joints_rest=b.joints_rest + shift)  # J0 != 0
    rng = np.random.default_rng(0)
    P, R, T = rng.normal(0, 0.3, (4, 72)), rng.normal(0, 0.8, (4, 3)), rng.normal(0, 1, (4, 3))
    P2, R2, T2 = fold_root_pose(P, R, T, b.joints_rest[0].double().numpy())
    assert np.all(P2[:, :3] == 0) and np.array_equal(P2[:, 3:], P[:, 3:])
    f = lambda *a: b.pose(*(torch.as_tensor(x, dtype=torch.float32) for x in a)).vertices  # noqa: E731
    assert (f(P, R, T) - f(P2, R2, T2)).abs().max() < 1e-5


def test_same_seed_same_output(tiny, tmp_path):
    data, out, _ = tiny
    a, b, c = tmp_path / "a" / "s", tmp_path / "b" / "s", tmp_path / "c" / "s"
    for d, seed in ((a, 3), (b, 3), (c, 4)):
        run_export_capture(data, d, masks="parser", seed=seed, threads=2)
    fa, fb, fc = _all_files(a), _all_files(b), _all_files(c)
    assert fa == fb and fa == _all_files(out)
    assert fa.keys() == fc.keys()
    assert fa["walk/smpl/000000.json"] != fc["walk/smpl/000000.json"]
    assert fa["walk/intri.yml"] != fc["walk/intri.yml"]
    assert fa["walk/masks/01/000000.png"] != fc["walk/masks/01/000000.png"]
    ea, eb = (json.loads((d.parent / "s.truth" / "export.json").read_text()) for d in (a, b))
    for e in (ea, eb):
        for k in ("wall_s", "scene_dir", "truth_dir"):
            e.pop(k)
    assert ea == eb


def test_each_degradation_alone(tiny, tmp_path):
    """--no-distort, --pose-noise-cm 0, --masks none, --image-size: each cause can be switched off alone."""
    data, _, _ = tiny
    out = tmp_path / "p"
    rec = run_export_capture(data, out, distort=False, pose_noise_cm=0.0, masks="none", image_size="50x44",
                             normals=False, threads=1)
    validate_scene(out)
    assert not (out / "walk" / "masks").exists() and not (out / "walk" / "normals").exists()
    assert (out.parent / "p.truth" / "walk" / "gt" / "masks" / "01" / "000000.png").is_file()
    assert "predicted_normals" not in yaml.safe_load((out / "scene.yaml").read_text())
    cams = scene_cameras(out, "walk")
    assert (cams.height, cams.width) == (44, 50) and float(cams.dist.abs().max()) == 0.0
    # crop / pad only: the source image at the integer offset (rows cropped by 2, columns padded by 5)
    ox, oy = rec["sequences"]["walk"]["offset_px"]
    assert (ox, oy) == (5, -2)
    im = files.read_image(out / "walk" / "images" / "04" / "000002.png")
    orig = files.read_image(data / "walk" / "images" / "04" / "000002.png")
    np.testing.assert_array_equal(im[:, ox: ox + W], orig[-oy: -oy + 44])
    a, b = read_easymocap_smpl_dir(out / "walk" / "smpl"), read_easymocap_smpl_dir(data / "walk" / "smpl")
    for k in ("poses", "Rh", "Th", "shapes"):
        np.testing.assert_allclose(a[k], b[k], atol=1e-12)


def test_parser_labels_have_typical_errors():
    lab = np.zeros((256, 200), np.uint8)
    cv2.ellipse(lab, (100, 128), (40, 100), 0, 0, 360, 1, -1)
    lab[120:200][lab[120:200] == 1] = 2  # a skirt on the lower half
    out = parser_labels(lab, np.random.default_rng(0))
    again = parser_labels(lab, np.random.default_rng(0))
    assert np.array_equal(out, again) and set(np.unique(out)) <= {0, 1, 2}
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert 0.85 < iou(out > 0, lab > 0) < 0.995 and 0.75 < iou(out == 2, lab == 2) < 0.995
    assert not parser_labels(np.zeros((8, 8), np.uint8), np.random.default_rng(0)).any()
    with pytest.raises(ValueError, match="labels are"):
        parser_labels(lab.astype(np.float32), np.random.default_rng(0))


def _copy(data: Path, tmp: Path) -> Path:
    d = tmp / "src"
    shutil.copytree(data, d)
    return d


def test_malformed_inputs_name_file_and_field(tiny, tmp_path):
    data, out, _ = tiny
    with pytest.raises(FileNotFoundError, match=r"nowhere/scene.yaml: scene description not found"):
        run_export_capture(tmp_path / "nowhere", tmp_path / "o1")
    with pytest.raises(ValueError, match=r"scene.yaml: 'synthetic' is False"):
        run_export_capture(out, tmp_path / "o2")  # a capture has no truth to hold back
    with pytest.raises(ValueError, match=r"--image-size '64by48': expected WxH"):
        parse_image_size("64by48")
    with pytest.raises(ValueError, match=r"masks must be one of"):
        run_export_capture(data, tmp_path / "o3", masks="cihp")
    with pytest.raises(ValueError, match=r"o4: exists and is not empty"):
        (tmp_path / "o4").mkdir()
        (tmp_path / "o4" / "x").write_text("")
        run_export_capture(data, tmp_path / "o4")
    src = _copy(data, tmp_path)
    (src / "walk" / "gt" / "meshes.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"src/walk/gt/meshes.npz: not found \(sequence 'walk'"):
        run_export_capture(src, tmp_path / "o5")
    shutil.rmtree(src)
    src = _copy(data, tmp_path)
    p = src / "walk" / "smpl" / "000001.json"
    person = json.loads(p.read_text())
    person[0]["poses"] = [[0.0] * 50]
    p.write_text(json.dumps(person))
    with pytest.raises(ValueError, match=r"smpl/000001.json: 'poses' holds 50 numbers"):
        run_export_capture(src, tmp_path / "o6")
    shutil.rmtree(src)
    src = _copy(data, tmp_path)
    cv2.imwrite(str(src / "walk" / "images" / "03" / "000002.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match=r"images/03/000002.png: image is \(10, 10\)"):
        run_export_capture(src, tmp_path / "o7")
    assert not (tmp_path / "o5").exists() and not (tmp_path / "o7").exists() and not (tmp_path / "o7.truth").exists()


def test_cli_export_capture(tiny, tmp_path, capsys):
    data, _, _ = tiny
    out = tmp_path / "cli"
    assert main(["export-capture", str(data), str(out), "--no-distort", "--pose-noise-cm", "1.5", "--image-size",
                 "60x48", "--seed", "2", "--threads", "1"]) == 0
    text = capsys.readouterr().out
    assert "body joint error 1.5" in text and "distortion off" in text and f"{out}: OK" in text
    assert "scenes:" in text and "anchor_reference" not in text  # the default fit needs no texture
    assert main(["export-capture", str(data), str(out)]) == 2  # exists: refused, named


def test_exported_flow_undistorts_back_to_the_source_flow():
    """warp_flow (source pinhole -> exported distorted camera) then rule undistort's undistort_flow (back to a
    pinhole working camera with the source's K): the source flow again, away from the border."""
    from anidress_core.camera import Cameras
    from anidress_core.stages.export_capture import warp_flow
    from anidress_core.undistort import undistort_flow, undistort_maps

    H2, W2 = 48, 64
    K = torch.tensor([[[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]], dtype=torch.float64)
    src = Cameras(["01"], K, torch.zeros(1, 5, dtype=torch.float64), torch.eye(3, dtype=torch.float64)[None],
                  torch.zeros(1, 3, dtype=torch.float64), H2, W2)
    dist = torch.tensor([[-0.25, 0.08, 0.0005, -0.001, 0.0]], dtype=torch.float64)
    dst = Cameras(["01"], K.clone(), dist, src.R.clone(), src.T.clone(), H2, W2)
    v, u = np.mgrid[0:H2, 0:W2].astype(np.float32)
    flow = np.stack([0.8 + 0.02 * (u - 32), -0.5 + 0.03 * (v - 24)], -1).astype(np.float32)
    exp, ok = warp_flow(flow, np.ones((H2, W2), bool), warp_maps(src, dst), 0, src, dst)
    assert ok.mean() > 0.8 and np.abs(exp - flow)[ok].max() > 0.05  # the lens bends the vectors
    back, ok2 = undistort_flow(exp, ok, undistort_maps(dst.K, dst.dist, H2, W2), 0, dst.K[0], dst.dist[0])
    inner = ok2.copy()
    inner[:6], inner[-6:], inner[:, :6], inner[:, -6:] = False, False, False, False
    assert inner.mean() > 0.5 and np.abs(back - flow)[inner].max() < 0.02
