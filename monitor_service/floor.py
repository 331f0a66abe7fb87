"""The framework's floor for ``jepa-monitor bench``: bare FastAPI + SQLite that only inserts what it is sent.

``POST /v1/decisions``, ``/v1/targets`` and ``/v1/batch`` decode the body exactly as the service does (JSON or
msgpack), inserts one row per record (the latent as bytes) and commits: no auth, no validation, no scoring, no
episode state, no alerts. The ratio of its throughput to the service's is the cost of everything the monitor does
on top of its framework.

    python -m uvicorn monitor_service.floor:create_app --factory   # JEPA_MONITOR_FLOOR_DB=/tmp/floor.db
"""
from __future__ import annotations

import os
import sqlite3
import threading

import numpy as np
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from monitor_service.encoding import decode_body


def create_app() -> FastAPI:
    path = os.environ.get("JEPA_MONITOR_FLOOR_DB", "floor.db")
    conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=NORMAL")   # as the service: durable across a process crash
    conn.execute("CREATE TABLE IF NOT EXISTS rows (id INTEGER PRIMARY KEY, episode TEXT, step INTEGER, z BLOB)")
    lock = threading.Lock()
    app = FastAPI(title="floor")

    def insert(body: bytes, content_type: str | None) -> int:
        payload = decode_body(body, content_type)
        records = payload["records"] if "records" in payload else [payload]
        rows = [(r["episode"], r["step"], np.asarray(r.get("z_hat", r.get("z")), dtype="<f4").tobytes())
                for r in records]
        with lock:
            conn.execute("BEGIN IMMEDIATE")
            conn.executemany("INSERT INTO rows (episode, step, z) VALUES (?, ?, ?)", rows)
            conn.execute("COMMIT")
        return len(rows)

    async def ingest(request: Request) -> JSONResponse:
        body = await request.body()
        n = await run_in_threadpool(insert, body, request.headers.get("content-type"))
        return JSONResponse({"accepted": n})

    for path in ("/v1/decisions", "/v1/targets", "/v1/batch"):
        app.add_api_route(path, ingest, methods=["POST"])

    return app
