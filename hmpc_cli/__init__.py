"""hmpc: layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024)."""

from hmpc_cli.core.blas import pin_kernels

__version__ = "0.1.0"

# before NumPy loads its BLAS: the same kernels on every x86-64 CPU with AVX2 and FMA
pin_kernels()
