"""Fixed-mode MPC layer."""
