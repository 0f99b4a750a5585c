# AniDress pipeline. Stages live in workflow/rules/*.smk; see README.md and DESIGN.md.
include: "workflow/rules/common.smk"
include: "workflow/rules/scene_files.smk"  # a captured scene's files as rule inputs
include: "workflow/rules/synth.smk"
include: "workflow/rules/validate.smk"
include: "workflow/rules/undistort.smk"  # before the stages: their input functions use undistorted_dir()
include: "workflow/rules/sim.smk"
include: "workflow/rules/rig.smk"
include: "workflow/rules/cues.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/field.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"  # after the stages: its input is everything above
include: "workflow/rules/bench.smk"


rule all:
    input:
        get_final_outputs(),
        "results/report.html",
