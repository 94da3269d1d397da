"""The package's one native part: the I/Q kernel (`cohflash_jax/native_kernels.c`), a plain C
library that `cohflash_jax.native` loads with ctypes. Optional: where no C compiler is found the
install goes on without it, and the reconstruction runs XLA's I/Q programs instead. Everything
else is in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "cohflash_jax.native_kernels",
            sources=["cohflash_jax/native_kernels.c"],
            extra_compile_args=["-O3"],
            libraries=["m"],
            optional=True,
        )
    ]
)
