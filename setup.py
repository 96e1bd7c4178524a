"""The packages of the wheel; everything else is in pyproject.toml.

Every package under gst_jax/ is found, so that a new subpackage cannot be left out of an
installed wheel (it once shipped without gst_jax.conformal), and the bundled data/ ships as
gst_jax.datasets (pyproject.toml maps its folder and names its files). pyproject.toml alone
cannot say both: a `packages.find` table finds only folders that exist under their own names."""

from setuptools import find_packages, setup

setup(packages=[*find_packages(include=["gst_jax", "gst_jax.*"]), "gst_jax.datasets"])
