"""Evaluation: the ``evaluate`` command, the paper's metrics, reports and plots, trajectories, and the retrieval
baseline."""
