"""Image headers without decoding (anidress_core.io.images)."""
import cv2
import numpy as np
import pytest

from anidress_core.io import files
from anidress_core.io.files import ArtifactError
from anidress_core.io.images import check_exr_magic, image_size_from_header


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
