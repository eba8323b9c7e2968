"""Tasks: the MJX environments (brax, backend="mjx") with their reward and termination functions."""
