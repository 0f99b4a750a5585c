# Rules render_novel_view, render_novel_pose, render_library: images of a trained field.
from anidress_core.stages import setup_logging

log = setup_logging(snakemake.log[0])
try:
    import torch

    from anidress_core.stages.field import run_render
    from anidress_core.io.scene import read_scene

    torch.set_num_threads(snakemake.threads)
    p, inp, wc = snakemake.params, snakemake.input, snakemake.wildcards
    info = read_scene(inp.scene)
    common = dict(template_npz=inp.get("template"), rig_npz=inp.get("rig"),
                  frame_stride=p.field["render"]["library_frame_stride" if p.kind == "library" else "frame_stride"],
                  device=p.field["device"], progress=False, undistorted_dir=inp.get("undistorted") or None,
                  body_dir=inp.get("body") or None)
    if p.kind == "novel_view":
        run_render(inp.field, inp.scene, snakemake.output[0], p.field, seq=wc.seq, cameras=info["cameras"]["test"],
                   garment_poses_npz=inp.get("poses"), **common)
    elif p.kind == "novel_pose":
        cams = info["cameras"]["train"] + info["cameras"]["test"]
        run_render(inp.field, inp.scene, snakemake.output[0], p.field, seq=wc.pose_seq, cameras=cams,
                   garment_poses_npz=inp.get("poses"), **common)
    else:
        run_render(inp.field, inp.scene, snakemake.output[0], p.field, cameras=info["cameras"]["test"],
                   library_motion_npz=inp.motion, library_name=wc.motion, **common)
except Exception:
    log.exception("render failed")
    raise
