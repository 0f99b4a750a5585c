# Rule scene_files: the manifest of one part of a captured scene -> results/<scene>/inputs/<part>.json
# ({"files": [[path, size in bytes, mtime in ns], ...]}: any change of a file changes it). Standard library
# only: a job starts in a fraction of a second (a `run:` block is a whole Snakemake process, about 2 s).
import json
import os

paths = list(snakemake.input)  # noqa: F821 (set by Snakemake)
rows = [[p, os.stat(p).st_size, os.stat(p).st_mtime_ns] for p in paths]
out, log = snakemake.output[0], snakemake.log[0]  # noqa: F821
for path in (out, log):
    os.makedirs(os.path.dirname(path), exist_ok=True)
tmp = out + ".part"
with open(tmp, "w") as fh:
    json.dump({"files": rows}, fh, indent=0)
os.replace(tmp, out)
with open(log, "w") as fh:
    fh.write(f"{out}: {len(rows)} files, {sum(r[1] for r in rows)} bytes\n")
