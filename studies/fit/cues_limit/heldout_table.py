"""Section 22's table: RMSE over the rig floor per held-out scene, for several rows of bench_fit csvs, with the median,
the worst and the scenes whose drift is above issue 23's 1.3. Each argument is ``label=<csv>[+<csv>...]:<method>``.

    python studies/fit/cues_limit/heldout_table.py pipeline=benchmarks/fit.csv:pipeline \\
        exact=studies/fit/cues_limit/heldout_gt_cues_a.csv+studies/fit/cues_limit/heldout_gt_cues_b.csv:pipeline
"""
from __future__ import annotations

import csv
import statistics
import sys

DRIFT_TARGET = 1.3


def read(spec: str) -> tuple[str, dict]:
    """``label=<csv>[+<csv>]:<method>`` -> (label, {(scene, views): (rmse over floor, drift)})."""
    label, _, rest = spec.partition("=")
    paths, _, method = rest.rpartition(":")
    rows = {}
    for path in paths.split("+"):
        with open(path, newline="") as f:
            for r in csv.DictReader(f):
                if r["method"] == method:
                    rows[(r["scene"], r["views"])] = float(r["rmse_over_floor"]), float(r["drift"])
    if not rows:
        raise SystemExit(f"{spec}: no row of method {method!r} in {paths}")
    return label, rows


def main() -> None:
    cols = [read(a) for a in sys.argv[1:]]
    for views in sorted({k[1] for _, rows in cols for k in rows}, key=int, reverse=True):
        scenes = sorted({k[0] for _, rows in cols for k in rows if k[1] == views})
        print(f"\n| {views} views | " + " | ".join(label for label, _ in cols) + " |")
        print("| --- |" + " ---: |" * len(cols))
        for s in scenes:
            print(f"| {s} | " + " | ".join(f"{rows[(s, views)][0]:.2f}" if (s, views) in rows else "--"
                                           for _, rows in cols) + " |")
        for name, fn in (("median", statistics.median), ("worst", max)):
            vals = [[v[0] for k, v in rows.items() if k[1] == views] for _, rows in cols]
            print(f"| {name} | " + " | ".join(f"{fn(v):.2f}" if v else "--" for v in vals) + " |")
        print(f"| drift > {DRIFT_TARGET} | " + " | ".join(
            f"{sum(v[1] > DRIFT_TARGET for k, v in rows.items() if k[1] == views)} of "
            f"{sum(k[1] == views for k in rows)}" for _, rows in cols) + " |")


if __name__ == "__main__":
    main()
