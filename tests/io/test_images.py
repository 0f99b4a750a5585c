"""Where a frame's image file is, and image headers without decoding (anidress_core.io.images)."""
import os

import cv2
import numpy as np
import pytest

from anidress_core.io import files
from anidress_core.io.files import ArtifactError
from anidress_core.io.images import (check_exr_magic, frame_file, frame_files, image_path, image_size_from_header,
                                     plate_path)


def test_image_headers(tmp_path):
    img = (np.random.default_rng(1).random((20, 30, 3)) * 255).astype(np.uint8)
    for ext in (".png", ".jpg"):
        p = tmp_path / f"a{ext}"
        cv2.imwrite(str(p), img)
        assert image_size_from_header(p) == (20, 30)
    p = tmp_path / "b.jpg"
    p.write_bytes((tmp_path / "a.jpg").read_bytes()[:-100])
    with pytest.raises(ArtifactError, match="truncated JPEG"):
        image_size_from_header(p)
    (tmp_path / "e.png").write_bytes(b"")
    with pytest.raises(ArtifactError, match=r"e\.png: unreadable image: the file is empty"):
        image_size_from_header(tmp_path / "e.png")
    p = tmp_path / "c.png"
    p.write_bytes((tmp_path / "a.png").read_bytes()[:-12])
    with pytest.raises(ArtifactError, match=r"c\.png: truncated or corrupt PNG"):
        image_size_from_header(p)


def test_exr_magic(tmp_path):
    files.write_exr(tmp_path / "n.exr", np.zeros((2, 3, 3), np.float32))
    check_exr_magic(tmp_path / "n.exr")
    (tmp_path / "x.exr").write_bytes(b"PNG?")
    with pytest.raises(ArtifactError, match=r"x\.exr: not an OpenEXR file"):
        check_exr_magic(tmp_path / "x.exr")


def test_frame_files_take_any_padding_and_letter_case(tmp_path):
    cam = tmp_path / "images" / "3"
    cam.mkdir(parents=True)
    for name in ("000000.png", "1.JPG", "00002.jpeg", "000003.Jpg", "notes.txt", "4a.png", "000005.exr"):
        (cam / name).write_bytes(b"x")
    assert {f: p.name for f, p in frame_files(cam).items()} == {0: "000000.png", 1: "1.JPG", 2: "00002.jpeg",
                                                                3: "000003.Jpg"}
    assert [image_path(tmp_path, "3", f).name for f in range(4)] == ["000000.png", "1.JPG", "00002.jpeg", "000003.Jpg"]
    assert frame_file(cam, 1) == cam / "1.JPG"
    # a frame that is not there: the padded .png path, whose reader names the missing file
    assert image_path(tmp_path, "3", 7) == cam / "000007.png"
    assert frame_files(tmp_path / "nothing") == {} and frame_file(tmp_path / "nothing", 0).name == "000000.png"
    # the same frame twice (validate_scene refuses it): .png before .jpg before .jpeg
    (cam / "01.png").write_bytes(b"x")
    assert frame_file(cam, 1) == cam / "01.png"


def test_frame_files_see_a_file_added_later(tmp_path):
    cam = tmp_path / "c"
    cam.mkdir()
    (cam / "7.jpg").write_bytes(b"x")
    assert set(frame_files(cam)) == {7}
    (cam / "8.JPEG").write_bytes(b"x")
    st = cam.stat()
    os.utime(cam, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # a coarse clock: the folder's mtime moves
    assert set(frame_files(cam)) == {7, 8} and frame_file(cam, 8).name == "8.JPEG"


def test_plate_path_takes_any_image_extension(tmp_path):
    bg = tmp_path / "backgrounds"
    bg.mkdir()
    (bg / "01.JPG").write_bytes(b"x")
    (bg / "02.png").write_bytes(b"x")
    (bg / "02.jpg").write_bytes(b"x")
    (bg / "03.txt").write_bytes(b"x")
    assert plate_path(tmp_path, "01").name == "01.JPG" and plate_path(tmp_path, "02").name == "02.png"
    assert plate_path(tmp_path, "03") == bg / "03.png" and plate_path(tmp_path / "x", "01").name == "01.png"
