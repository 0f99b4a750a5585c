"""Probe: the joint window refinement (fit/window, anidress_core.fit.window) at other window lengths,
LM budgets, and chain budgets.

Registers ``window_<W>_<window_iters>`` (chain as the pipeline's) and ``window_<W>_<window_iters>_chain<k>``
(the chain's max_iters k) as loss variants and runs the maintained benchmark (benchmarks/bench_fit.py)
with its own arguments, e.g. on half of the tuning suite:

    .venv/bin/python studies/fit/window/run.py --suite config/fit_suite.yaml --views 8 \\
        --methods pipeline,window_5_3,window_10_5 --threads 1 --reuse --out /tmp/window
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

for W, iters, chain in ((5, 3, None), (10, 5, None), (5, 3, 3)):
    name = f"window_{W}_{iters}" + ("" if chain is None else f"_chain{chain}")
    V.VARIANTS[name] = V.Variant(
        f"the pipeline with every {W} chained frames refined jointly, at most {iters} evaluations"
        + ("" if chain is None else f", the chain at most {chain} evaluations per frame"),
        lambda c, W=W, iters=iters, chain=chain: c.replace(window=W, window_iters=iters,
                                                           **({} if chain is None else {"max_iters": chain})))

if __name__ == "__main__":
    bench_fit.PROG = ".venv/bin/python studies/fit/window/run.py"
    bench_fit.main()
