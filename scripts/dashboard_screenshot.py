"""The operator dashboard of a monitor database in headless Chromium, checked against the service's API and saved
as a screenshot (docs/figures/dashboard_tasks.png, from a `jepa-monitor tasks-study --keep DIR --in-flight K`
database):

    python scripts/dashboard_screenshot.py --database-url sqlite:///DIR/tasks_study.db --out dashboard.png

A real server is started on the database (a fresh admin and operator key, both revoked at the end); the page is
read the way an operator reads it, and for every calibrated task the script checks what the API says: the
task's own threshold in its row, its live-episode and open-alert counts, every open alert listed, and a risk
trajectory for each of its live episodes drawn (up to the dashboard's four) against that task's threshold. A
mismatch is an error. Needs the `test` extra (playwright) and Debian's chromium (scripts/setup.sh installs both).
"""
from __future__ import annotations

import argparse
import json
import secrets
import sys
from pathlib import Path

import httpx

from monitor_service.server import start_server

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
PER_TASK = 4   # the dashboard's TRAJECTORIES_PER_TASK


def screenshot(database_url: str, out: str | Path, live_window_s: float = 30 * 86400.0, width: int = 1500) -> dict:
    """Serve ``database_url``, open its dashboard, check it against the API and save a full-page PNG at ``out``.
    ``live_window_s``: how long an episode without outcome counts as live (a kept database's in-flight
    episodes are hours old). Returns what was checked, per task."""
    from playwright.sync_api import sync_playwright

    admin = {"X-API-Key": secrets.token_urlsafe(24)}
    env = {"JEPA_MONITOR_LIVE_EPISODE_S": str(live_window_s)}
    checked: dict = {}
    with start_server(database_url, admin_key=admin["X-API-Key"], env=env, create=False) as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        # ours: the bootstrap key the server just made (the newest of that name) and an operator key
        mine = [max((k for k in http.get("/v1/keys", headers=admin).json() if k["name"].startswith("bootstrap-admin")),
                    key=lambda k: k["id"])["id"]]
        operator = http.post("/v1/keys", headers=admin, json={"name": f"screenshot-{secrets.token_hex(4)}",
                                                              "role": "operator"}).json()
        mine.insert(0, operator["id"])
        try:
            report = http.get("/v1/report", headers=admin).json()
            tasks = [c for c in report["tasks"] if not c.get("checkpoint")]
            if not tasks:
                raise ValueError(f"{database_url}: no calibrated task to show; calibrate one first")
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
                try:
                    page = browser.new_page(viewport={"width": width, "height": 900})
                    page.goto(f"{server.url}/dashboard#key={operator['key']}")
                    page.wait_for_function("document.getElementById('status').textContent === 'connected'")
                    for c in tasks:
                        task = c["task"]
                        live = http.get("/v1/episodes", headers=admin,
                                        params={"live": "true", "task": task, "limit": 200}).json()
                        row = page.locator(f"#tasks tr[data-task='{task}']")
                        detector = row.locator("td.detector").inner_text()
                        if f"up to {c['threshold']:.4f}" not in detector:   # dashboard.js: toFixed(4)
                            raise RuntimeError(f"{task}: the row says {detector!r}, the API's threshold is "
                                               f"{c['threshold']}")
                        shown_live = row.locator("td").nth(6).inner_text()
                        if shown_live != str(len(live)):
                            raise RuntimeError(f"{task}: the row shows {shown_live} live episodes, the API {len(live)}")
                        drawn = page.locator(f"svg.trajectory[data-task='{task}']")
                        scored = [e["id"] for e in live if e["n_scored"]][:PER_TASK]
                        ids = sorted(drawn.nth(i).get_attribute("data-episode") for i in range(drawn.count()))
                        if ids != sorted(scored):
                            raise RuntimeError(f"{task}: trajectories drawn for {ids}, live scored episodes {scored}")
                        for i in range(drawn.count()):
                            if drawn.nth(i).locator("polyline.threshold").count() != 1:
                                raise RuntimeError(f"{task}: a trajectory without its threshold line")
                        alerts = http.get("/v1/alerts", headers=admin, params={"task": task, "limit": 5000}).json()
                        waiting = sum(a["state"] in ("open", "acknowledged") for a in alerts)
                        if row.locator("td").nth(8).inner_text() != str(waiting):
                            raise RuntimeError(f"{task}: the row shows {row.locator('td').nth(8).inner_text()} open "
                                               f"alerts, the API {waiting}")
                        listed = page.locator("#alerts tbody tr", has=page.locator(f"td:text-is('{task}')"))
                        shown = {int(listed.nth(i).get_attribute("data-alert")) for i in range(listed.count())}
                        if not {a["id"] for a in alerts if a["state"] in ("open", "acknowledged")} <= shown:
                            raise RuntimeError(f"{task}: an open or acknowledged alert is missing from the list")
                        checked[task] = {"threshold": c["threshold"], "rule": c["rule"], "live": len(live),
                                         "trajectories": ids,
                                         "alerted_episodes": len({a["episode_id"] for a in alerts}),
                                         "waiting_alerts": waiting}
                    page.screenshot(path=str(out), full_page=True)
                finally:
                    browser.close()
        finally:
            for key_id in mine:   # the admin key last: it revokes the operator's
                http.delete(f"/v1/keys/{key_id}", headers=admin).raise_for_status()
    return checked


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--database-url", required=True, help="e.g. sqlite:///DIR/tasks_study.db")
    ap.add_argument("--out", required=True, help="the PNG written")
    ap.add_argument("--live-window", type=float, default=30 * 86400.0,
                    help="seconds an episode without outcome counts as live (default 30 days)")
    ap.add_argument("--json", action="store_true", help="print what was checked as JSON")
    args = ap.parse_args(argv)
    try:
        checked = screenshot(args.database_url, args.out, args.live_window)
    except (ValueError, RuntimeError) as exc:
        print(f"dashboard_screenshot: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(checked, indent=2))
    else:
        for task, c in checked.items():
            print(f"{task}: threshold {c['threshold']:.4g} ({c['rule']}), {c['live']} live, "
                  f"{len(c['trajectories'])} trajectories, {c['alerted_episodes']} episodes alerted")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
