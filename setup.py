"""Packages of anidress-core (the metadata is in pyproject.toml).

Besides the ``anidress_core*`` packages, the wheel carries two folders that live
outside the package in the repository, mapped with ``package_dir`` so that each file
exists once (anidress_core/resources.py finds them):

* ``workflow/schemas/`` -> ``anidress_core/_data/schemas/`` (config.schema.yaml, which
  the Snakemake workflow validates against);
* ``reports/`` -> ``anidress_core/_data/reports/`` (report.html.j2, captions/).
"""
from setuptools import find_packages, setup

DATA = {"anidress_core._data.schemas": "workflow/schemas", "anidress_core._data.reports": "reports"}

setup(
    packages=find_packages(include=["anidress_core", "anidress_core.*"]) + list(DATA),
    package_dir=DATA,
    package_data={"anidress_core._data.schemas": ["*.yaml"], "anidress_core._data.reports": ["*.j2", "captions/*"]},
)
