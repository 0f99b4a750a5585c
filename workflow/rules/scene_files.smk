# The files of a captured scene as rule inputs (issue 24 item 6): an edit of walk/intri.yml, a smpl/*.json
# body file, an image or a shipped mask reruns rule validate_scene and the jobs that read that file, nothing
# else. (A folder input is compared by its own mtime, which an edit inside it does not change.)
#
#   scene_files -> results/{scene}/inputs/{part}.json   one per part of the scene: scene, body, garment, and
#                  <seq>/cameras, <seq>/smpl, <seq>/images, <seq>/masks, <seq>/masks_parsing, <seq>/normals,
#                  <seq>/flows, <seq>/backgrounds,
#                  <seq>/gt_masks; its inputs are the part's files one by one, it writes their list with
#                  size and mtime (a manifest: any change of a file changes it).
# validate_scene takes every manifest; a stage rule the manifests of the parts it reads (scene_inputs()),
# besides ancient(scene_check.json), which orders it after the validation without rerunning it when the
# validation reruns. Why manifests rather than the files as inputs of the stage rules: Snakemake 9.27 does
# not evaluate a job whose only link to a job that must rerun is an ancient() input (snakemake#4166: when
# validate_scene reruns, the jobs after it are skipped unless reached through another input), so a stage
# rule must learn of the edit through a job that is not after validate_scene. The remaining exposure of
# that bug: in a run where validate_scene reruns, a job whose only reason is a config or code change (and
# no edited file) is planned by the next run, not this one.
#
# Synthetic scenes: data/{scene} is rule synth's directory output, no file inside it can be an input
# (ChildIOException); their rules take the folder, and synth reruns when the scene's settings change.
# Captured scenes: the folder stays the rules' `scene` input (the scripts read it) but as ancient(): only
# the manifests count. The folder is listed once per Snakemake run (os.walk). Images, masks and normals
# are inputs file by file of their manifest job only, each file of one job. Measured (2 cores, dry run of
# an up-to-date run): a 4-camera capture with 3 frames 1.55 s, the same with 900 frames (14,435 files:
# images, masks, normals, gt masks) 2.7 s.


localrules: scene_files  # a listing of files: on the submitting host (SLURM profile: no job)


rule scene_files:
    input:
        lambda wc: scene_part_files(wc.scene, wc.part),
    output:
        "results/{scene}/inputs/{part}.json",
    log:
        "logs/{scene}/inputs/{part}.log",
    wildcard_constraints:
        scene="|".join(s for s, c in config["scenes"].items() if not c["synthetic"]) or "^$",
        part=_PART_NAMES,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/scene_files.py"
