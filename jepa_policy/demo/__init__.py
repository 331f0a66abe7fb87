"""The main job (``jepa-demo``): the whole method end to end on the embedded PushT task.

It sits above the policy package and is the one place where the environments, the policy and the monitor
service meet:
- ``job.py``: the orchestration (demonstrations, both arms trained, the monitor service with live rollouts,
  latency) and the ``jepa-demo`` command;
- ``report.py``: the Markdown report, its figures and statistics;
- ``ceiling.py``: the PushT imitation ceiling of a demonstration file (``jepa-demo ceiling``).
"""
