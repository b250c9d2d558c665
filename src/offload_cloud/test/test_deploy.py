"""The recipes for real cloud hosts, validated offline with the tools that can: the Kubernetes manifests
against the API schemas (kubernetes-validate), the HAProxy configurations with `haproxy -c`, the systemd
unit with `systemd-analyze verify`; every command line in them is one the server and the health check
accept; every recipe bounds the server's connections below a descriptor limit; and the HAProxy recipe run on
loopback keeps a source that is no robot it has seen to a few connections while robots are served."""
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import kubernetes_validate
import pytest
import yaml

from offload_cloud.client import CloudClient
from offload_cloud.server_cli import parse_args as server_args
from offload_demos.fleet import haproxy_config

from cloud_test_helpers import free_port, start_server

PACKAGE = Path(__file__).resolve().parents[1]
DEPLOY = PACKAGE / "deploy"
K8S_VERSION = "1.30.0"


def scripts():
    return tomllib.loads((PACKAGE / "pyproject.toml").read_text())["project"]["scripts"]


def manifests():
    return [doc for doc in yaml.safe_load_all((DEPLOY / "kubernetes" / "cloud-server.yaml").read_text()) if doc]


def test_kubernetes_manifests_are_valid_and_the_check_is_real():
    docs = manifests()
    assert {doc["kind"] for doc in docs} == {"Deployment", "Service"}
    for doc in docs:
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)
    broken = manifests()[0]
    broken["spec"]["replicas"] = "three"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, K8S_VERSION, strict=True)


def test_kubernetes_commands_are_the_servers_and_the_health_checks():
    deployment = manifests()[0]
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    args = server_args(container["args"])
    assert args.keys_dir == "/keys" and not args.insecure
    # A Pod cannot set a descriptor limit: the server's own cap bounds its connections below the runtime's.
    assert 0 < args.max_connections <= 65536
    probe = container["readinessProbe"]["exec"]["command"]
    assert probe[0] == "offload-cloud-ping" and scripts()[probe[0]] == "offload_cloud.client:main"
    assert "--ping" in probe and probe[probe.index("--keys-dir") + 1] == "/probe-keys"
    mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    assert mounts == {"server-keys": "/keys", "probe-keys": "/probe-keys"}
    secret = next(v for v in deployment["spec"]["template"]["spec"]["volumes"] if v["name"] == "server-keys")
    paths = {item["path"] for item in secret["secret"]["items"]}
    assert {"server.key", "server.key_secret"} <= paths and any(p.startswith("clients/") for p in paths)


def test_dockerfile_runs_the_servers_console_script():
    text = (DEPLOY / "Dockerfile").read_text()
    entrypoint = yaml.safe_load(re.search(r"^ENTRYPOINT (.+)$", text, re.M).group(1))
    command = yaml.safe_load(re.search(r"^CMD (.+)$", text, re.M).group(1))
    assert scripts()[entrypoint[0]] == "offload_cloud.server_cli:main"
    assert server_args(command).keys_dir == "/keys"
    # The documented run command gives the container a descriptor limit with room for the connection cap.
    run = re.search(r"^#\s+(docker run .+)$", text, re.M).group(1)
    soft, hard = map(int, re.search(r"--ulimit nofile=(\d+):(\d+)", run).groups())
    assert soft == hard and 0 < server_args(command).max_connections <= soft - 1024
    health = yaml.safe_load(re.search(r"CMD (\[\"offload-cloud-ping\".+)$", text, re.M).group(1))
    assert scripts()[health[0]] == "offload_cloud.client:main"


@pytest.mark.parametrize("name", ["example", "fleet"])
def test_haproxy_configurations_pass_haproxy_check(name, tmp_path):
    if name == "example":
        path = DEPLOY / "haproxy" / "haproxy.cfg"
    else:
        path = tmp_path / "haproxy.cfg"
        path.write_text(haproxy_config(6000, [7001, 7002], stats_port=6001))
    checked = subprocess.run(["haproxy", "-c", "-f", str(path)], capture_output=True, text=True)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    broken = tmp_path / "broken.cfg"
    broken.write_text(path.read_text().replace("balance leastconn", "balance sometimes"))
    assert subprocess.run(["haproxy", "-c", "-f", str(broken)], capture_output=True).returncode != 0


def test_systemd_unit_verifies_and_its_command_is_accepted(tmp_path):
    unit = (DEPLOY / "systemd" / "offload-cloud-server.service").read_text()
    exec_start = shlex.split(re.search(r"^ExecStart=(.+)$", unit, re.M).group(1))
    assert Path(exec_start[0]).name == "offload-cloud-server" and "offload-cloud-server" in scripts()
    assert server_args(exec_start[1:]).keys_dir == "/etc/offload/keys"
    # systemd's soft limit is 1024 descriptors: the unit sets one with room for the connection cap.
    limit = int(re.search(r"^LimitNOFILE=(\d+)$", unit, re.M).group(1))
    assert 0 < server_args(exec_start[1:]).max_connections <= limit - 1024
    # systemd-analyze needs the command to exist: point it at this interpreter for the check.
    local = tmp_path / "offload-cloud-server.service"
    local.write_text(unit.replace(exec_start[0], sys.executable))
    verified = subprocess.run(["systemd-analyze", "verify", str(local)], capture_output=True, text=True)
    assert verified.returncode == 0, verified.stderr
    broken = tmp_path / "broken.service"
    broken.write_text(local.read_text().replace("Restart=on-failure", "Restart=sometimes"))
    assert "sometimes" in subprocess.run(["systemd-analyze", "verify", str(broken)], capture_output=True,
                                         text=True).stderr


def learner_manifests():
    return [doc for doc in yaml.safe_load_all((DEPLOY / "kubernetes" / "cloud-learner.yaml").read_text()) if doc]


def test_learner_kubernetes_manifest_is_valid_and_runs_the_learner():
    from offload_cloud.learner.cli import parse_args as learner_args

    docs = learner_manifests()
    assert {doc["kind"] for doc in docs} == {"Deployment", "Service", "PersistentVolumeClaim"}
    for doc in docs:
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)
    container = docs[0]["spec"]["template"]["spec"]["containers"][0]
    assert scripts()[container["command"][0]] == "offload_cloud.learner.cli:main"
    args = learner_args(container["args"])
    assert args.command == "serve" and args.keys_dir == "/keys" and args.store == "/store" and not args.insecure
    assert {m["mountPath"] for m in container["volumeMounts"]} == {"/keys", "/store"}
    assert docs[0]["spec"]["replicas"] == 1   # one store, one source of versions


def test_learner_systemd_unit_verifies_and_its_command_is_accepted(tmp_path):
    from offload_cloud.learner.cli import parse_args as learner_args

    unit = (DEPLOY / "systemd" / "offload-cloud-learner.service").read_text()
    exec_start = shlex.split(re.search(r"^ExecStart=(.+)$", unit, re.M).group(1))
    assert Path(exec_start[0]).name == "offload-cloud-learner" and "offload-cloud-learner" in scripts()
    args = learner_args(exec_start[1:])
    assert args.keys_dir == "/etc/offload/keys" and args.store == "/var/lib/offload-learner"
    local = tmp_path / "offload-cloud-learner.service"
    local.write_text(unit.replace(exec_start[0], sys.executable))
    verified = subprocess.run(["systemd-analyze", "verify", str(local)], capture_output=True, text=True)
    assert verified.returncode == 0, verified.stderr
    broken = tmp_path / "broken.service"
    broken.write_text(local.read_text().replace("Restart=on-failure", "Restart=sometimes"))
    assert "sometimes" in subprocess.run(["systemd-analyze", "verify", str(broken)], capture_output=True,
                                         text=True).stderr


def haproxy_recipe():
    return (DEPLOY / "haproxy" / "haproxy.cfg").read_text()


def test_haproxy_recipe_probes_idle_peers_on_both_sides_and_bounds_sources_it_has_not_seen():
    """Keepalive: behind HAProxy the servers' probes reach HAProxy only, so HAProxy probes the robots itself. A
    source that is no robot it has seen is held to a few connections and to a share of the frontend."""
    text = haproxy_recipe()
    defaults = text.split("defaults", 1)[1].split("frontend", 1)[0]
    assert "option clitcpka" in defaults and "option srvtcpka" in defaults
    assert re.search(r"clitcpka-idle (\d+)s", defaults) and re.search(r"srvtcpka-idle (\d+)s", defaults)
    frontend = text.split("frontend robots", 1)[1].split("\nbackend", 1)[0]
    maxconn = int(re.search(r"maxconn (\d+)", frontend).group(1))
    newcomers = int(re.search(r"sc1_conn_cur\(newcomers\) gt (\d+)", frontend).group(1))
    per_source = int(re.search(r"!seen_robot \{ sc0_conn_cur gt (\d+) \}", frontend).group(1))
    assert newcomers <= maxconn // 2 and per_source <= 16
    assert int(re.search(r"inspect-delay (\d+)s", frontend).group(1)) <= 5


@pytest.mark.timeout(120)
def test_haproxy_recipe_on_loopback_refuses_a_flood_from_one_source_and_serves_robots(key_root, tmp_path):
    """The recipe with its bind and servers on loopback: one source address opens connections that send a
    ZMTP greeting and idle; past 8 HAProxy closes them at once (landed recipe: 64 per source, 125 sources fill
    its 8000 slots), and robots from other addresses are served meanwhile."""
    binary = shutil.which("haproxy") or "/usr/sbin/haproxy"
    server = start_server(key_root / "server")
    port = free_port()
    text = haproxy_recipe().replace("bind :5555", f"bind 127.0.0.1:{port}")
    text = re.sub(r"(    server cloud\d .*\n)+", f"    server cloud0 127.0.0.1:{server.endpoint.rsplit(':', 1)[1]} check\n",
                  text)
    (tmp_path / "haproxy.cfg").write_text(text)
    haproxy = subprocess.Popen([binary, "-f", str(tmp_path / "haproxy.cfg"), "-db"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    flood = []
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.1)
        time.sleep(2.5)   # two health checks: the server is up
        for _ in range(12):
            sock = socket.socket()
            sock.bind(("127.0.0.7", 0))
            sock.connect(("127.0.0.1", port))
            flood.append(sock)
            try:
                sock.sendall(b"\xff" + bytes(8) + b"\x7f")
            except OSError:
                pass   # HAProxy already closed it (past the per-source cap): counted as closed below
        time.sleep(0.5)
        open_ones = 0
        for sock in flood:
            sock.settimeout(0.2)
            try:
                open_ones += sock.recv(64) != b""      # the server's greeting came back through HAProxy
            except socket.timeout:
                open_ones += 1
            except OSError:
                pass
        with CloudClient(f"tcp://127.0.0.8:0;127.0.0.1:{port}", keys_dir=str(key_root / "robot"),
                         timeout_s=5.0) as robot:
            robot.ping()
    finally:
        for sock in flood:
            sock.close()
        haproxy.terminate()
        haproxy.wait(10)
        server.stop()
    assert open_ones == 8, open_ones


@pytest.mark.timeout(60)
def test_haproxy_recipe_exports_prometheus_metrics_of_its_robots_and_planners(key_root, tmp_path):
    """The recipe's exporter stanza, run on loopback: after a robot's ping through HAProxy, /metrics shows the
    robots frontend's connection and the planners backend's one live server."""
    from metrics_helpers import scrape, value

    server = start_server(key_root / "server")
    port, metrics_port = free_port(), free_port()
    text = haproxy_recipe().replace("bind :5555", f"bind 127.0.0.1:{port}")
    assert "bind 127.0.0.1:8405" in text and "use-service prometheus-exporter" in text
    text = text.replace("bind 127.0.0.1:8405", f"bind 127.0.0.1:{metrics_port}")
    text = re.sub(r"(    server cloud\d .*\n)+", f"    server cloud0 127.0.0.1:{server.endpoint.rsplit(':', 1)[1]} check\n",
                  text)
    (tmp_path / "haproxy.cfg").write_text(text)
    haproxy = subprocess.Popen([shutil.which("haproxy") or "/usr/sbin/haproxy", "-f", str(tmp_path / "haproxy.cfg"),
                                "-db"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                figures = scrape(f"127.0.0.1:{metrics_port}")
                if value(figures, "haproxy_backend_active_servers", proxy="planners") == 1:
                    break
            except OSError:
                pass
            assert time.monotonic() < deadline, "HAProxy's exporter never showed the planner up"
            time.sleep(0.2)
        with CloudClient(f"tcp://127.0.0.1:{port}", keys_dir=str(key_root / "robot"), timeout_s=5.0) as robot:
            robot.ping()
        figures = scrape(f"127.0.0.1:{metrics_port}")
    finally:
        haproxy.terminate()
        haproxy.wait(10)
        server.stop()
    assert value(figures, "haproxy_frontend_connections_total", proxy="robots") >= 1
    assert value(figures, "haproxy_server_status", proxy="planners", server="cloud0", state="UP") == 1
    # The Grafana dashboard's HAProxy panels query names this exporter has.
    dashboard = (DEPLOY / "grafana" / "offload-cloud.json").read_text()
    used = set(re.findall(r"\b(haproxy_[a-z_]+)", dashboard))
    assert used and used <= {name for name, _ in figures}, used - {name for name, _ in figures}


@pytest.mark.parametrize("which", ["server", "learner"])
def test_kubernetes_scrape_annotations_point_at_the_metrics_endpoint(which):
    """Prometheus' kubernetes-pods job scrapes the annotated port and path: the one the container's
    --metrics-bind serves, on all addresses of the pod, and declared as a container port."""
    from offload_cloud.learner.cli import parse_args as learner_args
    from offload_cloud.metrics import parse_bind

    deployment = (manifests if which == "server" else learner_manifests)()[0]
    template = deployment["spec"]["template"]
    container = template["spec"]["containers"][0]
    args = server_args(container["args"]) if which == "server" else learner_args(container["args"])
    host, port = parse_bind(args.metrics_bind)
    annotations = template["metadata"]["annotations"]
    assert annotations["prometheus.io/scrape"] == "true" and annotations["prometheus.io/path"] == "/metrics"
    assert int(annotations["prometheus.io/port"]) == port and host == "0.0.0.0"
    assert {"name": "metrics", "containerPort": port} in [{k: p[k] for k in ("name", "containerPort")}
                                                          for p in container["ports"]]
