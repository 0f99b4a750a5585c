"""Stage `synth`: write a synthetic scene with full ground truth (DESIGN.md §3, §5).

Layout written under ``data/<scene>/`` (EasyMocap / ZJU-MoCap convention)::

    scene.yaml                     what the scene is (fps, units, cameras, sequences, body)
    body_model.npz                 the mannequin the scene was made with (rest mesh, weights, joints, UVs)
    body_texture.png               its clothing texture (OBJ UV convention)
    garment/template.obj           (skirt/dress scenes) the garment in T-pose with UVs, as a
                                   static reconstruction would provide it
    garment/texture.png            its fabric texture
    <seq>/intri.yml extri.yml      EasyMocap camera files
    <seq>/backgrounds/<cam>.png    static background plate of each camera (no performer)
    <seq>/images/<cam>/<frame:06d>.png
    <seq>/smpl/<frame:06d>.json    EasyMocap body parameters (Rh, Th, poses, shapes)
    <seq>/gt/masks/<cam>/<frame>.png     0 background, 1 body, 2 garment
    <seq>/gt/normals/<cam>/<frame>.exr   camera-space unit normals (OpenCV axes), 0 on background
    <seq>/gt/flows/<cam>/<frame>.exr     channels X, Y, valid: flow from frame-1 to frame,
                                         in pixels on frame-1's pixel grid; valid = visible in frame
    <seq>/normals/<cam>/<frame>.exr      "predicted" normals: the true ones degraded as a
                                         network's are (blurred, noisy), only on the subject
    <seq>/gt/meshes.npz            per-frame body vertices (T, V, 3) and faces (F, 3); garment
                                   vertices (T, Vg, 3) and faces for skirt/dress scenes

The scene is written into a hidden temporary folder beside the target and renamed
into place when complete, so a failure leaves nothing half-written.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm import tqdm

from .. import __version__, garment, sim, synth
from ..body.model import BodyModel, mannequin_model
from ..body.motions import Motion, make_motion
from ..camera import Cameras, ring_cameras, save_cameras
from ..io import files
from ..io.mesh import write_obj
from ..io.motion import write_easymocap_smpl

__all__ = ["SceneAssets", "build_scene", "run_synth", "split_cameras"]

log = logging.getLogger("anidress.synth")


def split_cameras(count: int, train: int) -> tuple[list[int], list[int]]:
    """Spread ``train`` training cameras evenly around a ring of ``count``; the rest test."""
    tr = sorted({int(np.floor(i * count / train + 0.5)) % count for i in range(train)})
    if len(tr) != train:
        raise ValueError(f"cannot spread {train} training cameras over {count}")
    return tr, [i for i in range(count) if i not in tr]


@dataclass
class SceneAssets:
    """Everything a synthetic scene is made of, before any frame is rendered."""

    body: BodyModel
    body_texture: np.ndarray  # (S, S, 3)
    cameras: Cameras
    train_idx: list[int]
    test_idx: list[int]
    lights: synth.Lights
    background: torch.Tensor  # (C, H, W, 3)
    motions: dict[str, Motion]
    garment: garment.GarmentTemplate | None = None
    garment_texture: np.ndarray | None = None  # (S, S, 3)


def _centred(motion: Motion) -> Motion:
    """Shift the motion horizontally so its mean root position sits at the ring centre."""
    Th = motion.Th.clone()
    Th[:, :2] = Th[:, :2] - Th[:, :2].mean(0)
    return dataclasses.replace(motion, Th=Th)


def build_scene(cfg: dict) -> SceneAssets:
    """Body, texture, cameras, lights, background plates and motions of one scene config."""
    seed = int(cfg["seed"])
    H, W = cfg["image_size"]
    cam_cfg = cfg["cameras"]
    body = mannequin_model(height=cfg["body"]["height_m"], target_vertices=cfg["body"]["vertices"])
    face_part = body.vertex_part[body.faces].mode(dim=1).values.numpy()
    loose = cfg["kind"] in garment.KINDS
    # under a skirt or dress the legs are bare
    materials = [
        "skin" if loose and synth.body_part_material(n) == "denim" else synth.body_part_material(n)
        for n in body.part_names
    ]
    texture = synth.atlas_texture(body.face_uv.numpy(), face_part, materials, cfg["render"]["texture_size"], seed)
    focal = 0.5 * H / np.tan(np.deg2rad(cam_cfg["vfov_deg"]) / 2)
    cams = ring_cameras(
        n=cam_cfg["count"], radius=cam_cfg["radius_m"], height=cam_cfg["height_m"],
        target=(0.0, 0.0, cam_cfg["target_height_m"]), focal_px=focal, image_height=H, image_width=W,
    )
    train_idx, test_idx = split_cameras(cam_cfg["count"], cam_cfg["train"])
    lights = synth.default_lights()
    background = synth.studio_background(cams, lights, size=min(1024, cfg["render"]["texture_size"]), seed=seed)
    motions = {}
    for k, seq in enumerate(cfg["sequences"]):
        m = make_motion(seq["motion"], num_frames=seq["frames"], fps=cfg["fps"], seed=seed + 1000 * (k + 1), body=body)
        motions[seq["name"]] = _centred(m)
    assets = SceneAssets(body, texture, cams, train_idx, test_idx, lights, background, motions)
    if loose:
        make = garment.make_skirt if cfg["kind"] == "skirt" else garment.make_dress
        assets.garment = make(body, target_vertices=cfg["garment"]["vertices"])
        assets.garment_texture = synth.material_texture(cfg["garment"]["texture"], cfg["render"]["texture_size"],
                                                        seed + 17)
    return assets


def cloth_params(cloth_cfg: dict) -> sim.ClothParams:
    """ClothParams from a validated `cloth` config section (schema `$defs/cloth`)."""
    return sim.ClothParams(**cloth_cfg)


def simulate_garment(assets: SceneAssets, motion: Motion, cfg: dict) -> np.ndarray:
    """Ground-truth garment sequence (T, Vg, 3) of one motion, simulated on the body."""
    g, body = assets.garment, assets.body
    posed = body.pose(motion.poses, motion.Rh, motion.Th, motion.shapes)
    res = sim.simulate(g.verts, g.faces, g.band, g.body_weights, body.v_template, body.faces, body.weights,
                       posed.transforms, motion.fps, cloth_params(cfg["garment"]["cloth"]))
    log.info("simulated %s: %d frames, max stretch %.3f, max penetration %.1f mm, %d recoveries, %.1f s",
             motion.name, res.frames.shape[0], float(res.stats.max_stretch.max()),
             1e3 * float(res.stats.max_penetration_m.max()), len(res.stats.recoveries), res.stats.wall_s)
    return res.frames


def _scene_yaml(name: str, cfg: dict, assets: SceneAssets) -> dict:
    names = assets.cameras.names
    return {
        "name": name,
        "synthetic": True,
        "kind": cfg["kind"],
        "fps": cfg["fps"],
        "units": "metres",
        "up": [0.0, 0.0, 1.0],
        "image_size": list(cfg["image_size"]),
        "cameras": {"train": [names[i] for i in assets.train_idx], "test": [names[i] for i in assets.test_idx]},
        "sequences": [
            {"name": s["name"], "role": s["role"], "frames": s["frames"], "motion": s["motion"]}
            for s in cfg["sequences"]
        ],
        "garment_template": "garment/template.obj" if assets.garment is not None else None,
        "garment_kind": assets.garment.kind if assets.garment is not None else None,
        "body_model": {"type": "mannequin", "file": "body_model.npz", "height_m": cfg["body"]["height_m"]},
        "ground_truth": {"masks": "gt/masks", "normals": "gt/normals", "flows": "gt/flows", "meshes": "gt/meshes.npz"},
        "predicted_normals": "normals",
        "config_hash": files.config_hash(cfg),
        "code_version": __version__,
    }


def _write_sequence(root: Path, seq: dict, assets: SceneAssets, cfg: dict, pool: ThreadPoolExecutor,
                    progress: bool) -> None:
    name = seq["name"]
    sdir = root / name
    cams = assets.cameras
    save_cameras(cams, sdir / "intri.yml", sdir / "extri.yml")
    for c, cam in enumerate(cams.names):
        files.write_png(sdir / "backgrounds" / f"{cam}.png", assets.background[c].numpy())
    motion = assets.motions[name]
    posed = assets.body.pose(torch.as_tensor(motion.poses), torch.as_tensor(motion.Rh), torch.as_tensor(motion.Th),
                             torch.as_tensor(motion.shapes))
    verts = posed.vertices.float()  # (T, V, 3)
    faces = assets.body.faces
    texture = torch.from_numpy(assets.body_texture)
    face_uv = assets.body.face_uv.float()
    g_verts = None
    if assets.garment is not None:
        g_verts = torch.from_numpy(simulate_garment(assets, motion, cfg)).float()  # (T, Vg, 3)
        g_faces = torch.from_numpy(assets.garment.faces)
        g_uv = torch.from_numpy(assets.garment.face_uv).float()
        g_tex = torch.from_numpy(assets.garment_texture)
    pn = cfg["predicted_normals"]
    gen = torch.Generator().manual_seed(int(cfg["seed"]) * 7919 + sum(map(ord, name)))
    noise_std = float(cfg["render"]["noise_std"])
    prev = None
    pending = []
    T = verts.shape[0]
    for t in tqdm(range(T), desc=f"synth {name}", unit="frame", disable=not progress):
        frame = f"{t:06d}"
        pending.append(pool.submit(
            write_easymocap_smpl, sdir / "smpl" / f"{frame}.json", motion.poses[t], motion.Rh[t], motion.Th[t],
            motion.shapes,
        ))
        layers = [synth.MeshLayer(verts[t], faces, face_uv, texture, synth.LABEL_BODY)]
        if g_verts is not None:
            layers.append(synth.MeshLayer(g_verts[t], g_faces, g_uv, g_tex, synth.LABEL_GARMENT))
        out = synth.render_views(layers, cams, assets.lights, assets.background,
                                 supersample=int(cfg["render"]["supersample"]))
        rgb = out.rgb
        if noise_std > 0:
            rgb = (rgb + noise_std * torch.randn(rgb.shape, generator=gen)).clamp(0, 1)
        flow = None
        if prev is not None:
            flow = synth.forward_flow(prev.fragments, out.verts, out.faces, cams, out.depth)
        pred_n = synth.degrade_normals(out.normals_cam, out.labels > 0, pn["blur_px"], pn["noise_std"], gen)
        for c, cam in enumerate(cams.names):
            pending.append(pool.submit(files.write_png, sdir / "images" / cam / f"{frame}.png", rgb[c].numpy()))
            pending.append(pool.submit(files.write_mask, sdir / "gt" / "masks" / cam / f"{frame}.png",
                                       out.labels[c].numpy()))
            pending.append(pool.submit(files.write_exr, sdir / "gt" / "normals" / cam / f"{frame}.exr",
                                       out.normals_cam[c].numpy()))
            pending.append(pool.submit(files.write_exr, sdir / "normals" / cam / f"{frame}.exr",
                                       pred_n[c].numpy(), None, True))
            if flow is not None:
                fv = torch.cat([flow.flow[c], flow.valid[c, ..., None].to(flow.flow.dtype)], -1).numpy()
                pending.append(pool.submit(files.write_exr, sdir / "gt" / "flows" / cam / f"{frame}.exr", fv,
                                           ("X", "Y", "valid")))
        prev = out
        # bound the queue so memory stays flat; surface writer errors early
        if len(pending) > 64:
            for p in pending:
                p.result()
            pending = []
    for p in pending:
        p.result()
    meshes = {"body_vertices": verts.numpy(), "body_faces": faces.numpy()}
    if g_verts is not None:
        meshes.update(garment_vertices=g_verts.numpy(), garment_faces=g_faces.numpy())
    files.save_npz(sdir / "gt" / "meshes.npz", meshes, config=cfg, meta={"fps": cfg["fps"], "sequence": name})


def run_synth(cfg: dict, scene_name: str, out_dir: str | os.PathLike, threads: int = 2,
              progress: bool = True) -> Path:
    """Generate one synthetic scene (validated scene config ``cfg``) into ``out_dir``.

    Writes into a temporary sibling folder and renames it onto ``out_dir`` at the end;
    an existing ``out_dir`` is replaced only once the new scene is complete.
    """
    out_dir = Path(out_dir)
    if cfg.get("kind") not in ("tight", *garment.KINDS):
        raise ValueError(f"scene {scene_name!r}: unknown synthetic kind {cfg.get('kind')!r}")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(cfg["seed"]))
    log.info("building scene %s (body, texture, cameras, motions)", scene_name)
    assets = build_scene(cfg)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        body = assets.body
        files.save_npz(tmp / "body_model.npz", {
            "v_template": body.v_template.numpy(), "faces": body.faces.numpy(), "weights": body.weights.numpy(),
            "joints_rest": body.joints_rest.numpy(), "parents": body.parents.numpy(),
            "face_uv": body.face_uv.numpy(), "vertex_part": body.vertex_part.numpy(),
            "part_names": np.array(body.part_names),
        }, config=cfg)
        files.write_png(tmp / "body_texture.png", assets.body_texture)
        if assets.garment is not None:
            g = assets.garment
            write_obj(tmp / "garment" / "template.obj", g.verts, g.faces, g.face_uv)
            files.write_png(tmp / "garment" / "texture.png", assets.garment_texture)
        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            for seq in cfg["sequences"]:
                log.info("rendering sequence %s: %d frames x %d cameras at %dx%d", seq["name"], seq["frames"],
                         len(assets.cameras), *cfg["image_size"])
                _write_sequence(tmp, seq, assets, cfg, pool, progress)
        # scene.yaml last: its presence marks a complete scene
        with files.atomic_path(tmp / "scene.yaml") as p:
            p.write_text(yaml.safe_dump(_scene_yaml(scene_name, cfg, assets), sort_keys=False))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    log.info("wrote %s", out_dir)
    return out_dir
