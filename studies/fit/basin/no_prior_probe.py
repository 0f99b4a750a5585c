"""Probe: the loss's own minimum near the truth without L_prior (every frame started on the rig floor)."""
import sys
import benchmarks.bench_fit as B
B.OPTIMUM_OF = sys.argv[1]
sys.argv = ["bench_fit"] + sys.argv[2:]
B.main()
