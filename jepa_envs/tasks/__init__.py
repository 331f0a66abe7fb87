"""Simulated tasks: the task specs, each simulator family's env (one backend per file), and what they share.

``spec`` (every task's facts), ``base`` (the JEPAEnv interface), ``entry`` (what ``gym.make`` calls), ``wrappers``,
``render`` (the measured OpenGL backend), ``rotations`` and ``abs_actions`` (action conventions);
``pusht`` + ``pusht_expert`` (the embedded 2-D task and its scripted demonstrator), ``robosuite_common`` with
``robomimic_env`` (+ ``robosuite_expert``, Lift's and Can's scripted demonstrators), ``libero_env``
(+ ``libero_setup``) and ``mimicgen_env`` (+ ``install_mimicgen``).
"""
