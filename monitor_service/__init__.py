"""monitor_service: the future-consistency monitor the robot loop talks to (paper Sec. 3.6, 4.10).

Public entry points: :func:`monitor_service.app.create_app`, :class:`monitor_service.settings.MonitorSettings`,
:class:`monitor_service.client.MonitorClient` / :class:`monitor_service.client.AsyncMonitorClient`,
:func:`monitor_service.server.start_server` and the ``jepa-monitor`` console script.
"""
