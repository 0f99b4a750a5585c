# Helpers of workflow/rules/report.smk: what the report page takes from the run and the config.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

# (from the light module, not stages.report: parsing the workflow imports no torch; issue 22)
from anidress_core.resources import REFERENCE_TABLES


def report_reference(key):
    """Input function: [path] of a committed reference table if present here, else []."""
    path = REFERENCE_TABLES[key]
    return lambda wildcards: [path] if os.path.isfile(path) else []


def report_scenes():
    """What the page takes from the config: the scenes run, their kind, whether synthetic (a captured scene has no
    ground truth) and sequences (names, roles, frames)."""
    return {"run_scenes": config["run_scenes"],
            "scenes": {s: {k: config["scenes"][s][k] for k in ("kind", "synthetic", "sequences")}
                       for s in config["run_scenes"]}}
