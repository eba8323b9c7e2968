"""The simulator model: the dynamics family, the generator and critic networks, termination,
and ``Simulator`` with its value rollouts."""
