"""The robot bridge: a networked safety service on the robot computer that serves a robot (or a simulated one)
to one policy client at a time, with the e-stop latch, the safety rules, supervision and the operator's tools.

Import-light on purpose: ``jepa_robot.operator`` (the operator's client, the protocol version, the operator's
credential) and ``jepa_robot.operator_cli`` (``jepa-robot-bridge``) need only ZeroMQ and msgpack, so an e-stop
command starts in tens of milliseconds. ``jepa_robot.protocol`` is the wire both ends speak (the bridge here,
the Gymnasium proxy env in ``jepa_envs.real_robot.proxy``) and the loopback rule the policy server shares. The
rest (``bridge``, ``backends``, ``cli`` ...) serves ``jepa_envs`` tasks and imports them.
"""
