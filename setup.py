"""The compiled tick kernels (Cython); everything else about the package is in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension("humanoid_prime.control._tick", ["src/humanoid_prime/control/_tick.pyx"]),
    Extension("humanoid_prime.drivers.ethercat._tick", ["src/humanoid_prime/drivers/ethercat/_tick.pyx"]),
    Extension("humanoid_prime.drivers.sito._tick", ["src/humanoid_prime/drivers/sito/_tick.pyx"]),
])
