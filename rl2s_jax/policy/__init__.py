"""Policies and the learners that train them: the tanh-Gaussian MLP policy, SAC, PPO."""
