"""Policy zoos: load and split (``zoo``), build with SAC/PPO (``build``, ``learners``,
``store``); the shipped zoos are package data under ``shipped/<task>/``."""
