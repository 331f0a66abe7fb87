"""Deploying jepa-policy serve off loopback: a network bind needs an API key or mutual TLS (TLS
alone let a client with neither key nor certificate drive the robot), and the keys come from the environment or
a file so that no local user reads them in ``ps``. Real certificates (openssl), real `jepa-policy serve` processes,
the real monitor service."""
from __future__ import annotations

import os
import shutil
import socket
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import websockets
from _serve_helpers import GOOD, checkpoint, events, serve  # noqa: F401 (fixtures)
from websockets.sync.client import connect

from jepa_policy.cli import main as policy_main
from jepa_policy.policy import Policy
from jepa_policy.serve import PolicyServer, ServeConfig, check_config, pack, read_secret, unpack

pytestmark = pytest.mark.timeout(300)


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _signed(name: str, ca: str, cwd: Path, san: str = "") -> None:
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", f"{name}.key",
             "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=cwd)
    ext = cwd / f"{name}.ext"
    ext.write_text(f"subjectAltName={san}\n" if san else "basicConstraints=CA:FALSE\n")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key", "-CAcreateserial",
             "-out", f"{name}.pem", "-days", "1", "-extfile", str(ext), cwd=cwd)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A CA that signs the server's and one robot's certificate, and a stranger's CA with its own robot."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make certificates")
    d = tmp_path_factory.mktemp("pki")
    for ca in ("ca", "other-ca"):
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
                 f"{ca}.key", "-out", f"{ca}.pem", "-days", "1", "-subj", f"/CN={ca}", cwd=d)
    _signed("server", "ca", d, san="IP:127.0.0.1,DNS:localhost")
    _signed("robot", "ca", d)
    _signed("stranger", "other-ca", d)
    return d


def _tls_client(port: int, pki: Path, cert: str | None):
    ctx = ssl.create_default_context(cafile=str(pki / "ca.pem"))
    if cert:
        ctx.load_cert_chain(str(pki / f"{cert}.pem"), str(pki / f"{cert}.key"))
    ws = connect(f"wss://127.0.0.1:{port}", ssl=ctx, compression=None, max_size=None, open_timeout=10)
    return ws, unpack(ws.recv(timeout=10))


def test_a_network_bind_needs_a_key_or_mutual_tls(serve, checkpoint, pki, events):
    tls = {"tls_cert": str(pki / "server.pem"), "tls_key": str(pki / "server.key")}
    with pytest.raises(ValueError, match="mutual TLS .*--tls-client-ca"):   # TLS alone was accepted
        PolicyServer(Policy.from_checkpoint(checkpoint), ServeConfig(host="0.0.0.0", port=0, **tls))
    server = serve(host="0.0.0.0", tls_client_ca=str(pki / "ca.pem"), **tls)
    ws, meta = _tls_client(server.port, pki, "robot")
    assert meta["task"] == "PushT"
    ws.send(pack(GOOD))
    assert unpack(ws.recv())["actions"].shape == (8, 2)
    ws.close()
    for cert in (None, "stranger"):   # no certificate, or one our CA did not sign: no metadata, no actions
        with pytest.raises((ssl.SSLError, ConnectionError, websockets.InvalidHandshake, websockets.ConnectionClosed)):
            _tls_client(server.port, pki, cert)
    # each refused handshake is a line of the event log, with the peer and the reason (it used to leave none)
    deadline = time.monotonic() + 10
    while len(refused := [e for e in events() if e["event"] == "tls_refused"]) < 2:
        assert time.monotonic() < deadline, events()
        time.sleep(0.05)
    assert all(e["peer"].startswith("127.0.0.1:") for e in refused), refused
    assert "CERTIFICATE" in refused[0]["problem"] and "CERTIFICATE" in refused[1]["problem"], refused


def test_secrets_from_a_file_or_the_environment(tmp_path, monkeypatch, capsys):
    key = tmp_path / "api.key"
    key.write_text("from-file\n")
    key.chmod(0o600)
    monkeypatch.setenv("JEPA_TEST_KEY", "from-env")
    assert read_secret("--api-key", None, str(key), "JEPA_TEST_KEY") == "from-file"
    assert read_secret("--api-key", None, None, "JEPA_TEST_KEY") == "from-env"
    assert read_secret("--api-key", "argv", None, "JEPA_TEST_KEY") == "argv"
    monkeypatch.delenv("JEPA_TEST_KEY")
    capsys.readouterr()
    assert read_secret("--monitor-key", None, None, "JEPA_TEST_KEY") is None
    assert capsys.readouterr().err == ""                       # nothing on argv, nothing to warn about
    assert read_secret("--api-key", None, None, "JEPA_TEST_KEY") is None
    with pytest.raises(ValueError, match="not both"):
        read_secret("--api-key", "argv", str(key), "JEPA_TEST_KEY")
    key.chmod(0o644)
    with pytest.raises(ValueError, match="readable by other users; chmod 600"):
        read_secret("--api-key", None, str(key), "JEPA_TEST_KEY")
    (tmp_path / "empty.key").write_text("")
    (tmp_path / "empty.key").chmod(0o600)
    with pytest.raises(ValueError, match="is empty"):
        read_secret("--monitor-key", None, str(tmp_path / "empty.key"), "JEPA_TEST_KEY")
    with pytest.raises(ValueError, match=f"--api-key-file {tmp_path} is a directory"):   # said "does not exist"
        read_secret("--api-key", None, str(tmp_path), "JEPA_TEST_KEY")
    (tmp_path / "bin.key").write_bytes(b"\xff\xfe\x00key\n")
    (tmp_path / "bin.key").chmod(0o600)
    with pytest.raises(ValueError, match=f"--api-key-file {tmp_path / 'bin.key'} is not UTF-8 text"):
        read_secret("--api-key", None, str(tmp_path / "bin.key"), "JEPA_TEST_KEY")
    monkeypatch.setenv("JEPA_TEST_KEY", " \t ")   # a blank key used to let a 0.0.0.0 server start
    with pytest.raises(ValueError, match="JEPA_TEST_KEY is blank"):
        read_secret("--api-key", None, None, "JEPA_TEST_KEY")
    with pytest.raises(ValueError, match="the API key is blank"):
        check_config(ServeConfig(host="0.0.0.0", api_key="   "))


def test_bad_key_files_are_one_line_errors(checkpoint, tmp_path, capsys):
    key = tmp_path / "open.key"
    key.write_text("k\n")
    key.chmod(0o644)
    for flags, message in ((["--api-key-file", str(key)], "chmod 600"),
                           (["--api-key-file", str(tmp_path / "none")], "does not exist"),
                           (["--api-key", "a", "--api-key-file", str(key)], "not both"),
                           (["--monitor-url", "http://127.0.0.1:9"], "--monitor-url needs --monitor-key")):
        assert policy_main(["serve", "--checkpoint", str(checkpoint), *flags]) == 2
        assert message in capsys.readouterr().err


def test_a_key_given_on_argv_is_warned_about_with_the_env_var_and_file_alternatives(checkpoint, tmp_path, capsys,
                                                                                     monkeypatch):
    """--api-key / --monitor-key still work (scripts rely on them) but say that `ps` shows them and what hides them;
    the file and the environment variable say nothing. (--tls-cert without --tls-key stops serve right after the
    secrets are read, before any port is bound.)"""
    stop = ["--tls-cert", str(tmp_path / "c.pem")]
    assert policy_main(["serve", "--checkpoint", str(checkpoint), "--api-key", "s3cret",
                        "--monitor-url", "http://127.0.0.1:9", "--monitor-key", "m0n", *stop]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "warning: --api-key on the command line is visible to every local user (ps, /proc/<pid>/cmdline); set "
        "JEPA_POLICY_API_KEY or pass --api-key-file PATH (a file of mode 600) instead",
        "warning: --monitor-key on the command line is visible to every local user (ps, /proc/<pid>/cmdline); set "
        "JEPA_POLICY_MONITOR_KEY or pass --monitor-key-file PATH (a file of mode 600) instead",
        "jepa-policy serve: error: TLS needs both --tls-cert and --tls-key"]
    key = tmp_path / "api.key"
    key.write_text("s3cret\n")
    key.chmod(0o600)
    monkeypatch.setenv("JEPA_POLICY_MONITOR_KEY", "m0n")
    assert policy_main(["serve", "--checkpoint", str(checkpoint), "--api-key-file", str(key),
                        "--monitor-url", "http://127.0.0.1:9", *stop]) == 2
    assert capsys.readouterr().err.splitlines() == ["jepa-policy serve: error: TLS needs both --tls-cert and --tls-key"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_served_keys_never_appear_on_the_command_line(checkpoint, tmp_path):
    """`jepa-policy serve` reads its API key from a file and its monitor key from JEPA_POLICY_MONITOR_KEY: clients
    need the key, the monitor receives the decisions, and neither key is in the process's argv."""
    from monitor_service.server import start_server

    admin = "deploy-test-admin"
    with start_server(f"sqlite:///{tmp_path / 'monitor.db'}", admin_key=admin) as monitor:
        with httpx.Client(base_url=monitor.url, headers={"X-API-Key": admin}) as http:
            assert http.put("/v1/tasks/PushT", json={}).status_code == 200
            robot_key = http.post("/v1/keys", json={"name": "arm", "role": "robot", "robot": "arm"}).json()["key"]
            api_key = "api-" + os.urandom(8).hex()
            key_file = tmp_path / "api.key"
            key_file.write_text(api_key + "\n")
            key_file.chmod(0o600)
            port = _free_port()
            proc = subprocess.Popen(
                [sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", str(checkpoint), "--port",
                 str(port), "--threads", "1", "--api-key-file", str(key_file), "--monitor-url", monitor.url,
                 "--robot", "arm"], env={**os.environ, "JEPA_POLICY_MONITOR_KEY": robot_key},
                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            try:
                deadline = time.monotonic() + 120
                while True:
                    try:
                        if httpx.get(f"http://127.0.0.1:{port}/healthz").text == "OK\n":
                            break
                    except httpx.HTTPError:
                        pass
                    assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read().decode()[-2000:]
                    time.sleep(0.2)
                argv = Path(f"/proc/{proc.pid}/cmdline").read_bytes().decode()
                assert api_key not in argv and robot_key not in argv
                with pytest.raises(websockets.InvalidStatus, match="401"):
                    connect(f"ws://127.0.0.1:{port}")
                with connect(f"ws://127.0.0.1:{port}", additional_headers={"Authorization": f"Api-Key {api_key}"},
                             compression=None, max_size=None) as ws:
                    assert unpack(ws.recv())["monitor"] == {"task_id": "PushT"}
                    for step in range(3):
                        ws.send(pack({**GOOD, "episode": "deploy-ep", "step": step}))
                        assert unpack(ws.recv())["actions"].shape == (8, 2)
                deadline = time.monotonic() + 30
                while http.get("/v1/episodes/deploy-ep").status_code != 200 or \
                        http.get("/v1/episodes/deploy-ep").json()["n_decisions"] < 3:
                    assert time.monotonic() < deadline, "the monitor never received the decisions"
                    time.sleep(0.2)
            finally:
                proc.terminate()
                _, err = proc.communicate(timeout=30)
    lines = err.decode().splitlines()
    assert any('"event": "unauthorized"' in line for line in lines), lines[-20:]
    assert not any(api_key in line or robot_key in line for line in lines)


def test_a_stalled_tls_handshake_is_closed_and_logged(serve, pki, events, monkeypatch):
    """The first bytes of a ClientHello, then silence: the server closed it after 10 s without a line; now the
    close is a tls_refused line naming the stall (the timeout shortened here)."""
    import jepa_policy.serve.server as server_module
    monkeypatch.setattr(server_module, "TLS_HANDSHAKE_TIMEOUT_S", 0.5)
    server = serve(tls_cert=str(pki / "server.pem"), tls_key=str(pki / "server.key"))
    stalled = socket.create_connection(("127.0.0.1", server.port))
    stalled.sendall(b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03")
    stalled.settimeout(10)
    start = time.monotonic()
    assert stalled.recv(100) == b"" and time.monotonic() - start < 5, "the server closed the stalled handshake"
    stalled.close()
    deadline = time.monotonic() + 5
    while not (refused := [e for e in events() if e["event"] == "tls_refused"]):
        assert time.monotonic() < deadline, events()
        time.sleep(0.05)
    assert "not finished within 0.5 s" in refused[0]["problem"] and refused[0]["peer"].startswith("127.0.0.1:")
    ws, meta = _tls_client(server.port, pki, None)   # a client that finishes its handshake is served as before
    assert meta["task"] == "PushT"
    ws.close()
    assert len([e for e in events() if e["event"] == "tls_refused"]) == 1


def test_accept_errors_out_of_descriptors_are_json_lines_not_tracebacks(checkpoint, tmp_path):
    """jepa-policy serve at RLIMIT_NOFILE 128 and 200 idle connections: asyncio's accept() failed with EMFILE and
    wrote 15,934 lines of tracebacks in 25 s; now each failure is an accept_failed event line, rate-limited, and a
    robot is served once the connections close."""
    import json
    import resource
    out = tmp_path / "serve.err"
    with out.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", str(checkpoint),
                                 "--port", "0", "--threads", "1"], stdout=subprocess.PIPE, stderr=err, text=True,
                                preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (128, 128)))
    try:
        banner = proc.stdout.readline()
        port = int(banner.rsplit(":", 1)[1].split()[0])
        held = []
        for _ in range(200):
            try:
                held.append(socket.create_connection(("127.0.0.1", port), timeout=2))
            except OSError:
                break
        time.sleep(3.0)
        for sock in held:
            sock.close()
        ws = None
        deadline = time.monotonic() + 30
        while ws is None:
            try:
                ws = connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None, open_timeout=5)
            except (OSError, websockets.InvalidHandshake, TimeoutError):
                assert time.monotonic() < deadline
                time.sleep(0.5)
        unpack(ws.recv())
        ws.send(pack(GOOD))
        assert unpack(ws.recv())["actions"].shape == (8, 2)
        ws.close()
    finally:
        proc.terminate()
        proc.wait(30)
    lines = [line for line in out.read_text().splitlines() if line.strip()]
    assert lines and all(line.startswith("{") for line in lines), lines[:5]
    failed = [json.loads(line) for line in lines if '"accept_failed"' in line]
    assert failed and failed[0]["errno"] == "EMFILE" and len(failed) <= 8, (len(failed), failed[:2])   # ~1 a second
    assert sum(e["failures"] for e in failed) >= len(failed)
