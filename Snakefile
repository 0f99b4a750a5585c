# AniDress pipeline. Stages live in workflow/rules/*.smk; see README.md and DESIGN.md.
include: "workflow/rules/common.smk"
# input functions and settings of the rules, by stage (functions only: every rule file may use them)
include: "workflow/rules/helpers/scene_files.smk"
include: "workflow/rules/helpers/undistort.smk"
include: "workflow/rules/helpers/cues.smk"
include: "workflow/rules/helpers/body.smk"
include: "workflow/rules/helpers/fit.smk"
include: "workflow/rules/helpers/field.smk"
include: "workflow/rules/helpers/evaluate.smk"
include: "workflow/rules/helpers/report.smk"
include: "workflow/rules/scene_files.smk"  # a captured scene's files as rule inputs
include: "workflow/rules/synth.smk"
include: "workflow/rules/validate.smk"
include: "workflow/rules/undistort.smk"
include: "workflow/rules/sim.smk"
include: "workflow/rules/rig.smk"
include: "workflow/rules/cues.smk"
include: "workflow/rules/refine_body.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/field.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"  # after the stages: its input is everything above
include: "workflow/rules/bench.smk"


rule all:
    input:
        get_final_outputs(),
        "results/report.html",
