"""Evaluation: ranking and value metrics (NumPy), a simulator scored on a Dataset's
policies, the oracle (real dynamics through the same path)."""
