"""The compiled tick kernels (Cython); everything else about the package is in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[
    # The body check calls MuJoCo's C functions in the library the mujoco package loads (dlopen, dlsym).
    Extension("humanoid_prime.control._tick", ["src/humanoid_prime/control/_tick.pyx"], libraries=["dl"]),
    Extension("humanoid_prime.drivers.ethercat._tick", ["src/humanoid_prime/drivers/ethercat/_tick.pyx"]),
    Extension("humanoid_prime.drivers.sito._tick", ["src/humanoid_prime/drivers/sito/_tick.pyx"]),
])
