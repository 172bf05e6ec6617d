"""Evaluation of a run folder (trajectory and formation error, recovery, behaviour, cost) and
``tagswarm report``."""
