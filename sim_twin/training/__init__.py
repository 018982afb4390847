"""Training: the MJX environment, rewards, the rsl_rl PPO run, its site-matrix gate, ONNX export
and model card."""
