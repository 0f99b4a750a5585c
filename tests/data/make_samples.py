"""Writes the small capture samples under tests/data/ (run from the repository root:
``python tests/data/make_samples.py``). Every value is made up here (a seeded
generator): no licensed data. The layouts follow what the tools write:

* ``easymocap/<name>/<frame:06d>.json``: EasyMocap's ``write_smpl``
  (``easymocap/mytools/file_utils.py``: a JSON list of people, ``"id"`` then
  ``Rh``, ``Th``, ``poses``, ``handl``, ``handr``, ``expression``, ``shapes`` as
  ``[[...]]`` rows, numbers with ``%2.3f``; an empty frame is ``[\\n]``).
  ``smpl_v02``: ``SMPLModel(use_root_rot=False)``, poses of 69; ``smplh_v02``:
  ``SMPLHModel``, poses of 63 + 6 PCA coefficients per hand; ``smplx_v02``: 63 +
  hands + 10 expression coefficients; ``two_people``: two ids whose order swaps at
  frame 1, nobody at frame 2; ``bad_poses``: 70 numbers.
* ``easymocap_cams/intri.yml``, ``extri.yml``: OpenCV FileStorage YAML as
  EasyMocap's ``write_intri`` / ``write_extri`` write it, but with the camera names
  unquoted (``- 01``), as hand-edited files have them.
* ``amass/stageii_smplx.npz``: the keys of an AMASS SMPL-X stage-II file
  (MoSh++), including ``markers_latent_vids``, a dict stored as a pickled object
  array, and ``mocap_frame_rate``.
* ``zju/annots.npy``: ZJU-MoCap's ``annots.npy`` (``np.save`` of a dict, read with
  ``allow_pickle=True`` by neuralbody ``lib/datasets/light_stage``): ``cams`` with
  lists K (3, 3), D (5, 1), R (3, 3), T (3, 1) in millimetres; ``ims``: one
  ``{"ims": [path per camera]}`` per frame. ``zju/mask`` (0 / 255) and
  ``zju/mask_cihp`` (CIHP part labels) hold one 6x4 PNG each.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
rng = np.random.default_rng(2024)


def _row(a) -> str:
    return "[[" + ", ".join("%2.3f" % x for x in np.asarray(a, float).reshape(-1)) + "]]"


def write_smpl(path: Path, people: list[dict]) -> None:
    """EasyMocap write_smpl's text layout (keys in its order, %2.3f numbers)."""
    keys = ["Rh", "Th", "poses", "handl", "handr", "expression", "shapes"]
    out = ["[\n"]
    for i, person in enumerate(people):
        out.append("    {\n")
        lines = [f'        "id": {person["id"]}'] + [f'        "{k}": {_row(person[k])}' for k in keys if k in person]
        out.append(",\n".join(lines) + "\n")
        out.append("    }" + (",\n" if i != len(people) - 1 else "\n"))
    out.append("]\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(out))


def person(pid: int, n_poses: int, th, **extra) -> dict:
    return {"id": pid, "Rh": rng.normal(0, 0.3, 3), "Th": np.asarray(th, float),
            "poses": rng.normal(0, 0.2, n_poses), "shapes": rng.normal(0, 1, 10), **extra}


def easymocap() -> None:
    d = ROOT / "easymocap"
    for f in range(2):
        write_smpl(d / "smpl_v02" / f"{f:06d}.json", [person(0, 69, [0.1 * f, 0.0, 0.9])])
    write_smpl(d / "smplh_v02" / "000000.json",
               [person(0, 63, [0.0, 0.1, 0.9], handl=rng.normal(0, 1, 6), handr=rng.normal(0, 1, 6))])
    write_smpl(d / "smplx_v02" / "000000.json",
               [person(0, 63, [0.0, 0.1, 0.9], handl=rng.normal(0, 1, 12), handr=rng.normal(0, 1, 12),
                       expression=rng.normal(0, 1, 10))])
    a0, b0 = person(0, 69, [0.0, 0.0, 0.9]), person(1, 69, [5.0, 0.0, 0.9])
    a1, b1 = person(0, 69, [0.2, 0.0, 0.9]), person(1, 69, [5.2, 0.0, 0.9])
    a3, b3 = person(0, 69, [0.6, 0.0, 0.9]), person(1, 69, [5.6, 0.0, 0.9])
    write_smpl(d / "two_people" / "000000.json", [a0, b0])
    write_smpl(d / "two_people" / "000001.json", [b1, a1])  # the order changes between frames
    write_smpl(d / "two_people" / "000002.json", [])  # nobody detected
    write_smpl(d / "two_people" / "000003.json", [a3, b3])
    write_smpl(d / "bad_poses" / "000000.json", [person(0, 70, [0.0, 0.0, 0.9])])


def _mat(key: str, a, rows: int, cols: int) -> list[str]:
    data = ", ".join("%.6f" % x for x in np.asarray(a, float).reshape(-1))
    return [f"{key}: !!opencv-matrix", f"  rows: {rows}", f"  cols: {cols}", "  dt: d", f"  data: [{data}]"]


def easymocap_cams() -> None:
    d = ROOT / "easymocap_cams"
    d.mkdir(parents=True, exist_ok=True)
    names = ["01", "02", "03"]
    intri = ["%YAML:1.0", "---", "names:"] + [f"  - {n}" for n in names]  # unquoted: YAML numbers
    extri = list(intri)
    for i, n in enumerate(names):
        K = [[500.0 + i, 0.0, 320.0], [0.0, 500.0 + i, 240.0], [0.0, 0.0, 1.0]]
        intri += _mat(f"K_{n}", K, 3, 3) + _mat(f"dist_{n}", np.zeros(5), 1, 5)
        ang = 2 * np.pi * i / len(names)
        R = cv2.Rodrigues(np.array([0.0, ang, 0.0]))[0]
        T = np.array([0.0, 0.0, 3.0])
        extri += _mat(f"R_{n}", cv2.Rodrigues(R)[0], 3, 1) + _mat(f"Rot_{n}", R, 3, 3) + _mat(f"T_{n}", T, 3, 1)
    (d / "intri.yml").write_bytes("".join(line + "\r\n" for line in intri).encode())
    (d / "extri.yml").write_bytes("".join(line + "\r\n" for line in extri).encode())


def amass() -> None:
    T = 4
    d = ROOT / "amass"
    d.mkdir(parents=True, exist_ok=True)
    root, body = rng.normal(0, 0.2, (T, 3)), rng.normal(0, 0.2, (T, 63))
    jaw, eye, hand = rng.normal(0, 0.1, (T, 3)), rng.normal(0, 0.1, (T, 6)), rng.normal(0, 0.2, (T, 90))
    vids = np.empty((), dtype=object)
    vids[()] = {"C7": 3470, "CLAV": 3171, "LFHD": 8981}  # marker name -> vertex id, a pickled dict
    np.savez(d / "stageii_smplx.npz",
             gender=np.array("female"), surface_model_type=np.array("smplx"),
             mocap_frame_rate=np.array(120.0), mocap_time_length=np.array(T / 120.0),
             markers_latent=rng.normal(0, 0.3, (3, 3)), latent_labels=np.array(["C7", "CLAV", "LFHD"]),
             markers_latent_vids=vids, trans=rng.normal(0, 0.5, (T, 3)),
             poses=np.concatenate([root, body, jaw, eye, hand], axis=1), betas=rng.normal(0, 1, 16),
             num_betas=np.array(16), root_orient=root, pose_body=body, pose_hand=hand, pose_jaw=jaw, pose_eye=eye)


def zju() -> None:
    d = ROOT / "zju"
    d.mkdir(parents=True, exist_ok=True)
    C, T = 2, 3
    cams = {"K": [], "D": [], "R": [], "T": []}
    for c in range(C):
        cams["K"].append(np.array([[1000.0 + c, 0.0, 511.5], [0.0, 1000.0 + c, 511.5], [0.0, 0.0, 1.0]]))
        cams["D"].append(np.array([[-0.1], [0.05], [0.001], [0.0], [0.0]]))
        cams["R"].append(cv2.Rodrigues(np.array([0.0, np.pi * c, 0.0]))[0])
        cams["T"].append(np.array([[10.0 * c], [-200.0], [3000.0]]))  # millimetres
    ims = [{"ims": [f"Camera_B{c + 1}/{t:06d}.jpg" for c in range(C)]} for t in range(T)]
    np.save(d / "annots.npy", {"cams": cams, "ims": ims}, allow_pickle=True)
    mask = np.zeros((6, 4), np.uint8)
    mask[1:5, 1:3] = 255
    cihp = np.zeros((6, 4), np.uint8)
    cihp[1, 1:3] = 13  # face
    cihp[2, 1:3] = 5  # upper clothes
    cihp[3, 1:3] = 6  # dress
    cihp[4, 1:3] = 12  # skirt
    cihp[5, 0] = 18  # a shoe outside mask/
    for sub, img in (("mask", mask), ("mask_cihp", cihp)):
        (d / sub / "Camera_B1").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(d / sub / "Camera_B1" / "000000.png"), img)


if __name__ == "__main__":
    easymocap()
    easymocap_cams()
    amass()
    zju()
