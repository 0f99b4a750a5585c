# Rule bench: the run-time-vs-error sweeps of benchmarks/bench_tradeoffs.py on params.scene, with the
# effective config (config.yaml + any --configfile / --config) written beside its results. A script (not
# a run: block) so that the rule's conda environment applies (`snakemake --sdm conda bench`).
import os
import subprocess
import sys

import yaml

if snakemake.params.scene is None:
    sys.exit("bench: no garment scene in run_scenes to sweep")
cfg_path = "benchmarks/runs/tradeoffs/config.yaml"
os.makedirs(os.path.dirname(cfg_path), exist_ok=True)
with open(cfg_path, "w") as fh:
    yaml.safe_dump(dict(snakemake.config), fh)
with open(snakemake.log[0], "w") as log:
    subprocess.run([sys.executable, "-m", "benchmarks.bench_tradeoffs", "--scene", snakemake.params.scene,
                    "--config", cfg_path], stdout=log, stderr=subprocess.STDOUT, check=True)
