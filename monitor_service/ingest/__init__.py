"""The ingest path: decisions, realized latents and outcomes applied in one transaction, fast enough for a fleet.

One layer per module, lowest first:

- ``state``: what is kept in memory (each episode's state between requests, one request's changes) and the
  errors a request can end with;
- ``sql``: the few raw statements a request runs (read, lock, bulk insert, update under a version counter);
- ``records``: decisions, targets and outcomes applied in order to drafts of the touched episodes, paired and
  scored (NMSE) in memory;
- ``alerting``: per episode, the early and running scores and the calibrated alert rule stepped over the newly
  scored decisions;
- ``store``: the transaction around them and the episode cache (:class:`IngestStore`).
"""
from monitor_service.ingest.alerting import rule_params
from monitor_service.ingest.state import IngestError, StaleState
from monitor_service.ingest.store import IngestStore

__all__ = ["IngestError", "IngestStore", "StaleState", "rule_params"]
