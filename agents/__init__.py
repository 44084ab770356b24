"""SB3 agents for AUVFollow: a residual wrapper over the paper's controllers, training and
evaluation entry points (PPO, SAC, TD3), rl-zoo3-format hyperparameters and the
``auv-follow`` command line (train | evaluate | compare). See ``agents/README.md``."""
