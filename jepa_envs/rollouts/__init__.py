"""Rollouts at scale: the persistent pool of env-only worker processes (``pool``)."""
