"""The solver's C kernels (solver/_kernels.c); everything else is in pyproject.toml.

Built without fast-math, FMA contraction or host-specific instructions, so a solve gives
the same bits on every machine (-fno-math-errno only spares sqrt setting errno).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("slamtka.solver._kernels", ["solver/_kernels.c"],
                             extra_compile_args=["-std=c99", "-O2", "-ffp-contract=off", "-fno-math-errno"])])
