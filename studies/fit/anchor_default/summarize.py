"""Summary of sweep.py's tables (several CSVs of bench_fit, e.g. the two halves of the tuning suite): per views and
method, the median and worst RMSE / rig floor over the scenes, the median per-scene ratio to ``--base``, on how many
scenes it is better than ``--base``, the Chamfer / floor median. Markdown on stdout.

    .venv/bin/python studies/fit/anchor_default/summarize.py studies/fit/anchor_default/sweep4_{a,b}.csv
"""
from __future__ import annotations

import argparse
import csv

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("csv", nargs="+")
    ap.add_argument("--base", default="pipeline")
    args = ap.parse_args()
    rows = [r for f in args.csv for r in csv.DictReader(open(f))]
    by: dict[tuple, dict] = {}
    for r in rows:
        by.setdefault((int(r["views"]), r["method"]), {})[r["scene"]] = r
    print("| views | method | scenes | RMSE / floor median | worst (scene) | median ratio to `%s` | better on | "
          "Chamfer / floor median |" % args.base)
    print("| ---: | --- | ---: | ---: | --- | ---: | ---: | ---: |")
    for (nv, m), per in sorted(by.items(), key=lambda kv: (-kv[0][0], kv[0][1] != args.base, kv[0][1])):
        base = by.get((nv, args.base), {})
        ratio = {s: float(r["rmse_over_floor"]) for s, r in per.items()}
        worst = max(ratio, key=ratio.get)
        common = sorted(set(per) & set(base))
        rel = [float(per[s]["vertex_rmse_m_mean"]) / float(base[s]["vertex_rmse_m_mean"]) for s in common]
        print(f"| {nv} | `{m}` | {len(per)} | {np.median(list(ratio.values())):.2f} | {ratio[worst]:.2f} ({worst}) | "
              f"{np.median(rel):.3f} | {sum(x < 1 for x in rel)} of {len(rel)} | "
              f"{np.median([float(r['chamfer_over_floor']) for r in per.values()]):.2f} |")


if __name__ == "__main__":
    main()
