"""Cue files of external tools (anidress_core.io.cue_files). Samples: tests/data/cue_files/, written by
its make_samples.py the way each tool's own code writes them (README.md there names the sources),
so these tests check our readers against the tools' writers."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from anidress_core.io import cue_files as cf
from anidress_core.io.files import ArtifactError, write_exr
from anidress_core.io.scene_info import SCHP_LABEL_SET_NAMES, SHIPPED_CUE_FORMATS

DATA = Path(__file__).resolve().parents[1] / "data" / "cue_files"
H, W = 12, 20
BOUND_8BIT_ROUND = 2 * math.sqrt(3) / 255  # |n - decode(encode(n))|, rounding to 8 bits, renormalised
BOUND_8BIT_TRUNC = 4 * math.sqrt(3) / 255  # the same when the writer truncates (ICON, Sapiens' visualisation)


# the analytic patterns of make_samples.py


def normal_field(frame: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    n = np.stack([(x - 9.5) / 12.0 + 0.1 * frame, (y - 5.5) / 8.0, -np.ones_like(x)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def flow_field(frame: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([(x - 10.0) / 4.0 + frame, (y - 6.0) / 4.0 - 0.5 * frame], -1)


def icon_crop() -> np.ndarray:
    yy, xx = np.mgrid[0:8, 0:8]
    inside = (xx >= 1) & (xx <= 6) & (yy >= 1) & (yy <= 6)
    c = np.stack([(xx - 3.5) / 6.0, (yy - 3.5) / 6.0, np.ones((8, 8))], -1)
    return np.where(inside[..., None], c / np.linalg.norm(c, axis=-1, keepdims=True), 0.0)


# --------------------------------------------------------------------------- SCHP


def test_label_sets_and_default_garment_labels():
    sets = cf.SCHP_LABEL_SETS
    assert {k: len(v) for k, v in sets.items()} == {"lip": 20, "atr": 18, "cihp": 20}
    assert (sets["lip"][6], sets["lip"][12], sets["lip"][10]) == ("Dress", "Skirt", "Jumpsuits")
    assert (sets["atr"][7], sets["atr"][5], sets["atr"][16]) == ("Dress", "Skirt", "Bag")
    assert sets["cihp"][10] == "Torso-skin"
    assert [a for a, b in zip(sets["lip"], sets["cihp"]) if a != b] == ["Jumpsuits"]  # differ at 10 only
    assert cf.SCHP_GARMENT_LABELS == {"lip": (6, 12), "atr": (7, 5), "cihp": (6, 12)}
    assert tuple(sets) == SCHP_LABEL_SET_NAMES  # scene.yaml's label sets (io.scene_info)
    assert set(cf.FLOW_SUFFIXES.values()) == set(SHIPPED_CUE_FORMATS["flows"])


def test_palette_is_schps():
    pal = cf.schp_palette(256)
    assert pal.shape == (256, 3) and pal.dtype == np.uint8
    assert pal[:8].tolist() == [[0, 0, 0], [128, 0, 0], [0, 128, 0], [128, 128, 0], [0, 0, 128], [128, 0, 128],
                                [0, 128, 128], [128, 128, 128]]
    assert pal[8].tolist() == [64, 0, 0] and pal[13].tolist() == [192, 0, 128]
    assert len({tuple(c) for c in pal.tolist()}) == 256  # one colour per index: colours map back
    with Image.open(DATA / "schp" / "lip" / "01" / "000000.png") as im:  # simple_extractor: get_palette(20)
        assert im.mode == "P"
        assert np.array(im.getpalette(), np.uint8).reshape(-1, 3)[:20].tolist() == cf.schp_palette(20).tolist()


@pytest.mark.parametrize("label_set, dress, skirt, face", [("lip", 6, 12, 13), ("atr", 7, 5, 11), ("cihp", 6, 12, 13)])
def test_schp_samples_read_as_indices_and_labels(label_set, dress, skirt, face):
    for frame, lower in ((0, dress), (1, skirt)):
        path = DATA / "schp" / label_set / "01" / f"{frame:06d}.png"
        idx = cf.read_label_indices(path)
        assert idx.shape == (H, W) and idx.dtype == np.uint8
        assert idx[0, 0] == 0 and idx[1, 8 + frame] == face and idx[7, 9 + frame] == lower
        lab = cf.schp_to_labels(idx, label_set, path=path)
        assert lab.dtype == np.uint8 and (lab[0, 0], lab[1, 8 + frame], lab[7, 9 + frame]) == (0, 1, 2)
        assert np.array_equal(lab == 2, idx == lower) and np.array_equal(lab == 0, idx == 0)


def test_rgb_resave_maps_back_and_foreign_colours_error(tmp_path):
    src = DATA / "schp" / "lip" / "01" / "000000.png"
    want = cf.read_label_indices(src)
    with Image.open(src) as im:
        rgb = np.array(im.convert("RGB"))
    Image.fromarray(rgb).save(tmp_path / "rgb.png")  # a user re-saved the mask as colours
    assert np.array_equal(cf.read_label_indices(tmp_path / "rgb.png"), want)
    Image.fromarray(np.dstack([rgb, np.full((H, W), 255, np.uint8)])).save(tmp_path / "rgba.png")
    assert np.array_equal(cf.read_label_indices(tmp_path / "rgba.png"), want)
    rgb[3, 4] = (10, 200, 30)
    Image.fromarray(rgb).save(tmp_path / "jet.png")
    with pytest.raises(ArtifactError, match=r"jet\.png.*\(10, 200, 30\) at row 3, column 4.*indices were lost"):
        cf.read_label_indices(tmp_path / "jet.png")
    Image.fromarray(np.full((H, W, 3), 255, np.uint8)).save(tmp_path / "grey.png")
    with pytest.raises(ArtifactError, match="grey image saved as colour"):
        cf.read_label_indices(tmp_path / "grey.png")
    Image.fromarray(want).save(tmp_path / "l.png")  # mode 'L': the values
    assert np.array_equal(cf.read_label_indices(tmp_path / "l.png"), want)
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ArtifactError, match="broken.png"):
        cf.read_label_indices(tmp_path / "broken.png")


def test_write_schp_png_round_trip(tmp_path):
    idx = np.random.default_rng(0).integers(0, 18, size=(5, 7)).astype(np.uint8)
    cf.write_schp_png(tmp_path / "m.png", idx, num_classes=18)
    with Image.open(tmp_path / "m.png") as im:
        assert im.mode == "P" and im.getpalette() == cf.schp_palette(18).reshape(-1).tolist()
    assert np.array_equal(cf.read_label_indices(tmp_path / "m.png"), idx)
    cf.write_schp_png(tmp_path / "m256.png", idx)
    assert np.array_equal(cf.read_label_indices(tmp_path / "m256.png"), idx)
    with pytest.raises(ValueError, match="0..17"):
        cf.write_schp_png(tmp_path / "bad.png", idx + 1, num_classes=18)


def test_schp_to_labels_checks_values_and_settings():
    idx = np.array([[0, 6, 12], [5, 19, 1]])
    assert cf.schp_to_labels(idx, "lip").tolist() == [[0, 2, 2], [1, 1, 1]]
    assert cf.schp_to_labels(idx, "lip", garment_labels=[5]).tolist() == [[0, 1, 1], [2, 1, 1]]
    with pytest.raises(ArtifactError, match=r"masks/a\.png: label values \[19\] lie outside SCHP's atr set \(0..17\)"
                                            r".*lip or cihp"):
        cf.schp_to_labels(idx, "atr", path="masks/a.png")
    with pytest.raises(ArtifactError, match="binary silhouette.*mask-schp-parsing"):
        cf.schp_to_labels(np.array([[0, 255]]), "cihp", path="m.png")
    with pytest.raises(ValueError, match="unknown SCHP label set 'pascal'"):
        cf.schp_to_labels(idx, "pascal")
    with pytest.raises(ValueError, match=r"garment labels \[20\]"):
        cf.schp_to_labels(idx, "lip", garment_labels=[20])


def test_easymocap_mask_schp_layout():
    folder = DATA / "easymocap" / "mask-schp"
    with pytest.raises(ArtifactError, match=r"frame 0 has masks of 2 persons \[0, 1\].*person setting"):
        cf.schp_mask_path(folder, "01", 0)
    assert cf.schp_mask_path(folder, "01", 0, person=1).name == "000000_1.png"
    assert cf.schp_mask_path(folder, "01", 1).name == "000001_0.png"  # one person: no setting needed
    with pytest.raises(FileNotFoundError, match=r"no mask of person 3 \(persons present: \[0, 1\]\)"):
        cf.schp_mask_path(folder, "01", 0, person=3)
    with pytest.raises(FileNotFoundError, match="no SCHP mask for frame 7"):
        cf.schp_mask_path(folder, "01", 7)
    with pytest.raises(FileNotFoundError, match="camera '02'"):
        cf.schp_mask_path(folder, "02", 0)
    # the per-person files are 0 / 255 silhouettes; the part labels come from mask-schp-parsing
    sil = cf.read_label_indices(cf.schp_mask_path(folder, "01", 0, person=1))
    assert set(np.unique(sil).tolist()) == {0, 255}
    parsing = cf.read_label_indices(DATA / "easymocap" / "mask-schp-parsing" / "01" / "000000.png")
    for p, garment in ((0, 12), (1, 6)):  # person 0 wears a skirt, person 1 a dress
        lab = cf.read_schp_labels(folder, "01", 0, "cihp", person=p)
        mine = cf.read_label_indices(cf.schp_mask_path(folder, "01", 0, person=p)) > 0
        assert np.array_equal(lab > 0, mine)
        assert np.array_equal(lab == 2, mine & (parsing == garment))
    assert cf.read_schp_labels(folder, "01", 0, "cihp", person=0)[4, 2] == 1  # torso skin: body
    assert cf.read_schp_labels(folder, "01", 1, "cihp").max() == 2
    plain = cf.read_schp_labels(DATA / "schp" / "cihp", "01", 0, "cihp", person=4)  # person: plain layout ignores it
    assert np.array_equal(plain, cf.schp_to_labels(cf.read_label_indices(DATA / "schp/cihp/01/000000.png"), "cihp"))


def test_mask_paths_accept_any_zero_padding(tmp_path):
    d = tmp_path / "masks" / "c0"
    d.mkdir(parents=True)
    for name in ("1.png", "0002.png", "000003_0.png", "000003_vis.png", "notes.txt", "10.png"):
        (d / name).write_bytes(b"")
    assert cf.schp_mask_path(tmp_path / "masks", "c0", 1).name == "1.png"
    assert cf.schp_mask_path(tmp_path / "masks", "c0", 2).name == "0002.png"
    assert cf.schp_mask_path(tmp_path / "masks", "c0", 3).name == "000003_0.png"
    assert cf.schp_mask_path(tmp_path / "masks", "c0", 10).name == "10.png"
    (d / "000001.png").write_bytes(b"")
    with pytest.raises(ArtifactError, match=r"several mask files for frame 1: \['000001.png', '1.png'\]"):
        cf.schp_mask_path(tmp_path / "masks", "c0", 1)
    (d / "2_0.png").write_bytes(b"")
    with pytest.raises(ArtifactError, match="keep one layout"):
        cf.schp_mask_path(tmp_path / "masks", "c0", 2)
    (d / "0.png").write_bytes(b"")
    assert cf.schp_mask_path(tmp_path / "masks", "c0", 0).name == "0.png"


def test_per_person_silhouette_without_parsing_explains(tmp_path):
    d = tmp_path / "mask-schp" / "01"
    d.mkdir(parents=True)
    cv2.imwrite(str(d / "000000_0.png"), np.full((4, 4), 255, np.uint8))
    with pytest.raises(ArtifactError, match=r"000000_0.png: a per-person silhouette.*mask-schp-parsing"):
        cf.read_schp_labels(tmp_path / "mask-schp", "01", 0, "cihp")


# --------------------------------------------------------------------------- normals


def test_sapiens_npy_sample():
    for frame in (0, 1):
        path = DATA / "sapiens" / "01" / f"{frame:06d}.npy"
        raw = np.load(path)
        assert raw.shape == (H, W, 3) and raw.dtype == np.float32  # the demo's layout
        n = cf.read_sapiens_normals(path)
        assert n.shape == (H, W, 3) and n.dtype == np.float32
        np.testing.assert_allclose(n, normal_field(frame), atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)


def test_sapiens_npy_checks(tmp_path):
    n = normal_field(0).astype(np.float32)
    cf.write_sapiens_normals(tmp_path / "n.npy", n)
    assert np.array_equal(np.load(tmp_path / "n.npy"), n)
    np.testing.assert_allclose(cf.read_sapiens_normals(tmp_path / "n.npy"), n, atol=1e-6)
    np.save(tmp_path / "chw.npy", n.transpose(2, 0, 1))
    with pytest.raises(ArtifactError, match=r"chw.npy: .*\(3, 12, 20\).*channel-first"):
        cf.read_sapiens_normals(tmp_path / "chw.npy")
    np.save(tmp_path / "int.npy", (n * 100).astype(np.int16))
    with pytest.raises(ArtifactError, match="int.npy: normals must be floating point"):
        cf.read_sapiens_normals(tmp_path / "int.npy")
    n[2, 3, 1] = np.nan
    np.save(tmp_path / "nan.npy", n)
    with pytest.raises(ArtifactError, match="nan.npy: 1 pixels with non-finite normals.*row 2, column 3"):
        cf.read_sapiens_normals(tmp_path / "nan.npy")
    (tmp_path / "junk.npy").write_bytes(b"junk")
    with pytest.raises(ArtifactError, match="junk.npy: not a readable .npy"):
        cf.read_sapiens_normals(tmp_path / "junk.npy")


def test_normal_png_sample_decodes_within_8bit_truncation():
    y, x = np.mgrid[0:H, 0:W]
    fg = ((x - 9.5) / 8.0) ** 2 + ((y - 5.5) / 5.0) ** 2 <= 1.0
    for frame in (0, 1):
        n = cf.read_normal_image(DATA / "normals_png" / "01" / f"{frame:06d}.png")
        assert n.shape == (H, W, 3) and n.dtype == np.float32
        assert not n[~fg].any()  # black background -> zero vector
        err = np.linalg.norm(n[fg] - normal_field(frame)[fg], axis=-1)
        assert err.max() <= BOUND_8BIT_TRUNC
        np.testing.assert_allclose(np.linalg.norm(n[fg], axis=-1), 1.0, atol=1e-6)
        assert (n[fg][:, 2] < 0).all()  # channel order kept: z (blue) is the negative one


def test_normal_image_round_trips(tmp_path):
    n = normal_field(1)
    n[0, :3] = 0.0  # background
    cf.write_normal_image(tmp_path / "n8.png", n)
    raw = cv2.imread(str(tmp_path / "n8.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw[0, 0].tolist() == [0, 0, 0]
    assert raw[5, 10, 0] == np.floor((n[5, 10, 2] + 1) / 2 * 255 + 0.5)  # blue stored where OpenCV keeps it
    back = cf.read_normal_image(tmp_path / "n8.png")
    assert not back[0, :3].any()
    assert np.linalg.norm(back - n, axis=-1).max() <= BOUND_8BIT_ROUND
    cf.write_normal_image(tmp_path / "n16.png", n, bits=16)
    assert cv2.imread(str(tmp_path / "n16.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert np.linalg.norm(cf.read_normal_image(tmp_path / "n16.png") - n, axis=-1).max() <= 1e-4
    write_exr(tmp_path / "n.exr", ((n + 1) / 2).astype(np.float32))
    exr = cf.read_normal_image(tmp_path / "n.exr")
    np.testing.assert_allclose(exr[1:], n[1:], atol=1e-6)
    np.testing.assert_allclose(exr[0, 3:], n[0, 3:], atol=1e-6)
    assert not exr[0, :3].any()  # the zero vector, stored as 0.5 grey in the EXR
    with pytest.raises(ValueError, match="bits must be 8 or 16"):
        cf.write_normal_image(tmp_path / "x.png", n, bits=12)


def test_grey_and_alpha_backgrounds_are_no_normal(tmp_path):
    img = np.full((2, 3, 4), 200, np.uint8)
    img[0, 0, :3] = 127  # ICON's background: the zero vector, truncated
    img[0, 1, :3] = 128  # ECON's: rounded
    img[0, 2, 3] = 0  # transparent
    img[1, :, :3] = (255, 128, 128)  # +z: OpenCV stores blue first
    cv2.imwrite(str(tmp_path / "a.png"), img)
    n = cf.read_normal_image(tmp_path / "a.png")
    assert not n[0].any()
    np.testing.assert_allclose(n[1], [[1 / 255, 1 / 255, 1.0]] * 3, atol=1e-4)  # (x, y, z) = (R, G, B)
    cv2.imwrite(str(tmp_path / "grey.png"), np.zeros((2, 2), np.uint8))
    with pytest.raises(ArtifactError, match="grey.png: a normal image has 3 colour channels"):
        cf.read_normal_image(tmp_path / "grey.png")


def test_icon_crop_sample_and_crops_json():
    crop = cf.read_normal_image(DATA / "icon" / "01" / "000000.png")
    want = icon_crop()
    assert crop.shape == (8, 8, 3)
    assert not crop[0].any() and not crop[:, 7].any()  # the masked background (127 grey)
    assert np.linalg.norm(crop - want, axis=-1).max() <= BOUND_8BIT_TRUNC
    boxes = cf.read_crops(DATA / "icon" / "crops.json")
    assert boxes == {"01/000000": (6.5, -1.5, 14.5, 6.5), "01/000001": (2.5, -2.5, 18.5, 13.5)}
    assert cf.crop_key("01", 1) == "01/000001"
    # scale 1: image pixel (r, c) is crop pixel (r + 1, c - 7); the crop's row 0 lies above the image
    img = cf.paste_crop(crop, boxes["01/000000"], H, W)
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    np.testing.assert_allclose(img[0:7, 7:15], crop[1:8, 0:8], atol=1e-6)
    mask = np.zeros((H, W), bool)
    mask[0:6, 8:14] = True
    assert np.array_equal(np.linalg.norm(img, axis=-1) > 0, mask)


def _paste_reference(crop, box, height, width):
    """Slow, obvious paste: per image pixel, the bilinear sample of the crop (module docstring)."""
    x0, y0, x1, y1 = box
    h, w = crop.shape[:2]
    has = np.linalg.norm(crop, axis=-1) > 1e-6
    out = np.zeros((height, width, 3))
    for r in range(height):
        for c in range(width):
            if not (x0 <= c < x1 and y0 <= r < y1):
                continue
            cx = min(max((c - x0) / ((x1 - x0) / w) - 0.5, 0), w - 1)
            cy = min(max((r - y0) / ((y1 - y0) / h) - 0.5, 0), h - 1)
            acc, wsum = np.zeros(3), 0.0
            for i in (math.floor(cy), math.floor(cy) + 1):
                for j in (math.floor(cx), math.floor(cx) + 1):
                    wt = (1 - abs(cy - i)) * (1 - abs(cx - j))
                    if wt <= 0 or i >= h or j >= w:
                        continue
                    if has[i, j]:
                        acc += wt * crop[i, j]
                        wsum += wt
            if wsum >= 0.5 and np.linalg.norm(acc) > 0:
                out[r, c] = acc / np.linalg.norm(acc)
    return out


@pytest.mark.parametrize("box", [(2.5, -2.5, 18.5, 13.5), (-3.2, 1.7, 9.1, 9.4), (5.0, 3.0, 6.0, 4.0)])
def test_paste_crop_matches_slow_reference(box):
    crop = cf.read_normal_image(DATA / "icon" / "01" / "000001.png")
    got = cf.paste_crop(crop, box, H, W)
    np.testing.assert_allclose(got, _paste_reference(crop, box, H, W), atol=1e-6)
    x0, y0, x1, y1 = box
    r, c = np.mgrid[0:H, 0:W]
    assert not got[~((c >= x0) & (c < x1) & (r >= y0) & (r < y1))].any()  # zero outside the box


def test_paste_crop_edge_cases():
    crop = np.zeros((4, 4, 3))
    crop[..., 2] = 1.0
    assert not cf.paste_crop(crop, (30.0, 30.0, 40.0, 40.0), H, W).any()  # box off the image
    full = cf.paste_crop(crop, (-0.5, -0.5, W - 0.5, H - 0.5), H, W)
    assert np.array_equal(full[..., 2], np.ones((H, W), np.float32))
    assert not cf.paste_crop(np.zeros((4, 4, 3)), (-0.5, -0.5, 5, 5), H, W).any()
    with pytest.raises(ValueError, match="x0 < x1"):
        cf.paste_crop(crop, (5, 0, 5, 4), H, W)
    with pytest.raises(ValueError, match=r"\(h, w, 3\)"):
        cf.paste_crop(crop[..., :2], (0, 0, 4, 4), H, W)


def test_crops_json_checks(tmp_path):
    p = tmp_path / "crops.json"
    cf.write_crops(p, {"01/000002": (0, 1, 2.5, 3), "a/b/000001": (1, 1, 2, 2)})
    assert cf.read_crops(p) == {"01/000002": (0.0, 1.0, 2.5, 3.0), "a/b/000001": (1.0, 1.0, 2.0, 2.0)}
    p.write_text(json.dumps({"01/7": [0, 0, 512, 512]}))
    assert cf.read_crops(p) == {"01/000007": (0.0, 0.0, 512.0, 512.0)}  # any zero padding
    for bad, msg in (({"01/7": [0, 0, 1]}, "4 numbers"), ({"017": [0, 0, 1, 1]}, "is not"),
                     ({"01/7": [0, 0, -1, 1]}, "x0 < x1"),
                     ({"01/7": [0, 0, 1, 1], "01/0007": [0, 0, 1, 1]}, "two boxes"),
                     ([1, 2], "an object")):
        p.write_text(json.dumps(bad))
        with pytest.raises(ArtifactError, match=f"crops.json: .*{msg}"):
            cf.read_crops(p)
    p.write_text("{")
    with pytest.raises(ArtifactError, match="crops.json: invalid JSON"):
        cf.read_crops(p)


def test_econ_crop_panels():
    front, back = cf.read_econ_crop(DATA / "econ" / "01" / "000000_crop.png")
    want = icon_crop()
    assert front.shape == back.shape == (8, 8, 3)
    assert np.linalg.norm(front - want, axis=-1).max() <= BOUND_8BIT_ROUND
    assert np.linalg.norm(back - want * [-1, 1, -1], axis=-1).max() <= BOUND_8BIT_ROUND
    assert not front[0].any()


# --------------------------------------------------------------------------- flows


def test_flo_sample_and_byte_identical_writer(tmp_path):
    for frame in (1, 2):
        path = DATA / "raft" / "01" / f"{frame:06d}.flo"
        flow, valid = cf.read_flo(path)
        assert flow.shape == (H, W, 2) and flow.dtype == np.float32 and valid.dtype == bool and valid.all()
        assert np.array_equal(flow, flow_field(frame))
        cf.write_flo(tmp_path / "f.flo", flow)
        assert (tmp_path / "f.flo").read_bytes() == path.read_bytes()  # RAFT's writeFlow, byte for byte
        cf.write_flo(tmp_path / "f64.flo", flow.astype(np.float64))
        assert (tmp_path / "f64.flo").read_bytes() == path.read_bytes()


def test_flo_magic_size_and_unknown_marker(tmp_path):
    good = (DATA / "raft" / "01" / "000001.flo").read_bytes()
    (tmp_path / "bad.flo").write_bytes(b"PIEX" + good[4:])
    with pytest.raises(ArtifactError, match=r"bad.flo: not a Middlebury .flo file \(magic number"):
        cf.read_flo(tmp_path / "bad.flo")
    (tmp_path / "short.flo").write_bytes(good[:-8])
    with pytest.raises(ArtifactError, match="short.flo: .*truncated"):
        cf.read_flo(tmp_path / "short.flo")
    (tmp_path / "tiny.flo").write_bytes(good[:6])
    with pytest.raises(ArtifactError, match="tiny.flo: 6 bytes"):
        cf.read_flo(tmp_path / "tiny.flo")
    # Middlebury's unknown flow: |u| or |v| > 1e9 (1e10 written)
    flow = flow_field(1)
    flow[3, 4] = (1e10, 1e10)
    flow[5, 6, 1] = -1e10
    with open(tmp_path / "unk.flo", "wb") as f:
        np.array([202021.25], np.float32).tofile(f)
        np.array([W, H], np.int32).tofile(f)
        flow.astype(np.float32).tofile(f)
    got, valid = cf.read_flo(tmp_path / "unk.flo")
    assert valid.sum() == H * W - 2 and not valid[3, 4] and not valid[5, 6]
    assert got[3, 4].tolist() == [0.0, 0.0]
    want = np.ones((H, W), bool)
    want[3, 4] = want[5, 6] = False
    cf.write_flo(tmp_path / "w.flo", flow_field(1), valid=want)
    g2, v2 = cf.read_flo(tmp_path / "w.flo")
    assert np.array_equal(v2, want) and np.array_equal(g2[want], flow_field(1)[want])


def test_kitti_samples_and_validity(tmp_path):
    flow, valid = cf.read_kitti_flow(DATA / "kitti" / "01" / "000001.png")
    assert flow.shape == (H, W, 2) and flow.dtype == np.float32 and valid.all()
    assert np.array_equal(flow, flow_field(1))
    flow, valid = cf.read_kitti_flow(DATA / "kitti" / "01" / "000002.png")
    assert np.array_equal(valid, np.broadcast_to(np.arange(W) >= 4, (H, W)))
    assert np.array_equal(flow[:, 4:], flow_field(2)[:, 4:]) and not flow[:, :4].any()
    # our writer reproduces both files' pixels
    cf.write_kitti_flow(tmp_path / "k.png", flow, valid)
    a = cv2.imread(str(tmp_path / "k.png"), cv2.IMREAD_UNCHANGED)
    assert a.dtype == np.uint16
    assert np.array_equal(a, cv2.imread(str(DATA / "kitti/01/000002.png"), cv2.IMREAD_UNCHANGED))
    cf.write_kitti_flow(tmp_path / "k1.png", flow_field(1))
    assert np.array_equal(cv2.imread(str(tmp_path / "k1.png"), cv2.IMREAD_UNCHANGED),
                          cv2.imread(str(DATA / "kitti/01/000001.png"), cv2.IMREAD_UNCHANGED))
    # 1/64 pixel steps, truncated as RAFT's astype(uint16)
    cf.write_kitti_flow(tmp_path / "q.png", np.array([[[0.3, -0.3]]], np.float32))
    q, _ = cf.read_kitti_flow(tmp_path / "q.png")
    assert q[0, 0].tolist() == [19 / 64, -20 / 64]
    nan = flow_field(1)
    nan[0, 0] = np.nan
    cf.write_kitti_flow(tmp_path / "n.png", nan, np.arange(W)[None, :].repeat(H, 0) > 0)  # NaN where invalid: fine
    assert cf.read_kitti_flow(tmp_path / "n.png")[0][0, 0].tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match="non-finite flow at valid pixels"):
        cf.write_kitti_flow(tmp_path / "n.png", nan)
    cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ArtifactError, match="eight.png: a KITTI flow PNG is 16-bit"):
        cf.read_kitti_flow(tmp_path / "eight.png")


def test_check_flow_padding_size_and_non_finite():
    flow, valid = cf.read_flo(DATA / "raft_padded" / "01" / "000001.flo")
    assert flow.shape == (16, 24, 2) and cf.raft_padded_shape(H, W) == (16, 24)
    with pytest.raises(ArtifactError, match=r"000001.flo: flow is 16x24 .* images are 12x20: it is padded to "
                                            r"multiples of 8 by RAFT's InputPadder.*'kitti' mode: 4 rows at the "
                                            r"bottom.*padder.unpad"):
        cf.check_flow(flow, valid, (H, W), DATA / "raft_padded" / "01" / "000001.flo")
    with pytest.raises(ArtifactError, match=r"x.flo: flow is 16x24 \(H x W\) but the images are 12x30$"):
        cf.check_flow(flow, valid, (12, 30), "x.flo")  # 12x30 pads to 16x32: not a padding
    good, gvalid = cf.read_flo(DATA / "raft" / "01" / "000001.flo")
    cf.check_flow(good, gvalid, (H, W), "ok.flo")
    with pytest.raises(ArtifactError, match="flow is 12x20 .* images are 13x20$"):
        cf.check_flow(good, gvalid, (13, 20), "x.flo")
    good = good.copy()
    good[2, 3, 0] = np.inf
    with pytest.raises(ArtifactError, match=r"nan.flo: 1 valid pixels with non-finite flow \(first at row 2, col"):
        cf.check_flow(good, gvalid, (H, W), "nan.flo")
    gvalid = gvalid.copy()
    gvalid[2, 3] = False
    cf.check_flow(good, gvalid, (H, W), "ok.flo")  # non-finite where invalid: fine
    with pytest.raises(ArtifactError, match="validity is"):
        cf.check_flow(good, gvalid[:-1], (H, W), "x.flo")
    with pytest.raises(ArtifactError, match=r"\(H, W, 2\)"):
        cf.check_flow(good[..., :1], gvalid, (H, W), "x.flo")


def test_read_flow_dispatches_by_suffix(tmp_path):
    f, v = cf.read_flow(DATA / "raft" / "01" / "000001.flo")
    assert np.array_equal(f, flow_field(1)) and v.all()
    f, v = cf.read_flow(DATA / "kitti" / "01" / "000002.png")
    assert not v[:, :4].any() and v[:, 4:].all()
    valid = np.ones((H, W), bool)
    valid[0, 0] = False
    write_exr(tmp_path / "f.exr", np.dstack([flow_field(1), valid.astype(np.float32)]), ("X", "Y", "valid"))
    f, v = cf.read_flow(tmp_path / "f.exr")
    assert np.array_equal(f, flow_field(1)) and np.array_equal(v, valid)
    with pytest.raises(ArtifactError, match=r"x.npy: unknown flow file suffix '.npy'"):
        cf.read_flow(tmp_path / "x.npy")
