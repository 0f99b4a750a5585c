# `snakemake --cores all bench`: run-time-vs-error sweeps (issue 8 §2) on the first
# garment scene of run_scenes, after the pipeline has built it. No output file on purpose:
# a benchmark runs whenever it is asked for. Runs `python -m benchmarks.bench_tradeoffs`, which
# writes benchmarks/tradeoffs.{csv,md}; the sweeps run with the effective config (config.yaml +
# any --configfile / --config).

BENCH_SCENE = next((s for s in SCENES if has_garment(s)), None)


rule bench:
    input:
        get_final_outputs() if BENCH_SCENE else [],
    log:
        "logs/bench.log",
    params:
        scene=BENCH_SCENE,
    threads: 2  # the sweeps run torch on 2 threads (a fixed count: other verbs need no --cores)
    run:
        import sys

        import yaml

        if params.scene is None:
            raise WorkflowError("bench: no garment scene in run_scenes to sweep")
        cfg_path = "benchmarks/runs/tradeoffs/config.yaml"
        os.makedirs(os.path.dirname(cfg_path), exist_ok=True)
        with open(cfg_path, "w") as fh:
            yaml.safe_dump(dict(config), fh)
        shell(f"{sys.executable} -m benchmarks.bench_tradeoffs --scene {params.scene} --config {cfg_path} > {log} 2>&1")
