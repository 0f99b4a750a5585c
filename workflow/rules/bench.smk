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
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/bench.py"
