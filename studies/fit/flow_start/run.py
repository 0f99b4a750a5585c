"""Runnable only at git 5d00caa: it calls the old anidress_core.fit.sequence.make_problem, which the fit's one term protocol (issue 48 item 2) replaced.

Probe: L_flow for the start only. Each frame t > 0 starts from frame t-1's result moved by the flow alignment (as in
the pipeline) and is then fitted with the pipeline's loss without L_flow, so the frame's minimum is the image terms'
and L_prior's, not that of L_flow's targets carried from the previous result (studies/fit section 22: from the rig
floor 1.76x without L_flow, 2.43x with it). Registers ``flow_start_only`` (the pipeline, window off: the window's
coupled L_flow is the term left out) and runs the maintained benchmark with every fit in the process built that way
(``anidress_core.fit.sequence.make_problem`` gets no flow targets), so pass that method alone. E.g.

    PYTHONPATH=. .venv/bin/python studies/fit/flow_start/run.py --suite <half of config/fit_suite.yaml> \\
        --views 8 --methods flow_start_only --no-sim --threads 1 --runs /tmp/flow_start --out /tmp/flow_start
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import sequence as SEQ  # noqa: E402
from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

V.VARIANTS["flow_start_only"] = V.Variant(
    "probe: the pipeline with L_flow used only by the flow alignment that starts each frame, not in the frame's loss; "
    "window off (the weights line still lists L_flow's weight, which the alignment's gate reads)",
    lambda c: c.replace(window=0))
_make_problem = SEQ.make_problem


def without_flow(rig, views, cues, flow, cfg, *args, **kwargs):
    """make_problem with no flow targets: L_flow off in the frame's loss."""
    return _make_problem(rig, views, cues, None, cfg, *args, **kwargs)


if __name__ == "__main__":
    methods = [sys.argv[i + 1] for i, a in enumerate(sys.argv[:-1]) if a == "--methods"]
    if methods != ["flow_start_only"]:
        raise SystemExit("run.py: pass --methods flow_start_only alone (every fit in this process is built without "
                         "L_flow)")
    SEQ.make_problem = without_flow
    bench_fit.PROG = "PYTHONPATH=. .venv/bin/python studies/fit/flow_start/run.py"
    bench_fit.main()
