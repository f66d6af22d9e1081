"""The Kubernetes manifests in docker/k8s: valid against Kubernetes' own schemas (offline, strict), and
consistent with the binary they run: every flag the Deployment passes is one `nak serve` takes, and the
probes ask the port that serves health checks."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from conftest import ROOT

MANIFESTS = sorted(p for p in (ROOT / "docker" / "k8s").glob("*.yaml") if p.name != "kustomization.yaml")


def load(name: str) -> dict[str, Any]:
    document: dict[str, Any] = yaml.safe_load((ROOT / "docker" / "k8s" / name).read_text())
    return document


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_manifests_are_valid_kubernetes(path: Path) -> None:
    for document in yaml.safe_load_all(path.read_text()):
        kubernetes_validate.validate(document, kubernetes_validate.latest_version(), strict=True)


def test_the_kustomization_lists_every_manifest() -> None:
    assert sorted(load("kustomization.yaml")["resources"]) == sorted(p.name for p in MANIFESTS)


def test_the_deployment_runs_flags_nak_serve_takes_and_probes_its_health_port(nak_binary: Path) -> None:
    container = load("deployment.yaml")["spec"]["template"]["spec"]["containers"][0]
    args: list[str] = container["args"]
    assert args[0] == "serve"
    help_text = subprocess.run([str(nak_binary), "serve", "--help"], capture_output=True, text=True, check=True).stdout
    for flag in (a.split("=")[0] for a in args[1:]):
        assert re.search(rf"^\s+{re.escape(flag)}\b", help_text, re.MULTILINE), f"nak serve has no {flag}"
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    listen = {a.split("=")[0]: int(a.rsplit(":", 1)[1]) for a in args if a.startswith("--") and "listen" in a}
    assert listen == {
        "--listen": ports["grpc"],
        "--metrics-listen": ports["metrics"],
        "--health-listen": ports["health"],
    }
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["grpc"]["port"] == ports["health"], probe
    service = load("service.yaml")["spec"]
    assert service["clusterIP"] == "None", "headless, so that clients balance per request"
