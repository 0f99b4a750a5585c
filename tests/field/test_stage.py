"""Stages train / render / evaluate on a tiny scene folder (EasyMocap layout written here)."""
import json

import numpy as np
import pytest
import torch
import yaml

from anidress_core.camera import ring_cameras, save_cameras
from anidress_core.io import files
from anidress_core.io.motion import write_easymocap_smpl_dir
from anidress_core.metrics.image import Unavailable
from anidress_core.raster import render_mesh
from anidress_core.stages.evaluate import COLUMNS, read_metrics_csv, run_evaluate
from anidress_core.stages.field import load_field, run_render, run_train

from .conftest import bent_pose

PARAMS = {"model": {"hash_levels": 4, "hash_log2_size": 12, "hash_max_resolution": 64, "width": 32, "volume_res": 16},
          "priors": {}, "sampler": {"occupancy_res": 32, "step_m": 0.015},
          "train": {"steps": 12, "rays_per_step": 128, "images_per_step": 2, "checkpoint_every": 4},
          "render": {"background": [0.0, 0.0, 0.0]}}


@pytest.fixture(scope="module")
def scene_dir(small_body, tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("tinyfield")
    body = small_body
    files.save_npz(root / "body_model.npz", {"v_template": body.v_template.numpy(), "faces": body.faces.numpy(),
                                              "weights": body.weights.numpy(), "joints_rest": body.joints_rest.numpy(),
                                              "parents": body.parents.numpy()})
    cams = ring_cameras(4, 3.0, 1.0, (0.0, 0.0, 0.9), focal_px=40, image_height=32, image_width=32)
    col = 0.5 + 0.4 * torch.sin(8 * body.v_template)
    poses = {"walk": torch.cat([torch.zeros(1, 72), bent_pose()]), "dance": bent_pose() * 0.5}
    for seq, P in poses.items():
        T = P.shape[0]
        Rh = torch.tensor([[1.5708, 0.0, 0.0]]).expand(T, 3)
        Th = torch.tensor([[0.0, 0.0, 0.95]]).expand(T, 3)
        save_cameras(cams, root / seq / "intri.yml", root / seq / "extri.yml")
        write_easymocap_smpl_dir(root / seq / "smpl", P, Rh, Th, torch.zeros(10))
        posed = body.pose(P, Rh, Th)
        for t in range(T):
            r = render_mesh(posed.vertices[t], body.faces, cams.K, cams.world_to_cam, 32, 32, vertex_colors=col)
            for c, name in enumerate(cams.names):
                files.write_png(root / seq / "images" / name / f"{t:06d}.png", r.rgb[c].clamp(0, 1).numpy())
                files.write_mask(root / seq / "gt" / "masks" / name / f"{t:06d}.png", r.mask[c].numpy().astype(np.uint8))
    info = {"name": "tiny", "fps": 30, "kind": "tight", "image_size": [32, 32],
            "cameras": {"train": ["01", "03"], "test": ["02", "04"]},
            "sequences": [{"name": "walk", "role": "train", "frames": 2}, {"name": "dance", "role": "novel_pose", "frames": 1}],
            "body_model": {"type": "mannequin", "file": "body_model.npz"}}
    (root / "scene.yaml").write_text(yaml.safe_dump(info))
    return root


def test_train_resume_render_evaluate(scene_dir, tmp_path):
    out = tmp_path / "walk" / "full" / "field.pt"
    masks = scene_dir / "walk" / "gt" / "masks"
    # 1. interrupted after step 8: the checkpoint stays, no field.pt
    r = run_train(scene_dir, "walk", "full", masks, out, PARAMS, progress=False, max_steps=8)
    assert r == {"stopped_at": 8} and not out.exists() and (tmp_path / "walk" / "full" / "field.pt.ckpt").is_file()
    # 2. rerun: resumes from step 8, finishes, removes the checkpoint
    meta = run_train(scene_dir, "walk", "full", masks, out, PARAMS, progress=False,
                     lpips=Unavailable("lpips", "no weights in this test"))
    assert out.is_file() and not (tmp_path / "walk" / "full" / "field.pt.ckpt").exists()
    assert meta["steps"] == 12 and meta["num_bones"] == 0 and meta["lpips"] == "no weights in this test"
    # 3. the same as an uninterrupted run
    other = tmp_path / "again" / "field.pt"
    run_train(scene_dir, "walk", "full", masks, other, PARAMS, progress=False)
    a, b = load_field(out).model.state_dict(), load_field(other).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # 4. render the novel view and the novel pose, evaluate
    nv = run_render(out, scene_dir, tmp_path / "nv", PARAMS, seq="walk", cameras=["02", "04"], progress=False)
    npz = run_render(out, scene_dir, tmp_path / "np", PARAMS, seq="dance", cameras=["01", "02", "03", "04"],
                     progress=False)
    assert nv["images"] == 4 and npz["images"] == 4
    assert (tmp_path / "nv" / "rgb" / "02" / "000001.png").is_file()
    assert files.read_exr(tmp_path / "nv" / "depth" / "04" / "000000.exr").shape == (32, 32, 1)
    rj = json.loads((tmp_path / "np" / "render.json").read_text())
    assert rj["frames"] == [0] and rj["samples_per_ray"] < rj["considered_per_ray"]
    summ = run_evaluate(scene_dir, [("novel_view", "walk", tmp_path / "nv"), ("novel_pose", "dance", tmp_path / "np")],
                        tmp_path / "metrics.csv", tmp_path / "summary.json", {}, progress=False)
    rows = read_metrics_csv(tmp_path / "metrics.csv")
    assert len(rows) == 8 and list(rows[0].keys()) == COLUMNS
    assert all(np.isfinite(r["psnr_db"]) and 0 <= r["iou"] <= 1 and np.isnan(r["lpips"]) and r["lpips_available"] == 0
               for r in rows)
    assert {(m["kind"], m["sequence"]) for m in summ["metrics"]} == {("novel_view", "walk"), ("novel_pose", "dance")}
    assert summ["lpips"] == "not requested"


def test_a_jpeg_capture_trains_renders_and_is_scored(scene_dir, tmp_path):
    """Images as JPEG under names validate_scene accepts (any padding, extension in any case) are read by the
    field's training and by evaluate, which scores the renders against them."""
    import shutil

    import cv2

    jpg = tmp_path / "jpg"
    shutil.copytree(scene_dir, jpg)
    for k, p in enumerate(sorted((jpg / "walk" / "images").glob("*/*.png"))):
        name = f"{int(p.stem)}.JPG" if k % 2 else f"{p.stem}.jpeg"
        cv2.imwrite(str(p.with_name(name)), cv2.imread(str(p)), [cv2.IMWRITE_JPEG_QUALITY, 95])
        p.unlink()
    assert not list((jpg / "walk" / "images").glob("*/*.png"))
    out = tmp_path / "field.pt"
    run_train(jpg, "walk", "full", jpg / "walk" / "gt" / "masks", out, PARAMS, progress=False)
    run_render(out, jpg, tmp_path / "nv", PARAMS, seq="walk", cameras=["02", "04"], progress=False)
    summ = run_evaluate(jpg, [("novel_view", "walk", tmp_path / "nv")], tmp_path / "m.csv", tmp_path / "s.json", {},
                        progress=False)
    rows = read_metrics_csv(tmp_path / "m.csv")
    assert len(rows) == 4 and all(np.isfinite(r["psnr_db"]) for r in rows)
    assert summ["metrics"][0]["scored"] == 4


def test_errors_name_the_problem(scene_dir, tmp_path):
    with pytest.raises(ValueError, match="variant"):
        run_train(scene_dir, "walk", "w/o G", scene_dir / "walk" / "gt" / "masks", tmp_path / "f.pt", PARAMS,
                  progress=False)
    with pytest.raises(FileNotFoundError, match="000000.png"):
        run_train(scene_dir, "walk", "full", tmp_path / "no_masks", tmp_path / "f.pt", PARAMS, progress=False)
    bad = tmp_path / "bad.pt"
    torch.save({"format": "something else"}, bad)
    with pytest.raises(files.ArtifactError, match="bad.pt"):
        load_field(bad)


def test_a_checkpoint_resumes_only_the_same_training(scene_dir, tmp_path, caplog):
    """checkpoint_every does not count (the field is the same), other data does (a rerun after an upstream
    change must not continue the stale training)."""
    import shutil

    masks = scene_dir / "walk" / "gt" / "masks"
    out, ckpt = tmp_path / "a" / "field.pt", tmp_path / "a" / "field.pt.ckpt"
    run_train(scene_dir, "walk", "full", masks, out, PARAMS, progress=False, max_steps=8)
    other_every = dict(PARAMS, train=dict(PARAMS["train"], checkpoint_every=5))
    with caplog.at_level("INFO", logger="anidress.field"):
        run_train(scene_dir, "walk", "full", masks, out, other_every, progress=False)
    assert "at step 8" in caplog.text and not ckpt.exists()
    ref = tmp_path / "ref" / "field.pt"
    run_train(scene_dir, "walk", "full", masks, ref, PARAMS, progress=False)
    a, b = load_field(out).model.state_dict(), load_field(ref).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # other masks (one emptied): the checkpoint is ignored, the field is that of the new data
    out.unlink()
    run_train(scene_dir, "walk", "full", masks, out, PARAMS, progress=False, max_steps=8)
    masks2 = tmp_path / "masks2"
    shutil.copytree(masks, masks2)
    first = sorted(masks2.rglob("*.png"))[0]
    files.write_mask(first, np.zeros_like(files.read_mask(first)))
    caplog.clear()
    with caplog.at_level("INFO", logger="anidress.field"):
        run_train(scene_dir, "walk", "full", masks2, out, PARAMS, progress=False)
    assert "ignoring" in caplog.text and "resuming" not in caplog.text
    fresh = tmp_path / "fresh" / "field.pt"
    run_train(scene_dir, "walk", "full", masks2, fresh, PARAMS, progress=False)
    a, b = load_field(out).model.state_dict(), load_field(fresh).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def _write_render(folder, frames, cams, pred_of):
    """A render folder as run_render writes it: render.json, rgb/<cam>/<f>.png (uint8 ``pred_of(cam, f)``),
    alpha/<cam>/<f>.png (16-bit, opaque)."""
    files.write_json(folder / "render.json", {"frames": frames, "cameras": cams, "background": [0.0, 0.0, 0.0]})
    for f in frames:
        for cam in cams:
            rgb = pred_of(cam, f)
            files.write_png(folder / "rgb" / cam / f"{f:06d}.png", rgb)
            files.write_png(folder / "alpha" / cam / f"{f:06d}.png", np.full(rgb.shape[:2], 65535, np.uint16))


def test_evaluate_region_metrics(scene_dir, tmp_path):
    """Subject / garment / body PSNR and SSIM: per image, and pooled per (kind, sequence) over the pixels.

    walk (cameras 02, 04, frames 0, 1): garment = the subject's pixels in rows >= 16 (none for 04 frame 1); the
    render is the composited image with an error of 51/255 = 0.2 on frame 0's garment pixels and 0.4 on frame 1's,
    exact elsewhere. dance: one mask saved 0 / 255 (no labels: "subject only"), the others 0 / 1."""
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    info = yaml.safe_load((root / "scene.yaml").read_text())
    (root / "scene.yaml").write_text(yaml.safe_dump(dict(info, garment_template="garment/template.obj")))
    walk_cams, counts = ["02", "04"], {}

    def composited(seq, cam, f):  # the image on the black background, uint8 (as the PNG holds it)
        img = np.round(files.read_image(root / seq / "images" / cam / f"{f:06d}.png") * 255).astype(np.int32)
        return np.where((files.read_mask(root / seq / "gt" / "masks" / cam / f"{f:06d}.png") > 0)[..., None], img, 0)

    for f in (0, 1):
        for cam in walk_cams:
            mp = root / "walk" / "gt" / "masks" / cam / f"{f:06d}.png"
            lab = files.read_mask(mp).copy()
            if not (cam == "04" and f == 1):
                lab[16:][lab[16:] > 0] = 2
            files.write_mask(mp, lab)
            counts[cam, f] = (int((lab > 0).sum()), int((lab == 2).sum()))
    assert all(n_g > 0 for (cam, f), (_, n_g) in counts.items() if (cam, f) != ("04", 1))

    def walk_pred(cam, f):
        gt = composited("walk", cam, f)
        lab = files.read_mask(root / "walk" / "gt" / "masks" / cam / f"{f:06d}.png")
        e = 51 * (f + 1)  # 0.2, 0.4
        wrong = np.where(gt >= e, gt - e, gt + e)
        return np.where((lab == 2)[..., None], wrong, gt).astype(np.uint8)

    dm = root / "dance" / "gt" / "masks" / "01" / "000000.png"
    files.write_mask(dm, (files.read_mask(dm) > 0).astype(np.uint8) * 255)
    _write_render(tmp_path / "nv", [0, 1], walk_cams, walk_pred)
    _write_render(tmp_path / "np", [0], ["01", "02", "03", "04"],
                  lambda cam, f: composited("dance", cam, f).astype(np.uint8))
    renders = [("novel_view", "walk", tmp_path / "nv"), ("novel_pose", "dance", tmp_path / "np")]
    summ = run_evaluate(root, renders, tmp_path / "metrics.csv", tmp_path / "summary.json", {}, progress=False)
    rows = read_metrics_csv(tmp_path / "metrics.csv")
    assert list(rows[0].keys()) == COLUMNS
    walk = {(r["camera"], r["frame"]): r for r in rows if r["kind"] == "novel_view"}
    # 1. per image: garment PSNR of its error, body identical (+inf), subject from the pixel counts
    for (cam, f), r in walk.items():
        n_s, n_g = counts[cam, f]
        assert r["region_masks"] == "gt/masks" and r["psnr_body_db"] == np.inf
        if n_g == 0:  # the garment is hidden: empty region
            assert np.isnan(r["psnr_garment_db"]) and np.isnan(r["ssim_garment"]) and r["psnr_subject_db"] == np.inf
            continue
        mse = (0.2 * (f + 1)) ** 2
        assert r["psnr_garment_db"] == pytest.approx(-10 * np.log10(mse), abs=1e-4)
        assert r["psnr_subject_db"] == pytest.approx(-10 * np.log10(mse * n_g / n_s), abs=1e-4)
        assert -1 <= r["ssim_garment"] < r["ssim_body"] < 1 and r["ssim_garment"] < r["ssim_subject"]
    # 2. pooled over the pixels of the images, not the mean of their PSNRs
    nv = next(m for m in summ["metrics"] if m["kind"] == "novel_view")
    g0 = sum(n_g for (cam, f), (_, n_g) in counts.items() if f == 0)
    g1 = sum(n_g for (cam, f), (_, n_g) in counts.items() if f == 1)
    n_s = sum(n for n, _ in counts.values())
    assert nv["psnr_garment_db"] == pytest.approx(-10 * np.log10((0.04 * g0 + 0.16 * g1) / (g0 + g1)), abs=1e-4)
    assert nv["psnr_subject_db"] == pytest.approx(-10 * np.log10((0.04 * g0 + 0.16 * g1) / n_s), abs=1e-4)
    assert nv["psnr_body_db"] == np.inf and nv["body_images"] == 4 and nv["body_empty_images"] == 0
    assert (nv["garment_images"], nv["garment_empty_images"], nv["subject_images"]) == (3, 1, 4)
    assert nv["subject_only_images"] == 0 and nv["region_masks"] == ["gt/masks"]
    assert -1 < nv["ssim_garment"] < nv["ssim_subject"] < 1 and "pooled" in summ["region_definition"]
    # 3. dance: the 0 / 255 mask has no labels; the 0 / 1 masks of this garment scene an empty garment region
    dance = {r["camera"]: r for r in rows if r["kind"] == "novel_pose"}
    assert dance["01"]["region_masks"] == "subject only" and dance["01"]["psnr_subject_db"] == np.inf
    assert np.isnan(dance["01"]["psnr_body_db"]) and np.isnan(dance["01"]["ssim_garment"])
    assert all(dance[c]["region_masks"] == "gt/masks" and np.isnan(dance[c]["psnr_garment_db"])
               for c in ("02", "03", "04"))
    npe = next(m for m in summ["metrics"] if m["kind"] == "novel_pose")
    counts_np = (npe["subject_only_images"], npe["garment_images"], npe["garment_empty_images"], npe["body_images"])
    assert counts_np == (1, 0, 3, 3)
    assert np.isnan(npe["psnr_garment_db"]) and npe["region_masks"] == ["gt/masks", "subject only"]
    assert npe["subject_images"] == 4 and npe["ssim_subject"] == pytest.approx(1.0, abs=1e-9)
    # 4. in a scene without a garment, a 0 / 1 mask carries no body / garment distinction; a mask with a 2 does
    (root / "scene.yaml").write_text(yaml.safe_dump(info))
    run_evaluate(root, renders[:1], tmp_path / "m2.csv", tmp_path / "s2.json", {}, progress=False)
    rows2 = {(r["camera"], r["frame"]): r for r in read_metrics_csv(tmp_path / "m2.csv")}
    assert rows2["04", 1]["region_masks"] == "subject only" and np.isnan(rows2["04", 1]["psnr_body_db"])
    assert rows2["02", 1]["region_masks"] == "gt/masks" and rows2["02", 1]["psnr_body_db"] == np.inf
    # 5. a mask of another size than the render: the error names the file and both sizes
    files.write_mask(root / "walk" / "gt" / "masks" / "02" / "000001.png", np.zeros((16, 32), np.uint8))
    with pytest.raises(files.ArtifactError,
                       match=r"masks/02/000001.png: mask size \(16, 32\) differs from the render \(32, 32\)"):
        run_evaluate(root, renders[:1], tmp_path / "m3.csv", tmp_path / "s3.json", {}, progress=False)


def test_partial_sections_take_the_schemas_defaults():
    """A field section that leaves keys out gets the schema's values (one source of defaults), the keys it has win,
    and an unknown training key is a clear error."""
    from anidress_core.config import section_defaults
    from anidress_core.stages.field import field_config_from_params, train_config_from_params

    full = section_defaults("field", {})
    t = train_config_from_params(PARAMS)
    assert (t.steps, t.rays_per_step, t.step_m) == (12, 128, 0.015)  # the section's own values
    for key in ("lr", "lr_weights", "weights_every", "refine_lr", "seed", "lpips_weight"):
        assert getattr(t, key) == full["train"][key]
    m = field_config_from_params(PARAMS)
    assert (m.grid.levels, m.width) == (4, 32)
    assert m.warp_iterations == full["model"]["warp_iterations"]
    assert m.density_bias == full["model"]["density_bias"]
    with pytest.raises(ValueError, match="unknown keys"):
        train_config_from_params({"train": {"stepz": 3}})
