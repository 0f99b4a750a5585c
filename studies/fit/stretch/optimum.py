"""Probe: where does the loss of variant OF (a variant of run.py, e.g. ``stretch_prior_3000``) hold the truth?
bench_fit's ``optimum`` row (every frame started from the rig floor) with that loss; its "As run" line names it.

    OF=stretch_prior_3000 PYTHONPATH=. .venv/bin/python studies/fit/stretch/optimum.py --suite <overlay> \\
        --methods optimum --views 8 --no-sim --threads 1 --runs /tmp/opt_3000 --out /tmp/opt_3000
"""
import os
import runpy
import sys
from pathlib import Path

runpy.run_path(str(Path(__file__).with_name("run.py")))  # registers the probe's variants
import benchmarks.bench_fit as B  # noqa: E402

B.OPTIMUM_OF = os.environ["OF"]
B.PROG = f"OF={B.OPTIMUM_OF} PYTHONPATH=. .venv/bin/python studies/fit/stretch/optimum.py"
B.main()
