"""Data: the Dataset (schema, file, validation), MJX collection, Minari, episodes, true values."""
