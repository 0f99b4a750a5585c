# AniDress pipeline. Stages live in workflow/rules/*.smk; see README.md and DESIGN.md.
include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/sim.smk"


rule all:
    input:
        get_final_outputs(),
