"""deploy/check.sh's live checks, against the binaries that deploy/docker/build.sh made (the image's build command):

1. The Dockerfile's run stage: its ENTRYPOINT started with its ENV (addresses moved to loopback port 0, the data
   directory to a temporary one, the compose example configuration as RAYD_CONFIG, as compose mounts it), then its
   HEALTHCHECK command, which must exit 0.
2. Scale-out by scene: three such nodes behind Envoy running deploy/envoy/envoy.yaml (endpoint and listener
   addresses rewritten to loopback, nothing else changed); scenes built, read and traced with rayctl through Envoy
   each live whole on one node, every node is used, and a node asked for a scene it does not hold answers
   NOT_FOUND naming the accel.
3. Every metric the Grafana dashboard queries is exported by the nodes.

Usage: check.py BIN_DIR (holding rayd and rayctl; `envoy` on PATH)."""

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.request
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.argv[1]).resolve()
CONFIG = ROOT / "deploy" / "compose" / "rayd.example.toml"
WRITE_KEY = next(k["key"] for k in tomllib.loads(CONFIG.read_text())["tenants"][0]["keys"] if k["role"] == "write")
processes = []


def dockerfile():
    """The run stage's ENV, ENTRYPOINT and HEALTHCHECK command, and the build stage's RUN of build.sh."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith("#")]
    run_stage = next(i for i, line in enumerate(lines) if re.match(r"FROM \S+ AS run$", line))
    assert any("deploy/docker/build.sh /out" in line for line in lines[:run_stage] if line.startswith("RUN ")), \
        "the build stage runs deploy/docker/build.sh"
    env, entrypoint, health = {}, None, None
    for line in lines[run_stage:]:
        if line.startswith("ENV "):
            env.update(dict(pair.split("=", 1) for pair in shlex.split(line[4:])))
        elif line.startswith("ENTRYPOINT "):
            entrypoint = json.loads(line[len("ENTRYPOINT "):])
        elif line.startswith("HEALTHCHECK "):
            health = json.loads(line.split(" CMD ", 1)[1])
    return env, entrypoint, health


def start_rayd(image_env, entrypoint, data_dir):
    """One node as the image starts it, on loopback; returns (grpc address, admin address)."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("RAYD_")}
    env.update(image_env)
    env.update(RAYD_LISTEN="127.0.0.1:0", RAYD_ADMIN_LISTEN="127.0.0.1:0", RAYD_DATA_DIR=str(data_dir),
               RAYD_CONFIG=str(CONFIG), RAYD_LOG="warn")
    process = subprocess.Popen([str(BIN / entrypoint[0]), *entrypoint[1:]], env=env, stdout=subprocess.PIPE, text=True)
    processes.append(process)
    first = process.stdout.readline()
    found = re.match(r"rayd listening on grpc=(\S+) admin=(\S+)", first)
    assert found, f"rayd's first line: {first!r}"
    return found.group(1), found.group(2)


def rayctl(server, *args, token=WRITE_KEY, check=True):
    result = subprocess.run([str(BIN / "rayctl"), "--server", f"http://{server}", "--token", token, "--json", *args],
                            capture_output=True, text=True, timeout=60)
    if check and result.returncode != 0:
        raise AssertionError(f"rayctl {' '.join(args)} via {server}: {result.stderr}")
    return result


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_envoy(nodes, work):
    """Envoy with deploy/envoy/envoy.yaml, its listener, admin and endpoints moved to loopback."""
    config = yaml.safe_load((ROOT / "deploy" / "envoy" / "envoy.yaml").read_text())
    config["admin"]["address"]["socket_address"].update(address="127.0.0.1", port_value=free_port())
    listen = free_port()
    config["static_resources"]["listeners"][0]["address"]["socket_address"].update(address="127.0.0.1",
                                                                                   port_value=listen)
    endpoints = config["static_resources"]["clusters"][0]["load_assignment"]["endpoints"][0]["lb_endpoints"]
    assert len(endpoints) == len(nodes), "one endpoint per node"
    for endpoint, node in zip(endpoints, nodes):
        host, port = node.rsplit(":", 1)
        endpoint["endpoint"]["address"]["socket_address"].update(address=host, port_value=int(port))
    path = work / "envoy.yaml"
    path.write_text(yaml.safe_dump(config))
    processes.append(subprocess.Popen(["envoy", "-c", str(path), "--use-dynamic-base-id", "--log-level", "error"]))
    server = f"127.0.0.1:{listen}"
    deadline = time.time() + 30
    while rayctl(server, "health", token="", check=False).returncode != 0:
        assert time.time() < deadline, "Envoy did not come up"
        time.sleep(0.2)
    return server


def accels(node):
    return sorted(a["name"] for a in json.loads(rayctl(node, "accels").stdout)["accels"])


def main():
    image_env, entrypoint, health = dockerfile()
    assert entrypoint == ["rayd"] and health[:2] == ["rayctl", "health"], (entrypoint, health)
    work = Path(tempfile.mkdtemp(prefix="rayd-deploy-check-"))
    processes.append(work)

    nodes, admins = [], []
    for i in range(3):
        grpc, admin = start_rayd(image_env, entrypoint, work / f"data-{i}")
        nodes.append(grpc)
        admins.append(admin)
    env = dict(os.environ, RAYD_SERVER=f"http://{nodes[0]}")
    # As Docker runs it: retried within the start period (rayd opens its devices before it serves; three nodes
    # starting at once on a loaded CI machine took longer than one try's 4 s).
    deadline = time.time() + 30
    while True:
        result = subprocess.run([str(BIN / health[0]), *health[1:]], env=env, capture_output=True, text=True, timeout=30)
        if result.returncode == 0 or time.time() > deadline:
            break
        time.sleep(1)
    assert result.returncode == 0 and result.stdout.strip() == "SERVING", result
    print(f"image entrypoint and environment: rayd started; HEALTHCHECK {' '.join(health)}: {result.stdout.strip()}")

    envoy = start_envoy(nodes, work)
    (work / "tet.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (work / "farm.json").write_text(json.dumps({
        "meshes": {"a": "tet.obj", "b": "tet.obj"},
        "instances": [{"mesh": "a"}, {"mesh": "b", "translate": [3, 0, 0]}],
    }))
    scenes = [f"farm{i}" for i in range(24)]
    for scene in scenes:
        # An instance accel can only place accels of its own node: this fails unless the whole scene is on one.
        rayctl(envoy, "scene", "--file", str(work / "farm.json"), "--name", scene)
        rayctl(envoy, "rays", "--accel", scene, "--width", "16", "--height", "16", "-o", str(work / "rays.bin"))
        traced = json.loads(rayctl(envoy, "trace", "--accel", scene, "--rays", str(work / "rays.bin"),
                                   "--ray-format", "origin_tmin_direction_tmax", "--hit-format", "t_triid").stdout)
        assert traced["rays"] == 256 and traced["hits"] > 0, traced
        rayctl(envoy, "info", f"{scene}.a")
    held = [accels(node) for node in nodes]
    owner = {}
    for i, names in enumerate(held):
        for name in names:
            assert name.split(".")[0] not in owner or owner[name.split(".")[0]] == i, f"{name} is split over nodes"
            owner[name.split(".")[0]] = i
    assert sorted(owner) == sorted(scenes) and sum(map(len, held)) == 3 * len(scenes), held
    used = sorted(set(owner.values()))
    assert used == [0, 1, 2], f"the {len(scenes)} scenes went to nodes {used} only"
    print(f"through Envoy: {len(scenes)} scenes built, framed and traced, each whole on one node "
          f"(scenes per node: {[sum(1 for n in owner.values() if n == i) for i in range(3)]})")

    stranger = next(i for i in range(3) if owner["farm0"] != i)
    result = rayctl(nodes[stranger], "info", "farm0", check=False)
    assert result.returncode == 1 and "NotFound" in result.stderr and '"farm0"' in result.stderr, result.stderr
    print(f"a node without the scene: {result.stderr.strip()}")

    dashboard = (ROOT / "deploy" / "grafana" / "rayd-dashboard.json").read_text()
    wanted = set(re.findall(r"\b(rayd_[a-z_]+)\{", dashboard))
    exported = "".join(urllib.request.urlopen(f"http://{admin}/metrics", timeout=10).read().decode() for admin in admins)
    missing = sorted(m for m in wanted if not re.search(rf"^{m}\{{", exported, re.M))
    assert not missing, f"the dashboard queries metrics no node exports: {missing}"
    print(f"the dashboard's {len(wanted)} metrics are exported: {', '.join(sorted(wanted))}")


if __name__ == "__main__":
    try:
        main()
    finally:
        started = [p for p in processes if isinstance(p, subprocess.Popen)]
        for process in started:
            process.terminate()
        for process in started:
            process.wait(timeout=30)
        for work in (p for p in processes if isinstance(p, Path)):
            shutil.rmtree(work, ignore_errors=True)
