"""The build step pyproject.toml cannot declare stably: the chamber models' C steps (the
dynamic mode's, and the one with entrained air the diagnosis fits), loaded with ctypes (no
Python API). Optional: without a C compiler the install succeeds and the same steps run in
Python."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("ddh_vsensor.estimator._chambers",
                             sources=["ddh_vsensor/estimator/_chambers.c"],
                             libraries=["m"], optional=True),
                   Extension("ddh_vsensor.estimator._air_chambers",
                             sources=["ddh_vsensor/estimator/_air_chambers.c"],
                             depends=["ddh_vsensor/estimator/_chambers.c"],
                             libraries=["m"], optional=True)])
