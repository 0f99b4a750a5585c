"""Writes the tiny cue-file samples under tests/data/cue_files/ (run from the repository root:
``python tests/data/cue_files/make_samples.py``).

Every file is written the way the tool's own code writes it, with PIL / OpenCV / numpy calls
restated here (not with anidress_core.io.cue_files' writers), so the tests check our readers
against the tools' writers. The values are made up (small analytic patterns, no licensed data);
the images are W x H = 20 x 12 pixels, camera "01". README.md lists the files.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent
H, W = 12, 20
CAM = "01"

# label geometry of the samples: (label name, row slice, column slice), painted in order
LIP = {"Face": 13, "Upper-clothes": 5, "Dress": 6, "Skirt": 12, "Left-leg": 16, "Right-leg": 17, "Pants": 9}
ATR = {"Face": 11, "Upper-clothes": 4, "Dress": 7, "Skirt": 5, "Left-leg": 12, "Right-leg": 13, "Pants": 6}
CIHP = {"Face": 13, "Upper-clothes": 5, "Dress": 6, "Skirt": 12, "Left-leg": 16, "Right-leg": 17,
        "Torso-skin": 10}


def get_palette(num_cls: int) -> list[int]:
    """SCHP's palette (GoGoDuck912/Self-Correction-Human-Parsing simple_extractor.py get_palette),
    restated: bit 3i of the label sets bit 7 - i of red, 3i + 1 of green, 3i + 2 of blue."""
    pal = [0] * (num_cls * 3)
    for j in range(num_cls):
        lab, i = j, 0
        while lab:
            for c in range(3):
                pal[j * 3 + c] |= ((lab >> c) & 1) << (7 - i)
            i += 1
            lab >>= 3
    return pal


def person(labels: dict[str, int], col: int, lower: str) -> np.ndarray:
    """(H, W) uint8 label indices: one person, left edge at ``col``, ``lower`` garment (Dress/Skirt/Pants)."""
    m = np.zeros((H, W), np.uint8)
    m[1:3, col + 2:col + 5] = labels["Face"]
    m[3:6, col + 1:col + 6] = labels["Upper-clothes"]
    m[6:10, col:col + 7] = labels[lower]
    m[10:12, col + 1:col + 3] = labels["Left-leg"]
    m[10:12, col + 4:col + 6] = labels["Right-leg"]
    return m


def save_schp(path: Path, parsing: np.ndarray, num_classes: int) -> None:
    """simple_extractor.py: Image.fromarray(uint8) -> putpalette(get_palette(num_classes)) -> save."""
    path.parent.mkdir(parents=True, exist_ok=True)
    img = Image.fromarray(np.asarray(parsing, dtype=np.uint8))
    img.putpalette(get_palette(num_classes))
    img.save(path)


def normal_field(frame: int) -> np.ndarray:
    """(H, W, 3) float64 unit normals, x right, y down, z out of the image (a tilted dome)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    n = np.stack([(x - 9.5) / 12.0 + 0.1 * frame, (y - 5.5) / 8.0, -np.ones_like(x)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def foreground() -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return ((x - 9.5) / 8.0) ** 2 + ((y - 5.5) / 5.0) ** 2 <= 1.0


def write_flow_raft(path: Path, uv: np.ndarray) -> None:
    """RAFT core/utils/frame_utils.py writeFlow, restated: TAG_CHAR, int32 width, int32 height,
    then float32 u, v interleaved per row."""
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width = uv.shape[:2]
    with open(path, "wb") as f:
        np.array([202021.25], np.float32).tofile(f)
        np.array(width).astype(np.int32).tofile(f)
        np.array(height).astype(np.int32).tofile(f)
        tmp = np.zeros((height, width * 2))
        tmp[:, np.arange(width) * 2] = uv[..., 0]
        tmp[:, np.arange(width) * 2 + 1] = uv[..., 1]
        tmp.astype(np.float32).tofile(f)


def flow_field(frame: int) -> np.ndarray:
    """(H, W, 2) float32 flow in quarter pixels (exact in .flo and in KITTI's 1/64 steps)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([(x - 10.0) / 4.0 + frame, (y - 6.0) / 4.0 - 0.5 * frame], -1).astype(np.float32)


def main() -> None:
    for sub in ("schp", "easymocap", "sapiens", "normals_png", "icon", "econ", "raft", "kitti", "raft_padded"):
        shutil.rmtree(ROOT / sub, ignore_errors=True)

    # 1. SCHP simple_extractor.py, plain layout <cam>/<frame:06d>.png: lip (palette of 20), atr (18);
    #    cihp (mhp_extension, get_palette(256)). Frame 0: a dress, frame 1: a skirt.
    for name, labels, ncls in (("lip", LIP, 20), ("atr", ATR, 18), ("cihp", CIHP, 256)):
        for frame, lower in ((0, "Dress"), (1, "Skirt")):
            save_schp(ROOT / "schp" / name / CAM / f"{frame:06d}.png", person(labels, 6 + frame, lower), ncls)

    # 2. EasyMocap's SCHP fork (mhp_extension/logits_fusion.py result_saving, copied by extract_multi.py):
    #    mask-schp/<cam>/<frame>_<i>.png = cv2.imwrite((person_id == i + 1) * 255), 8-bit grey;
    #    mask-schp-parsing/<cam>/<frame>.png = CIHP labels of everyone, 'P' with get_palette(256).
    #    Frame 0: two persons (0: skirt at the left, 1: dress at the right); frame 1: person 0 only.
    for frame, people in ((0, ((1, "Skirt"), (12, "Dress"))), (1, ((2, "Skirt"),))):
        parsing = np.zeros((H, W), np.uint8)
        ids = np.zeros((H, W), np.uint8)
        for pid, (col, lower) in enumerate(people, start=1):
            p = person(CIHP, col, lower)
            parsing = np.where(p > 0, p, parsing)
            ids[p > 0] = pid
        if frame == 0:
            parsing[4, 2] = CIHP["Torso-skin"]  # a body label other than clothes
        save_schp(ROOT / "easymocap" / "mask-schp-parsing" / CAM / f"{frame:06d}.png", parsing, 256)
        out = ROOT / "easymocap" / "mask-schp" / CAM
        out.mkdir(parents=True, exist_ok=True)
        for i in range(1, int(ids.max()) + 1):
            cv2.imwrite(str(out / f"{frame:06d}_{i - 1}.png"), ((ids == i) * 255).astype(np.uint8))

    # 3. Sapiens lite/demo/vis_normal.py img_save_and_viz: (H, W, 3) float32 at the image size,
    #    n / (|n| + 1e-5), np.save(<stem>.npy); unmasked.
    for frame in (0, 1):
        n = normal_field(frame).astype(np.float32) * 1.7  # the model's output is not unit length
        n = n / (np.linalg.norm(n, axis=-1, keepdims=True) + 1e-5)
        (ROOT / "sapiens" / CAM).mkdir(parents=True, exist_ok=True)
        np.save(ROOT / "sapiens" / CAM / f"{frame:06d}.npy", n)

    # 4. (n+1)/2 8-bit PNG as Sapiens' visualisation encodes it (the normal half of its
    #    [image | normals] picture): background set to -1 (black), ((n + 1) / 2 * 255).astype(uint8),
    #    [:, :, ::-1] and cv2.imwrite.
    fg = foreground()
    for frame in (0, 1):
        n = normal_field(frame).astype(np.float32)
        n[~fg] = -1
        vis = ((n + 1) / 2 * 255).astype(np.uint8)[:, :, ::-1]
        (ROOT / "normals_png" / CAM).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(ROOT / "normals_png" / CAM / f"{frame:06d}.png"), vis)

    # 5. ICON apps/infer.py: norm_pred = ((normal_F + 1) * 255 / 2).astype(uint8) of the masked crop
    #    (background = zero vector -> 127), written with PIL (Image.fromarray(...).save). An 8x8 crop
    #    per frame (ICON's are 512x512) and crops.json: frame 0 at scale 1 reaching past the top
    #    of the image, frame 1 at scale 2.
    crop = np.zeros((8, 8, 3), np.float32)
    yy, xx = np.mgrid[0:8, 0:8]
    inside = (xx >= 1) & (xx <= 6) & (yy >= 1) & (yy <= 6)
    c = np.stack([(xx - 3.5) / 6.0, (yy - 3.5) / 6.0, np.ones((8, 8))], -1)
    crop[inside] = (c / np.linalg.norm(c, axis=-1, keepdims=True))[inside]
    (ROOT / "icon" / CAM).mkdir(parents=True, exist_ok=True)
    for frame in (0, 1):
        norm_pred = ((crop + 1.0) * 255.0 / 2.0).astype(np.uint8)
        Image.fromarray(norm_pred).save(ROOT / "icon" / CAM / f"{frame:06d}.png")
    crops = {f"{CAM}/000000": [6.5, -1.5, 14.5, 6.5], f"{CAM}/000001": [2.5, -2.5, 18.5, 13.5]}
    (ROOT / "icon" / "crops.json").write_text(json.dumps(crops, indent=1))

    # 6. ECON apps/infer.py: png/<name>_crop.png = torchvision.utils.save_image of
    #    [img_crop, (normal_F + 1) * 0.5, (normal_B + 1) * 0.5] side by side; save_image rounds
    #    (x * 255 + 0.5, clamp, uint8) and writes RGB with PIL. 8x8 panels here (ECON's are 512).
    rgb = np.full((8, 8, 3), 0.25, np.float32)
    back = crop * np.array([-1.0, 1.0, -1.0], np.float32)
    grid = np.concatenate([rgb, (crop + 1.0) * 0.5, (back + 1.0) * 0.5], axis=1)
    (ROOT / "econ" / CAM).mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.clip(grid * 255 + 0.5, 0, 255).astype(np.uint8)).save(ROOT / "econ" / CAM / "000000_crop.png")

    # 7. RAFT .flo (writeFlow) at frames 1 and 2: the flow from the previous frame.
    for frame in (1, 2):
        write_flow_raft(ROOT / "raft" / CAM / f"{frame:06d}.flo", flow_field(frame))

    # 8. KITTI 16-bit PNG: frame 1 as RAFT's writeFlowKITTI (64 uv + 2^15, valid 1, astype(uint16),
    #    cv2.imwrite(uv[..., ::-1])); frame 2 as KITTI's ground truth, (0, 0, 0) where unknown
    #    (the left four columns).
    (ROOT / "kitti" / CAM).mkdir(parents=True, exist_ok=True)
    for frame in (1, 2):
        uv = 64.0 * flow_field(frame) + 2 ** 15
        valid = np.ones([H, W, 1])
        if frame == 2:
            valid[:, :4] = 0
            uv[:, :4] = 0
        img = np.concatenate([uv, valid], axis=-1).astype(np.uint16)
        cv2.imwrite(str(ROOT / "kitti" / CAM / f"{frame:06d}.png"), img[..., ::-1])

    # 9. A RAFT flow saved without padder.unpad: InputPadder pads 12x20 to 16x24 ('sintel' mode:
    #    2 rows top and bottom, 2 columns left and right).
    padded = np.pad(flow_field(1), ((2, 2), (2, 2), (0, 0)), mode="edge")
    write_flow_raft(ROOT / "raft_padded" / CAM / "000001.flo", padded)

    total = sum(p.stat().st_size for p in ROOT.rglob("*") if p.is_file())
    print(f"wrote the samples under {ROOT} ({total} bytes in all)")


if __name__ == "__main__":
    main()
