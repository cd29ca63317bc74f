"""The build step pyproject.toml cannot declare stably: the dynamic mode's C step, loaded with
ctypes (no Python API). Optional: without a C compiler the install succeeds and the same step
runs in Python."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("ddh_vsensor.estimator._chambers",
                             sources=["ddh_vsensor/estimator/_chambers.c"],
                             libraries=["m"], optional=True)])
