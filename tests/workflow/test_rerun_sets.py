"""Exact rerun sets (DESIGN.md §1): a setting reruns the stage whose params hold it and what depends on
it, nothing upstream. Against the tiny run built once (conftest.py), each case changes one value of one
config section (each stage's section, each part of a scene section) and reads the jobs of
``snakemake -n`` with the rerun triggers of profiles/default (params, input, mtime; not
code / software-env, nothing changes there)."""
import copy
import re

import pytest

from tests.workflow.tiny import RERUN_TRIGGERS, TINY, job_counts, snakemake

# every job of the garment scene (tinyskirt: one training sequence `walk`, library motion `sway`,
# variants full + body_only) / of the tight scene (tiny: train `walk`, novel pose `jump`, variant full)
SKIRT_ALL = {"synth": 1, "validate_scene": 1, "template": 1, "motions": 2, "simulate": 2, "simulate_ensemble": 1,
             "rig": 1, "masks": 1,
             "flows": 1, "normals": 1, "fit": 1, "fit_eval": 1, "train_field": 2, "render_novel_view": 2,
             "render_library": 2, "evaluate_field": 2, "report": 1, "all": 1}
TIGHT_ALL = {"synth": 1, "validate_scene": 1, "masks": 1, "train_field": 1, "render_novel_view": 1,
             "render_novel_pose": 1, "evaluate_field": 1, "report": 1, "all": 1}
# the garment poses of tinyskirt/walk and what reads them (the `full` field; body_only does not)
FIT_DOWN = {"fit": 1, "fit_eval": 1, "train_field": 1, "render_novel_view": 1, "render_library": 1,
            "evaluate_field": 1, "report": 1, "all": 1}
# every field of both scenes and what renders / evaluates them
FIELDS_DOWN = {"train_field": 3, "render_novel_view": 3, "render_novel_pose": 1, "render_library": 2,
               "evaluate_field": 3, "report": 1, "all": 1}


def _set(path: str, value):
    """A change of TINY: the value at ``path`` (keys and list indices separated by '/'), created if absent."""
    def change(cfg):
        *parents, last = path.split("/")
        node = cfg
        for k in parents:
            node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return change


# (config path, new value, the rules whose params hold it, the jobs a rerun plans: {rule: count})
CASES = [
    # the parts of a scene section: its data (rule synth) and its fit overrides (rule fit)
    ("scenes/tinyskirt/sequences/0/frames", 5, {"synth"}, SKIRT_ALL),
    ("scenes/tiny/cameras/vfov_deg", 36.0, {"synth"}, TIGHT_ALL),
    ("scenes/tinyskirt/body/height_m", 1.65, {"synth"}, SKIRT_ALL),
    ("scenes/tinyskirt/garment/texture", "plaid", {"synth"}, SKIRT_ALL),
    ("scenes/tiny/render/noise_std", 0.01, {"synth"}, TIGHT_ALL),
    ("scenes/tinyskirt/predicted_normals/blur_px", 1.0, {"synth"}, SKIRT_ALL),
    ("scenes/tinyskirt/fit/anchor_reference", "texture", {"fit"}, FIT_DOWN),
    ("scenes/tiny/fit/anchor_reference", "texture", set(), {}),  # a tight scene has no fit
    # the stages' sections
    ("template/vertices", 500, {"template"},
     {"template": 1, "simulate": 2, "simulate_ensemble": 1, "rig": 1, "masks": 1, "flows": 1, "normals": 1, "fit": 1,
      "fit_eval": 1, "train_field": 2,
      "render_novel_view": 2, "render_library": 2, "evaluate_field": 2, "report": 1, "all": 1}),
    ("simulate/cloth/damping", 0.6, {"simulate", "simulate_ensemble"},
     {"simulate": 2, "simulate_ensemble": 1, "rig": 1, **FIT_DOWN}),
    ("simulate/ensemble_bend_stiffness", [1.0e-4], {"simulate_ensemble"}, {"simulate_ensemble": 1, **FIT_DOWN}),
    ("simulate/library_frames", 6, {"motions"},  # the library motion only, and the two renders of it
     {"motions": 1, "simulate": 1, "rig": 1, **FIT_DOWN, "render_library": 2}),
    ("rig/iters", 8, {"rig"}, {"rig": 1, **FIT_DOWN}),
    ("cues/masks/fg_threshold", 0.1, {"masks"},
     {"masks": 2, "flows": 1, "fit": 1, "fit_eval": 1, **FIELDS_DOWN}),
    ("cues/flows/margin_px", 12, {"flows"}, {"flows": 1, **FIT_DOWN}),
    ("cues/normals", "off", {"normals", "fit"}, {"normals": 1, **FIT_DOWN}),  # fit: the normals folder, now none
    ("fit/max_iters", 4, {"fit"}, FIT_DOWN),
    ("fit/eval/samples", 10000, {"fit_eval"}, {"fit_eval": 1, "report": 1, "all": 1}),
    ("field/train/steps", 18, {"train_field"}, FIELDS_DOWN),
    ("field/train/checkpoint_every", 5, set(), {}),  # a resumed training ends with the same field
    ("field/sampler/body_only_garment_dilate_m", 0.1, {"train_field"},
     {"train_field": 1, "render_novel_view": 1, "render_library": 1, "evaluate_field": 1, "report": 1, "all": 1}),
    ("field/render/frame_stride", 1, {"render_novel_view", "render_novel_pose"},
     {"render_novel_view": 3, "render_novel_pose": 1, "evaluate_field": 3, "report": 1, "all": 1}),
    ("field/render/library_frame_stride", 1, {"render_library"}, {"render_library": 2, "report": 1, "all": 1}),
    ("metrics/box_pad_m", 0.1, {"evaluate_field"}, {"evaluate_field": 3, "report": 1, "all": 1}),
    ("refine_body/method", "adam", set(), {}),  # refine_body is off (the poses are exact): nothing reads it
]


@pytest.fixture(scope="module")
def upstream(tiny_run):
    """{rule: every rule it depends on, directly or not}, from ``snakemake --rulegraph`` of the tiny run."""
    res = snakemake(tiny_run, "--rulegraph")
    assert res.returncode == 0, res.stderr[-2000:]
    names = dict(re.findall(r"^\s*(\d+)\[label = \"(\w+)\"", res.stdout, re.M))
    parents: dict[str, set[str]] = {n: set() for n in names.values()}
    for a, b in re.findall(r"^\s*(\d+) -> (\d+)", res.stdout, re.M):
        parents[names[b]].add(names[a])
    assert {"synth", "simulate", "fit", "train_field", "report"} <= set(parents), sorted(parents)

    def ancestors(rule):
        out, todo = set(), [rule]
        while todo:
            for p in parents[todo.pop()] - out:
                out.add(p)
                todo.append(p)
        return out

    return {r: ancestors(r) for r in parents}


def _planned(workdir, cfg) -> tuple[dict[str, int], str]:
    """{rule: jobs} a run with ``cfg`` would start (tiny.yaml restored after), and Snakemake's output."""
    import yaml

    (workdir / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = snakemake(workdir, "-n", "--quiet", "rules", *RERUN_TRIGGERS)
    finally:
        (workdir / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    return job_counts(res), res.stdout + res.stderr


def test_the_tiny_run_is_up_to_date(tiny_run):
    jobs, out = _planned(tiny_run, copy.deepcopy(TINY))
    assert jobs == {} and "Nothing to be done" in out


@pytest.mark.parametrize("path, value, stage, expected", CASES, ids=[c[0] for c in CASES])
def test_one_setting_reruns_its_stage_and_what_depends_on_it(tiny_run, upstream, path, value, stage, expected):
    cfg = copy.deepcopy(TINY)
    _set(path, value)(cfg)
    assert cfg != TINY
    jobs, out = _planned(tiny_run, cfg)
    # 1. nothing upstream of the stage whose params hold the setting
    above = set().union(*(upstream[r] for r in stage)) - stage if stage else set()
    assert not above & set(jobs), f"{path}: upstream rules {sorted(above & set(jobs))} rerun"
    # 2. the stage itself, and (3.) exactly what depends on it
    assert stage <= set(jobs), f"{path}: {sorted(stage - set(jobs))} does not rerun"
    assert jobs == expected, out[-3000:]
    if not expected:
        assert "Nothing to be done" in out
    else:  # the stage reruns for its params (Snakemake names the first reason: a rule of the stage below
        # another one reruns for its input), the rest for their updated inputs
        first = sorted(r for r in stage if not upstream[r] & stage)
        assert re.search(r"params have changed since last execution:\s*\n\s*(.+)", out).group(1).split(", ") == first
