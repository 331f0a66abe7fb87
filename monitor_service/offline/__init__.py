"""The offline failure study of the monitor: recorded rollouts replayed into a running service, and the
comparisons of failure signals and alert rules on them. The deployable service imports none of it
(tests/test_architecture.py)."""
