"""Diagnosis: where a learned simulator is wrong, why, and how much an extended model gains.

See docs/DIAGNOSIS.md for the method and the report schema.
"""
