"""The build step pyproject.toml cannot declare stably: the C libraries loaded with ctypes (no
Python API).

``ddh_vsensor.model._unit``, the unit's dynamics, ``ddh_vsensor.estimator._kalman``, the
Kalman filter's sample with those dynamics compiled in, and ``ddh_vsensor.tables._interp``, the
tables' row-wise interpolation, are required: the simulator and the
filter run nothing else, so without a C compiler (gcc) the install fails here, saying so.
The chamber models' steps of the estimator (the dynamic mode's, and the one with entrained
air the diagnosis fits) are optional: without a compiler the same steps run in Python.
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CCompilerError, CompileError, ExecError, PlatformError


class BuildExt(build_ext):
    """A required extension that cannot be built names the cure, not only gcc's error."""

    def build_extension(self, ext: Extension) -> None:
        try:
            super().build_extension(ext)
        except (CCompilerError, ExecError, PlatformError) as e:
            if ext.optional:
                raise
            raise CompileError(f"{ext.name} was not built: install a C compiler (gcc) and "
                               f"reinstall ({e})") from e


setup(cmdclass={"build_ext": BuildExt},
      ext_modules=[Extension("ddh_vsensor.model._unit",
                             sources=["ddh_vsensor/model/_unit.c"],
                             libraries=["m"], extra_compile_args=["-ffp-contract=off"]),
                   Extension("ddh_vsensor.estimator._kalman",
                             sources=["ddh_vsensor/estimator/_kalman.c"],
                             depends=["ddh_vsensor/model/_unit.c"],
                             libraries=["m"], extra_compile_args=["-ffp-contract=off"]),
                   Extension("ddh_vsensor.tables._interp",
                             sources=["ddh_vsensor/tables/_interp.c"],
                             libraries=["m"], extra_compile_args=["-ffp-contract=off"]),
                   Extension("ddh_vsensor.estimator._chambers",
                             sources=["ddh_vsensor/estimator/_chambers.c"],
                             libraries=["m"], optional=True),
                   Extension("ddh_vsensor.estimator._air_chambers",
                             sources=["ddh_vsensor/estimator/_air_chambers.c"],
                             depends=["ddh_vsensor/estimator/_chambers.c"],
                             libraries=["m"], optional=True)])
