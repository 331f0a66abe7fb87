"""The deployment files (docker cannot run here): they parse, and they point at what the service really serves."""
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, episode_records, make_settings, new_key, post_batch, register_task

from monitor_service.app import create_app
from monitor_service.cli import build_parser
from monitor_service.routers import health

DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "monitor"


def _load(name):
    return yaml.safe_load((DEPLOY / name).read_text())


def _served_metric_names(tmp_path) -> set[str]:
    with TestClient(create_app(make_settings(tmp_path, webhook_urls=[]))) as c:
        register_task(c, "Square")
        robot = new_key(c, "r", "robot", "arm1")
        rng = np.random.default_rng(0)
        for i in range(12):
            fail = i % 3 == 0
            post_batch(c, robot, episode_records(f"e{i}", "Square", rng, 0.6 if fail else 0.3, n_steps=5,
                                                 success=not fail)[0])
        c.post("/v1/calibrations", json={"task": "Square", "alpha": 0.2},
               headers={"X-API-Key": ADMIN}).raise_for_status()
        text = c.get("/metrics", headers={"X-API-Key": ADMIN}).text
    names = {line.split("{")[0].split(" ")[0] for line in text.splitlines() if line and not line.startswith("#")}
    # Families without samples yet (no alert raised in this run) are still declared by their TYPE line.
    for family in re.findall(r"^# TYPE (\S+) (\S+)$", text, re.M):
        name, kind = family[0].removesuffix("_total"), family[1]
        suffixes = {"counter": ["_total"], "histogram": ["_bucket", "_sum", "_count"]}.get(kind, [""])
        names |= {name + s for s in suffixes}
    return names


def test_compose_prometheus_and_service_agree():
    compose = _load("docker-compose.yml")
    assert {"db", "monitor", "prometheus", "grafana"} <= set(compose["services"])
    monitor = compose["services"]["monitor"]
    assert monitor["build"]["dockerfile"] == "deploy/monitor/Dockerfile"
    assert (DEPLOY / monitor["build"]["context"]).resolve() == DEPLOY.parents[1].resolve()  # the repository root
    assert monitor["environment"]["JEPA_MONITOR_DATABASE_URL"].startswith("postgresql")
    published = {p.split(":")[1] for p in monitor["ports"]}
    cmd = re.search(r'CMD \[(.*)\]', (DEPLOY / "Dockerfile").read_text()).group(1)
    argv = json.loads(f"[{cmd}]")
    args = build_parser().parse_args(argv[1:])
    assert argv[0] == "jepa-monitor" and args.command == "serve" and str(args.port) in published
    prom = _load("prometheus.yml")
    job = next(j for j in prom["scrape_configs"] if j["job_name"] == "jepa-monitor")
    assert job["metrics_path"] == "/metrics"
    assert job["static_configs"][0]["targets"] == [f"monitor:{args.port}"]
    rules_mount = [v if isinstance(v, str) else f"{v['source']}:{v['target']}"
                   for v in compose["services"]["prometheus"]["volumes"]]
    assert job["authorization"]["credentials_file"] in " ".join(rules_mount)
    token = next(v for v in compose["services"]["prometheus"]["volumes"] if not isinstance(v, str))
    # a missing token file must stop `up`, not become a directory Docker creates in its place
    assert token["source"] == "./secrets/prometheus_token" and token["bind"]["create_host_path"] is False
    assert any(v.startswith("./alert_rules.yml:") and v.split(":")[1] in prom["rule_files"] for v in rules_mount)
    for volume in rules_mount + compose["services"]["grafana"]["volumes"]:
        source = volume.split(":")[0]
        if source.startswith("./") and "secrets/" not in source:
            assert (DEPLOY / source).exists(), source
    assert any(r.path == prom_path for r in health.router.routes for prom_path in [job["metrics_path"]])


def test_grafana_and_alert_rules_use_only_served_metrics(tmp_path):
    served = _served_metric_names(tmp_path)
    dash = json.loads((DEPLOY / "grafana/dashboards/jepa-monitor.json").read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p["targets"]]
    exprs += [r["expr"] for g in _load("alert_rules.yml")["groups"] for r in g["rules"]]
    used = {m for e in exprs for m in re.findall(r"\b(jepa_monitor_[a-z_]+)", e)}
    assert used, "no monitor metric referenced"
    missing = used - served
    assert not missing, f"dashboards/rules reference metrics the service does not expose: {missing}"
    assert len({p["id"] for p in dash["panels"]}) == len(dash["panels"])
    ds = _load("grafana/provisioning/datasources/prometheus.yml")["datasources"][0]
    assert all(p["datasource"]["uid"] == ds["uid"] for p in dash["panels"])
    provider = _load("grafana/provisioning/dashboards/dashboards.yml")["providers"][0]
    assert provider["options"]["path"] == "/var/lib/grafana/dashboards"


def _image_requirements() -> list[str]:
    """The requirement lines the image installs: its RUN line's own command, run here."""
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    command = re.search(r'RUN (python -c "(?:[^"\\]|\\.)*") > /tmp/monitor-requirements.txt', dockerfile)
    assert command, "the Dockerfile reads its requirements from pyproject's monitor extra"
    assert "pip install --no-deps ." in dockerfile and "pip install -r /tmp/monitor-requirements.txt" in dockerfile
    out = subprocess.run(["sh", "-c", command.group(1)], cwd=DEPLOY.parents[1], capture_output=True, text=True,
                         check=True)
    return [line for line in out.stdout.splitlines() if line.strip()]


def test_the_image_installs_every_module_the_monitor_imports_and_no_torch():
    """The image installs the package without its base dependencies and then pyproject's monitor extra: every
    third-party module monitor_service imports (anywhere, lazily too) must come from a distribution on that
    list, but for the offline study's figures (monitor_service/offline), which may use the plot extra too; and
    nothing on either may pull torch or a simulator."""
    import ast
    from importlib.metadata import packages_distributions, requires

    from packaging.requirements import Requirement

    import tomllib

    wanted = {Requirement(line).name.lower().replace("_", "-") for line in _image_requirements()}
    extras = tomllib.loads((DEPLOY.parents[1] / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    plot = {Requirement(line).name.lower().replace("_", "-") for line in extras["plot"]}
    root = DEPLOY.parents[1] / "monitor_service"
    modules, offline_modules = set(), set()
    for path in root.rglob("*.py"):
        found = offline_modules if path.relative_to(root).parts[0] == "offline" else modules
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])

    def third_party(names):
        return sorted(m for m in names - set(sys.stdlib_module_names) if m != "monitor_service")

    assert "orjson" in third_party(modules) and "fastapi" in third_party(modules)
    assert "matplotlib" in third_party(offline_modules) and "matplotlib" not in third_party(modules)
    dists = packages_distributions()

    def closure_of(names: set[str]) -> set[str]:
        closure: set[str] = set()
        todo = list(names)
        while todo:   # everything the list pulls in, from the installed metadata
            name = todo.pop()
            if name in closure:
                continue
            closure.add(name)
            for line in requires(name) or []:
                req = Requirement(line)
                if req.marker is None or req.marker.evaluate({"extra": ""}):
                    todo.append(req.name.lower().replace("_", "-"))
        return closure

    image, with_plot = closure_of(wanted), closure_of(wanted | plot)
    for names, closure, where in ((modules, image, "the image does not install"),
                                  (offline_modules, with_plot, "neither the image nor the plot extra installs")):
        for module in third_party(names):
            providers = {d.lower().replace("_", "-") for d in dists.get(module, [])}
            assert providers & closure, f"monitor_service imports {module!r}, which {where}"
    assert not {"torch", "robosuite", "mujoco", "gymnasium", "pymunk"} & with_plot
