"""The HTML report (anidress_core.stages.report): content from the pipeline's files, and a
real headless browser (Debian chromium) loading it without errors."""
import csv
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from anidress_core import plots
from anidress_core.io import files
from anidress_core.stages.report import collect_report, reference_label, run_report

REPO = Path(__file__).resolve().parents[1]
H = W = 24


def _tree(root: Path) -> dict:
    """A tiny but complete results tree: one skirt scene, one training + one novel-pose sequence."""
    rng = np.random.default_rng(0)
    cfg = {"run_scenes": ["sk", "tt"],
           "scenes": {"sk": {"kind": "skirt", "sequences": [{"name": "walk", "role": "train", "frames": 3},
                                                            {"name": "dance", "role": "novel_pose", "frames": 3}]},
                      "tt": {"kind": "tight", "sequences": [{"name": "walk", "role": "train", "frames": 3}]}}}
    data, res = root / "data" / "sk", root / "results" / "sk"
    (data).mkdir(parents=True)
    (data / "scene.yaml").write_text(yaml.safe_dump({"sequences": cfg["scenes"]["sk"]["sequences"]}))
    files.write_json(res / "scene_check.json", {"sequences": {"walk": {}, "dance": {}}, "cameras": {
        "train": ["01"], "test": ["02"]}, "image_size": [H, W], "checks": ["a", "b"], "warnings": []})
    for m in ("lib-twirl", "seq-walk"):
        files.save_npz(res / "sim" / f"{m}.npz", {"frames": np.zeros((3, 5, 3), np.float32),
                                                  "max_stretch": np.array([1.01, 1.02, 1.05]),
                                                  "max_penetration_m": np.zeros(3), "nan_count": np.zeros(3, int)},
                       meta={"wall_s": 1.5, "recoveries": []})
    files.save_npz(res / "rig.npz", {"rmse": np.float64(0.004), "rmse_per_sequence": np.array([0.003, 0.005]),
                                     "sequences": np.array(["lib-twirl", "seq-walk"]), "weights": np.ones((5, 2)) / 2,
                                     "rest": np.zeros((5, 3)), "faces": np.zeros((1, 3), int),
                                     "bone_centres": np.zeros((2, 3)), "transforms": np.tile(np.eye(4), (6, 2, 1, 1)),
                                     "offsets": np.array([0, 3, 6])},
                   meta={"wall_s": 2.0, "frames_decomposed": 6, "history_m": [0.01, 0.005, 0.004]})
    for seq in ("walk", "dance"):
        (res / seq).mkdir(parents=True)
        with open(res / seq / "fit_metrics.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["method", "frame", "vertex_rmse_m", "rig_floor_rmse_m", "chamfer_m", "normal_consistency",
                        "jitter_m", "gt_jitter_m", "accel_error_m", "loss", "loss_mask", "loss_normal", "loss_flow",
                        "iterations", "wall_s"])
            for meth, base in (("full", 0.005), ("no_flow", 0.007)):
                for f in range(3):
                    w.writerow([meth, f, base + 0.001 * f, 0.004, 0.003, 0.95, 0.001, 0.001, 0.0, 1, 1, 1, 1, 5, 0.5])
        files.save_npz(res / seq / "garment_poses.npz", {"curve": np.array([[3.0, 2.0, 1.0], [2.0, 1.5, np.nan],
                                                                             [1.0, 0.5, 0.4]])})
    # renders, images and masks of one novel-view and one novel-pose image
    for kind, seq, rel in (("novel_view", "walk", "novel_view"), ("novel_pose", "dance", "novel_pose/dance")):
        img = rng.random((H, W, 3)).astype(np.float32)
        files.write_png(data / seq / "images" / "02" / "000001.png", img)
        files.write_mask(data / seq / "gt" / "masks" / "02" / "000001.png", (rng.random((H, W)) > 0.5).astype(np.uint8))
        for v in ("full", "body_only"):
            d = res / "walk" / v / "renders" / rel
            files.write_json(d / "render.json", {"frames": [0, 1, 2], "cameras": ["02"], "background": [0, 0, 0]})
            files.write_png(d / "rgb" / "02" / "000001.png", np.clip(img + 0.05, 0, 1))
    for v, psnr in (("full", 27.5), ("body_only", 26.9)):
        files.write_json(res / "walk" / v / "metrics_summary.json", {
            "metrics": [{"kind": "novel_view", "sequence": "walk", "images": 3, "psnr_db": psnr + 1, "ssim": 0.9,
                         "iou": 0.95, "lpips": float("nan"), "dists": float("nan")},
                        {"kind": "novel_pose", "sequence": "dance", "images": 3, "psnr_db": psnr, "ssim": 0.88,
                         "iou": 0.93, "lpips": float("nan"), "dists": float("nan")}],
            "lpips": "weights not found (test)", "dists": "weights not found (test)"})
    files.write_json(res / "walk" / "normals.json", {"skipped": True, "reason": "no normals shipped"})
    tsv = root / "benchmarks" / "runs" / "sk"
    (tsv / "simulate").mkdir(parents=True)
    for p, s in ((tsv / "rig.tsv", 12.0), (tsv / "simulate" / "lib-twirl.tsv", 30.0)):
        p.write_text("s\th:m:s\tmax_rss\tcpu_time\n" + f"{s}\t0:00:12\t512.0\t{s}\n")
    with open(root / "benchmarks" / "tradeoffs.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["stage", "knob", "value", "wall_s", "cpu_s", "error", "error_metric", "is_default"])
        for b, t, e in ((10, 2.0, 5.1), (25, 5.0, 2.2), (30, 6.0, 1.8)):
            w.writerow(["rig", "bones", b, t, 2 * t, e, "rig RMSE (mm)", int(b == 25)])
    with open(root / "benchmarks" / "rig.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "vertices", "frames", "bones_asked", "rmse_m"])
        w.writerow(["anidress_core.rig.ssdr", 50, 4, 25, 0.002])  # not a sweep row: not charted
        for b, e in ((10, 0.005), (25, 0.0022)):
            w.writerow(["anidress_core.rig.ssdr (bones sweep)", 50, 4, b, e])
    return cfg


REFS = {"tradeoffs": "benchmarks/tradeoffs.csv", "rig_sweep": "benchmarks/rig.csv"}


def test_report_content(tmp_path):
    cfg = _tree(tmp_path)
    d = collect_report(cfg, tmp_path, references=REFS)
    sk = d["scenes"][0]
    assert sk["rig"]["rmse_mm"] == pytest.approx(4.0) and len(sk["sims"]) == 2
    fit = sk["sequences"][0]["fit"]["table"]
    assert {r["method"] for r in fit} == {"full", "no_flow"}
    assert fit[0]["rmse_mm"]["mean"] == pytest.approx(6.0) and fit[0]["rmse_mm"]["worst"] == pytest.approx(7.0)
    grids = sk["sequences"][0]["field"]["grids"]
    assert [g["kind"] for g in grids] == ["novel_view", "novel_pose"] and len(grids[0]["tiles"]) == 4
    reasons = " ".join(k["reason"] for k in d["skipped"])
    assert "tight-clothed" in reasons and "normal loss weight 0" in reasons and "unavailable" in reasons
    assert d["tradeoffs"]["verdicts"] == [{"stage": "rig", "metric": "rig RMSE (mm)", "default": "bones=25",
                                           "on_front": True, "dominated_by": []}]
    out = tmp_path / "report.html"
    run_report(cfg, out, tmp_path, references=REFS)
    html = out.read_text()
    assert "27.50" in html and "26.90" in html and "28.50" in html  # novel pose / view PSNR of both variants
    assert html.count("<table") >= 6 and html.count("<svg") >= 5 and html.count("data:image/png;base64") == 8
    # the committed tables are labelled as reference figures (tmp_path is no git checkout: said so)
    for name in ("benchmarks/tradeoffs.csv", "benchmarks/rig.csv"):
        label = f"reference figures in {name} (not in a git checkout: commit and date unknown)"
        assert html.count(label) == 1, label
    assert d["rig_sweep"]["label"].startswith("reference figures in benchmarks/rig.csv")
    assert "nothing on this page is typed in" not in html and "reference figures this run did" in html
    # older summaries without the region figures: n/a, and the note says so
    assert all(h in html for h in ("PSNR box (dB)", "PSNR subject", "PSNR garment", "PSNR body"))
    assert "regions from the masks: n/a" in html and "<td>n/a</td><td>n/a</td><td>n/a</td>" in html


def test_report_shows_the_region_psnrs(tmp_path):
    """metrics_summary.json with evaluate_field's pooled region figures: beside the box PSNR, +inf as inf; the note
    names the masks of the regions."""
    cfg = _tree(tmp_path)
    p = tmp_path / "results" / "sk" / "walk" / "full" / "metrics_summary.json"
    summ = files.read_json(p)
    for m, vals in zip(summ["metrics"], ((25.125, 21.25, float("inf")), (24.375, 19.5, float("nan")))):
        m.update(psnr_subject_db=vals[0], psnr_garment_db=vals[1], psnr_body_db=vals[2])
        m["region_masks"] = ["gt/masks"] if m["kind"] == "novel_view" else ["gt/masks", "subject only"]
    files.write_json(p, summ)
    out = tmp_path / "report.html"
    d = run_report(cfg, out, tmp_path)
    assert d["scenes"][0]["sequences"][0]["field"]["region_masks"] == ["gt/masks", "subject only"]
    html = out.read_text()
    assert "<td>28.50</td><td>25.12</td><td>21.25</td><td>inf</td>" in html  # full, novel view: box, subject, ...
    assert "<td>27.50</td><td>24.38</td><td>19.50</td><td>n/a</td>" in html
    assert "<td>27.90</td><td>n/a</td><td>n/a</td><td>n/a</td>" in html  # body_only: an older summary
    assert 'regions from the masks: gt/masks, subject only ("subject only": masks without' in html


def test_report_shows_no_reference_table_unless_passed(tmp_path):
    cfg = _tree(tmp_path)  # benchmarks/tradeoffs.csv and rig.csv exist under the root, but are not passed
    out = tmp_path / "report.html"
    d = run_report(cfg, out, tmp_path)
    html = out.read_text()
    assert d["tradeoffs"]["available"] is False and d["rig_sweep"] is None
    assert "reference figures in" not in html and "reference figures committed" not in html
    assert "No reference figures from earlier runs are shown" in html
    assert "Not shown: benchmarks/tradeoffs.csv was not given to the report" in html
    with pytest.raises(ValueError, match="unknown keys"):
        collect_report(cfg, tmp_path, references={"fit": "benchmarks/fit.csv"})


def test_reference_label_reads_commit_and_date_from_git(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git not installed")
    cfg = _tree(tmp_path)
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t", "GIT_COMMITTER_DATE": "2026-11-30T12:00:00+00:00",
           "GIT_AUTHOR_DATE": "2026-11-30T12:00:00+00:00"}

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=tmp_path, env=env, check=True, capture_output=True,
                              text=True).stdout.strip()

    git("init", "-q")
    path = tmp_path / "benchmarks" / "tradeoffs.csv"
    assert label_of(path) == "reference figures in benchmarks/tradeoffs.csv (not committed: commit and date unknown)"
    git("add", "benchmarks/tradeoffs.csv")
    git("commit", "-q", "-m", "sweeps")
    sha = git("rev-parse", "--short", "HEAD")
    assert label_of(path) == f"reference figures committed in benchmarks/tradeoffs.csv (commit {sha}, 2026-11-30)"
    out = tmp_path / "report.html"
    run_report(cfg, out, tmp_path, references={"tradeoffs": path})  # an absolute path: shown relative to root
    assert f"reference figures committed in benchmarks/tradeoffs.csv (commit {sha}, 2026-11-30)" in out.read_text()
    path.write_text(path.read_text() + "rig,bones,40,7.0,14.0,1.7,rig RMSE (mm),0\n")
    assert label_of(path) == (f"reference figures in benchmarks/tradeoffs.csv (changed since its last commit "
                              f"{sha}, 2026-11-30: not the committed figures)")


def label_of(path: Path) -> str:
    return reference_label(path, "benchmarks/tradeoffs.csv")


def test_pareto_front_and_empty_charts():
    pts = [(1, 5), (2, 3), (3, 3), (4, 1), (5, 2)]
    assert plots.pareto_front(pts) == [0, 1, 3]
    assert "no data" in plots.line_chart([("a", [1], [float("nan")])], "t", "x", "y")
    assert "<path" in plots.scatter_chart([{"x": 1, "y": 2}, {"x": 2, "y": 1}], "t", "x", "y")


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def test_report_loads_in_a_headless_browser(tmp_path):
    exe = _chromium()
    if exe is None:
        if os.environ.get("ANIDRESS_NO_BROWSER") == "1":
            pytest.skip("ANIDRESS_NO_BROWSER=1: browser check disabled explicitly")
        if os.environ.get("CI", "").lower() in ("1", "true"):  # .ci/run installs chromium: its absence is a failure
            pytest.fail("CI: Debian chromium not found (.ci/run installs it with root and apt)")
        pytest.skip("Debian chromium not found, the report is not loaded in a browser: `apt-get install chromium` "
                    "to run this check (CI installs it and fails without it)")
    cfg = _tree(tmp_path)
    out = tmp_path / "report.html"
    run_report(cfg, out, tmp_path, references=REFS)
    with tempfile.TemporaryDirectory() as profile:
        res = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                              "--disable-background-networking", "--disable-component-update", "--disable-sync",
                              f"--user-data-dir={profile}", "--virtual-time-budget=5000", "--dump-dom",
                              out.resolve().as_uri()], capture_output=True, text=True, timeout=120)
    body = re.search(r"<body([^>]*)>", res.stdout)
    assert body, f"no DOM from chromium (rc {res.returncode}): {res.stderr[-1500:]}"
    attrs = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body.group(1)))
    assert attrs.get("loaded") == "1", attrs
    assert attrs["errors"] == "0", attrs.get("error-list")
    assert int(attrs["images"]) == 8 and attrs["images-ok"] == attrs["images"]
    assert int(attrs["tables"]) >= 6 and int(attrs["svgs"]) >= 5
    assert "Skipped and why" in res.stdout and "Ours w/o G" in res.stdout
