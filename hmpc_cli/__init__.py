"""hmpc: layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024)."""

__version__ = "0.1.0"
