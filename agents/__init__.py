"""Layer 5: controllers for the MPA leg envs — classical baselines, PPO residual training and an
evaluation harness that treats them all alike (SB3's ``predict`` interface)."""
