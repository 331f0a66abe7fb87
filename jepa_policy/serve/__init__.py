"""``jepa-policy serve``: JEPA Policy behind openpi's websocket protocol, with the future-consistency monitor inside.

The wire is openpi's own (Physical-Intelligence/openpi: ``packages/openpi-client`` and
``src/openpi/serving/websocket_policy_server.py``), so a robot loop written for openpi's ``WebsocketClientPolicy``
drives this server unchanged:

* one websocket per robot; ``GET /healthz`` answers ``OK``; a non-loopback server needs the header
  ``Authorization: Api-Key <key>`` (openpi-client's ``api_key``) or mutual TLS (a client certificate);
* on connect the server sends its metadata; then each binary frame from the client is one request, a map packed
  with msgpack in which numpy arrays are ``{b"__ndarray__": True, b"data", b"dtype", b"shape"}`` (openpi's
  ``msgpack_numpy``; numeric dtypes only, nothing is ever pickled), answered by one map: ``actions`` (the chunk
  to execute, unnormalised, in the task's action space), ``server_timing`` (``infer_ms``, ``queue_ms``,
  ``prev_total_ms``), ``step``, ``episode``, ``history_padded`` and, with the monitor on, ``monitor``;
* a request that cannot be used is answered with a text frame naming the problem (openpi's client raises it as a
  RuntimeError) and, unlike openpi's server, the connection stays open for the next request.

Requests: the task's observation keys (``metadata["observation"]``), each either the newest frame (the server
keeps the history the policy needs, ``obs_steps`` frames) or the newest ``n <= obs_steps`` frames stacked on a
leading axis (a loop that calls once per chunk sends its own history). Optional fields: ``episode`` (an id; a new
one starts an episode), ``reset`` (start a new episode), ``step`` (the newest frame's episode step; default: the
step after the previous request's), ``outcome`` (true/false: the episode succeeded or failed; ends it),
``observe`` (feed frames only: no actions, e.g. the frames between two chunks the monitor scores), ``full_chunk``
(all H predicted actions instead of the ``n_action_steps`` executed ones).

Layers, lowest first: ``codec`` (the checked msgpack-numpy wire), ``request`` (a request checked against the
task), ``sessions`` (one robot's episode and history), ``batcher`` (cross-robot batching), ``events`` (the access
and event log), ``config`` (settings and secrets), ``server`` (connections, auth, the monitor inside).
"""
from jepa_policy.serve.codec import MAX_REQUEST_BYTES, RequestError, pack, unpack
from jepa_policy.serve.config import ServeConfig, check_config, read_secret
from jepa_policy.serve.server import PolicyServer, serve_checkpoint, server_metadata

__all__ = ["MAX_REQUEST_BYTES", "PolicyServer", "RequestError", "ServeConfig", "check_config", "pack", "read_secret",
           "serve_checkpoint", "server_metadata", "unpack"]
