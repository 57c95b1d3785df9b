"""Builds the optional native kernels (jaxspring/native/*.cc) against XLA's FFI headers.

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
            sources=["jaxspring/steppers/native/springs.cc", "jaxspring/steppers/native/lattice.cc"],
            include_dirs=[include],
            extra_compile_args=[
                "-std=c++17",
                "-O3",
                "-fno-math-errno",  # lets sqrt vectorise (IEEE results unchanged)
                "-march=native",  # built where it runs (pip builds it on install)
                "-pthread",
                "-Wno-attributes",
                "-Wno-return-type",
            ],
            extra_link_args=["-pthread"],
            language="c++",
            optional=True,
        )
    ]


setup(ext_modules=native_extensions())
