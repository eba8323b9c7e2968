"""The paper's harness, above ``app``: the protocol (``protocol``: data, oracle, training and
evaluation of every method's lanes; ``fork``: its fork and join of lanes; ``improvement_phases``:
the improvement phases), the model family's ablation (``ablation``) and the RESULTS tables' rows
(``tables``). Only ``experiments/`` and the tests use it; no ``rl2s`` command does."""
