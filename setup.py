"""Build script for the optional native extension; all metadata lives in pyproject.toml.

``radarpc.dsp.accel._rxsum`` and ``radarpc.dsp.accel._screen`` (the CPU kernels behind
:mod:`radarpc.dsp.accel.native`) are declared ``optional=True``: without a working C compiler the
build prints a warning and the package installs without them,
:func:`radarpc.dsp.accel.native.native_available` reports ``False`` and the torch paths run.
"""
from __future__ import annotations

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class BuildExt(build_ext):
    """Portable compile flags: ``-O3 -fno-math-errno -ffp-contract=off`` on GCC/Clang (inline
    IEEE ``sqrtf``, no fused ``re*re + im*im``, no ``-ffast-math``), ``/O2`` on MSVC. The SIMD
    kernel is selected in the C source with a function target attribute and a run-time CPU
    check, so no ``-march`` flag is used."""

    def build_extensions(self) -> None:
        if self.compiler.compiler_type == "msvc":
            flags = ["/O2"]
        else:
            flags = ["-O3", "-fno-math-errno", "-ffp-contract=off"]
        for ext in self.extensions:
            ext.extra_compile_args = flags + list(ext.extra_compile_args or [])
        super().build_extensions()


setup(
    ext_modules=[Extension("radarpc.dsp.accel._rxsum", sources=["src/radarpc/dsp/accel/_rxsum.c"], optional=True),
                 Extension("radarpc.dsp.accel._screen", sources=["src/radarpc/dsp/accel/_screen.c"], optional=True)],
    cmdclass={"build_ext": BuildExt},
)
