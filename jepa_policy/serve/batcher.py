"""Cross-robot batching: requests that wait together share one forward pass on one model thread."""
from __future__ import annotations

import asyncio
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from jepa_policy.policy import Policy, decide_frames
from jepa_policy.serve.codec import RequestError

log = logging.getLogger(__name__)


class ServerBusy(RequestError):
    """More requests wait than ``--max-queue``: this one is refused (the connection stays open)."""


@dataclass
class Work:
    """What one request needs from the model: a decision from a history, and the latents of target frames."""

    history: list[dict] | None
    targets: list[dict]
    future: asyncio.Future
    queued_at: float = field(default_factory=time.perf_counter)


class Batcher:
    """Requests that wait together share one forward pass, on one worker thread (the event loop keeps reading)."""

    def __init__(self, policy: Policy, max_batch: int, max_queue: int, scores: bool = False):
        self.policy, self.max_batch, self.max_queue = policy, max_batch, max_queue
        self.scores = scores and policy.detectors is not None   # the embedding scores of each decision's c_t
        self.queue: asyncio.Queue[Work] = asyncio.Queue()
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jepa-serve-model")
        self.batches = self.items = 0
        self.task: asyncio.Task | None = None

    def start(self) -> None:
        self.task = asyncio.get_running_loop().create_task(self._run())

    async def submit(self, work: Work) -> tuple[np.ndarray | None, np.ndarray | None, list[np.ndarray], dict, dict]:
        """(actions, z_hat, the target frames' latents, timing, the decision's embedding scores {name: float})."""
        if self.queue.qsize() >= self.max_queue:
            raise ServerBusy(f"the server is busy: {self.queue.qsize()} requests are waiting (limit "
                             f"{self.max_queue}); retry shortly, or start another server")
        self.queue.put_nowait(work)
        return await work.future

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            batch = [await self.queue.get()]
            while len(batch) < self.max_batch and not self.queue.empty():
                batch.append(self.queue.get_nowait())
            start = time.perf_counter()
            try:
                results = await loop.run_in_executor(self.executor, self._forward, batch)
            except Exception as exc:   # a model failure answers every waiting request, the server goes on
                log.exception("inference failed")
                for work in batch:
                    if not work.future.done():
                        work.future.set_exception(RequestError(f"inference failed ({type(exc).__name__}: {exc})"))
                continue
            infer_ms = (time.perf_counter() - start) * 1e3
            self.batches += 1
            self.items += len(batch)
            for work, (actions, z_hat, latents, scores) in zip(batch, results):
                if not work.future.done():   # the client may have gone meanwhile
                    work.future.set_result((actions, z_hat, latents, {
                        "infer_ms": infer_ms, "queue_ms": (start - work.queued_at) * 1e3, "batch": len(batch)},
                        scores))

    def _forward(self, batch: list[Work]) -> list[tuple]:
        policy = self.policy
        deciding = [w for w in batch if w.history is not None]
        actions = z_hat = None
        scores: dict[str, np.ndarray] = {}
        if deciding:
            frames = [{k: np.stack([w.history[i][k] for w in deciding]) for k in deciding[0].history[i]}
                      for i in range(policy.obs_steps)]
            actions, z_hat, c = decide_frames(policy.model, policy.spec, frames, policy.device,
                                              want_future=policy.model.cfg.has_future_token)
            if self.scores and c is not None:
                scores = policy.detectors.score(c)
        targets = [f for w in batch for f in w.targets]
        latents = list(policy.encode_future({k: np.stack([f[k] for f in targets]) for k in policy.spec.image_keys})) \
            if targets else []
        out, d, latent_iter = [], 0, iter(latents)
        for w in batch:
            mine = [next(latent_iter) for _ in w.targets]
            if w.history is not None:
                out.append((actions[d], None if z_hat is None else z_hat[d], mine,
                            {k: float(v[d]) for k, v in scores.items()}))
                d += 1
            else:
                out.append((None, None, mine, {}))
        return out
