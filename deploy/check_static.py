"""deploy/check.sh's static checks of what YAML parsing alone cannot see: the compose file against the compose
schema, the files it mounts, and the Helm chart's rendered objects (kinds, probes, GPU request, rayd.toml).
Usage: check_static.py COMPOSE_SCHEMA RENDERED_DIR (writes RENDERED_DIR/envoy-from-chart.yaml and
envoy-from-chart-tls.yaml)."""

import json
import sys
import tomllib
from pathlib import Path

import jsonschema
import yaml

DEPLOY = Path(__file__).resolve().parent


def compose(schema_path):
    """The compose file is valid for the compose schema and every file it names exists."""
    path = DEPLOY / "compose" / "compose.yaml"
    spec = yaml.safe_load(path.read_text())
    jsonschema.validate(spec, json.loads(Path(schema_path).read_text()))
    assert (path.parent / spec["services"]["rayd"]["build"]["context"] / "Dockerfile").is_file()
    for service in spec["services"].values():
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith("."):
                assert (path.parent / source).exists(), f"compose mounts {source}, which does not exist"
            else:
                assert source in spec["volumes"], f"named volume {source} is not declared"
    secret = spec["secrets"]["rayd-config"]["file"].split(":-")[-1].rstrip("}")
    config = tomllib.loads((path.parent / secret).read_text())
    assert config["tenants"], "the example configuration has tenants (rayd refuses 0.0.0.0 without them)"
    json.loads((DEPLOY / "grafana" / "rayd-dashboard.json").read_text())


def objects(path):
    """The objects of one rendered file, by (kind, name)."""
    docs = [doc for doc in yaml.safe_load_all(path.read_text()) if doc]
    return {(doc["kind"], doc["metadata"]["name"]): doc for doc in docs}


def container(objs):
    return objs[("StatefulSet", "rayd")]["spec"]["template"]["spec"]["containers"][0]


def chart(rendered):
    """The chart's three renderings hold what values.yaml promises."""
    rendered = Path(rendered)
    defaults = objects(rendered / "defaults.yaml")
    assert {k for k, _ in defaults} == {"StatefulSet", "Service", "ConfigMap", "Secret", "PodDisruptionBudget"}
    rayd = container(defaults)
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert rayd[probe]["grpc"] == {"port": 50051, "service": "rayd.v1.Rayd"}, probe
    assert defaults[("Service", "rayd-headless")]["spec"]["clusterIP"] == "None"
    assert defaults[("StatefulSet", "rayd")]["spec"]["serviceName"] == "rayd-headless"
    assert defaults[("StatefulSet", "rayd")]["spec"]["volumeClaimTemplates"][0]["metadata"]["name"] == "data"

    full = objects(rendered / "full.yaml")
    toml = tomllib.loads(full[("Secret", "rayd")]["stringData"]["rayd.toml"])
    assert toml["tenants"][0]["name"] == "acme" and len(toml["tenants"][0]["keys"]) == 2
    assert toml["tenants"][0]["share"] == 3, toml
    assert toml["tenants"][0]["limits"] == {"max_accels": 100, "max_accel_bytes": 8589934592}
    env = full[("ConfigMap", "rayd")]["data"]
    assert env["RAYD_LIMITS_MAX_TOTAL_ACCEL_BYTES"] == "34359738368", env
    assert container(full)["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert ("ServiceMonitor", "rayd") in full and ("Deployment", "rayd-envoy") in full
    envoy = yaml.safe_load(full[("ConfigMap", "rayd-envoy")]["data"]["envoy.yaml"])
    endpoints = envoy["static_resources"]["clusters"][0]["load_assignment"]["endpoints"][0]["lb_endpoints"]
    names = [e["endpoint"]["address"]["socket_address"]["address"] for e in endpoints]
    assert names == [f"rayd-{i}.rayd-headless.default.svc.cluster.local" for i in range(3)], names
    (rendered / "envoy-from-chart.yaml").write_text(full[("ConfigMap", "rayd-envoy")]["data"]["envoy.yaml"])

    tls = objects(rendered / "tls.yaml")
    assert ("Secret", "rayd") not in tls and ("PodDisruptionBudget", "rayd") not in tls
    # The TLS files' paths reach rayd through the ConfigMap, whoever made the Secret with rayd.toml.
    env = tls[("ConfigMap", "rayd")]["data"]
    files = {key: env.get(f"RAYD_TLS_{key}") for key in ("CERT", "KEY", "CLIENT_CA")}
    tls_files = {"CERT": "tls.crt", "KEY": "tls.key", "CLIENT_CA": "ca.crt"}
    assert files == {key: f"/etc/rayd/tls/{name}" for key, name in tls_files.items()}, files
    # Under mutual TLS the probes present a client certificate.
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        command = container(tls)[probe]["exec"]["command"]
        assert command[:2] == ["rayctl", "health"] and "--client-cert" in command and "--client-key" in command, probe
    envoy = yaml.safe_load(tls[("ConfigMap", "rayd-envoy")]["data"]["envoy.yaml"])
    assert envoy["static_resources"]["clusters"][0]["transport_socket"]["name"] == "envoy.transport_sockets.tls"
    assert envoy["static_resources"]["listeners"][0]["filter_chains"][0]["transport_socket"]["typed_config"][
        "require_client_certificate"
    ]
    envoy_mounts = tls[("Deployment", "rayd-envoy")]["spec"]["template"]["spec"]["containers"][0]["volumeMounts"]
    assert {"name": "tls", "mountPath": "/etc/rayd/tls", "readOnly": True} in envoy_mounts
    (rendered / "envoy-from-chart-tls.yaml").write_text(tls[("ConfigMap", "rayd-envoy")]["data"]["envoy.yaml"])
    assert "volumeClaimTemplates" not in tls[("StatefulSet", "rayd")]["spec"]
    volumes = tls[("StatefulSet", "rayd")]["spec"]["template"]["spec"]["volumes"]
    assert {"name": "config", "secret": {"secretName": "rayd-config"}} in volumes


if __name__ == "__main__":
    compose(sys.argv[1])
    chart(sys.argv[2])
    print("compose schema, mounted files and rendered chart objects: ok")
