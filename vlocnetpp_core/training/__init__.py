"""Training: the ``vlocnetpp train`` command line, the :class:`~vlocnetpp_core.training.trainer.Trainer` of one
stage, its data, inits, state, learning rate and losses, and the declarative recipes that run whole schedules.

Importing this package imports nothing else (no torch); see docs/architecture.md ("Training").
"""
