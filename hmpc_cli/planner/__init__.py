"""Hybrid MPC layer: mode schedules by cross-entropy (ball), footholds (biped), C rollouts."""
