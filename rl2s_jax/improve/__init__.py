"""Policy improvement inside a learned simulator: SAC fine-tuning, the deployment guard, the
simulator as a brax Env and as a Gymnasium env."""
