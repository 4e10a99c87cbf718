"""Evaluation of PIPE and its baselines on a domain's held-out test parts (DESIGN section 5)."""
