"""Builds the optional native kernels (jaxspring/steppers/native/*.cc) against XLA's FFI headers.

Everything else about the package is in pyproject.toml. If the kernel cannot be built
(no C++17 compiler), the install still succeeds and jaxspring uses its pure-JAX path.
"""

from setuptools import Extension, setup


def native_extensions():
    try:
        import jax.ffi

        include = jax.ffi.include_dir()
    except Exception:  # no jax in the build environment: skip the kernel
        return []
    return [
        Extension(
            "jaxspring.steppers._native_springs",
            sources=[
                "jaxspring/steppers/native/" + name
                for name in (
                    "support.cc",
                    "springs.cc",
                    "lattice_layout.cc",
                    "lattice_reverse.cc",
                    "lattice_groups.cc",
                    "lattice_ffi.cc",
                    "bending.cc",
                )
            ],
            depends=[
                "jaxspring/steppers/native/" + name
                for name in (
                    "spring_law.h",
                    "support.h",
                    "lattice.h",
                    "lattice_threads.h",
                    "lattice_step.h",
                    "lattice_reverse.h",
                    "lattice_groups.h",
                )
            ],
            extra_compile_args=[
                "-isystem",  # XLA's headers: their warnings are not ours
                include,
                "-std=c++17",
                "-O3",
                "-fno-math-errno",  # lets sqrt vectorise (IEEE results unchanged)
                "-march=native",  # built where it runs (pip builds it on install)
                "-pthread",
                "-Wall",
                "-Wextra",
            ],
            extra_link_args=["-pthread"],
            language="c++",
            optional=True,
        )
    ]


setup(ext_modules=native_extensions())
