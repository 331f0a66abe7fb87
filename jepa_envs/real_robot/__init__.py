"""The physical robot behind the jepa_envs interface: a robot bridge (robot computer) and a proxy env (policy).

Kept import-light on purpose: ``import jepa_envs`` registers the real-robot ids through ``registration``
without importing ZeroMQ or any hardware SDK; those load when a bridge or proxy is built.
"""
