"""The Kubernetes manifests in docker/k8s: valid against Kubernetes' own schemas (offline, strict), and
consistent with the binary they run: every flag the Deployment passes is one `nak serve` takes, and the
probes ask the port that serves health checks; the dataset Jobs pass flags `nak datagen` takes, run
one shard per completion index of as many as the Job completes, and the join reads where they write."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from conftest import ROOT

K8S = ROOT / "docker" / "k8s"
MANIFESTS = sorted(p for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")
DATAGEN = sorted((K8S / "datagen").glob("*.yaml"))


def load(name: str) -> dict[str, Any]:
    document: dict[str, Any] = yaml.safe_load((K8S / name).read_text())
    return document


def help_flags(nak_binary: Path, command: str) -> str:
    return subprocess.run([str(nak_binary), command, "--help"], capture_output=True, text=True, check=True).stdout


def takes(help_text: str, flag: str) -> bool:
    return re.search(rf"^\s+{re.escape(flag)}\b", help_text, re.MULTILINE) is not None


def datagen_options(nak_binary: Path, container: dict[str, Any]) -> dict[str, str]:
    """A datagen container's `--flag=value` arguments, each checked to be one `nak datagen` takes."""
    args: list[str] = container["args"]
    assert args[0] == "datagen"
    help_text = help_flags(nak_binary, "datagen")
    options = dict(a.split("=", 1) for a in args[1:])
    for flag in options:
        assert takes(help_text, flag), f"nak datagen has no {flag}"
    return options


@pytest.mark.parametrize("path", MANIFESTS + DATAGEN, ids=lambda p: p.name)
def test_manifests_are_valid_kubernetes(path: Path) -> None:
    for document in yaml.safe_load_all(path.read_text()):
        kubernetes_validate.validate(document, kubernetes_validate.latest_version(), strict=True)


def test_the_kustomization_lists_every_manifest() -> None:
    assert sorted(load("kustomization.yaml")["resources"]) == sorted(p.name for p in MANIFESTS)


def test_the_deployment_runs_flags_nak_serve_takes_and_probes_its_health_port(nak_binary: Path) -> None:
    container = load("deployment.yaml")["spec"]["template"]["spec"]["containers"][0]
    args: list[str] = container["args"]
    assert args[0] == "serve"
    help_text = help_flags(nak_binary, "serve")
    for flag in (a.split("=")[0] for a in args[1:]):
        assert takes(help_text, flag), f"nak serve has no {flag}"
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


@pytest.mark.parametrize("name", ["datagen/nonlinear.yaml", "datagen/linear.yaml"])
def test_a_dataset_job_runs_one_shard_per_completion_index(nak_binary: Path, name: str) -> None:
    job = load(name)["spec"]
    assert job["completionMode"] == "Indexed"
    assert job["parallelism"] <= job["completions"]
    container = job["template"]["spec"]["containers"][0]
    shard_env = next(e for e in container["env"] if e["name"] == "SHARD")
    assert "job-completion-index" in shard_env["valueFrom"]["fieldRef"]["fieldPath"]
    options = datagen_options(nak_binary, container)
    assert options["--shard"] == f"$(SHARD)/{job['completions']}"
    # Each shard writes a directory of its own under <dataset>/shards, which the join reads.
    dataset = options["--out"].removeprefix("/data/").split("/")[0]
    assert options["--out"] == f"/data/{dataset}/shards/$(SHARD)"
    assert dataset == f"{options['--regime']}-{options['--preset']}"
    join = load("datagen/join.yaml")["spec"]["template"]["spec"]["containers"][0]
    assert '/data/"$DATASET"/shards/*' in join["args"][0]
    assert takes(help_flags(nak_binary, "dataset"), "join")
    volumes = {
        v["persistentVolumeClaim"]["claimName"]
        for f in (name, "datagen/join.yaml")
        for v in load(f)["spec"]["template"]["spec"]["volumes"]
    }
    assert volumes == {load("datagen/volume.yaml")["metadata"]["name"]}


def test_the_organ_job_makes_the_set_nak_organ_new_looks_for(nak_binary: Path) -> None:
    """organ-nonlinear.yaml shards the nonlinear set of an organ under DIR/data, and organ-join.yaml
    joins it where `nak organ new` looks (DIR/data/<SET>); both name the same organ and set."""
    job = load("datagen/organ-nonlinear.yaml")["spec"]
    container = job["template"]["spec"]["containers"][0]
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert re.fullmatch(r"nonlinear-seed0-\d+-[0-9a-f]{8}", env["SET"]), env["SET"]
    options = datagen_options(nak_binary, container)
    # The words stage 4 runs for the nonlinear training set (seed 0, the paper preset's default size).
    assert (options["--mesh"], options["--regime"], options["--seed"]) == ("/data/$(ORGAN)", "nonlinear", "0")
    assert "--preset" not in options and "--chunk-size" not in options, "the organ's set keeps datagen's defaults"
    assert options["--shard"] == f"$(SHARD)/{job['completions']}"
    assert options["--out"] == "/data/$(ORGAN)/data/$(SET).shards/$(SHARD)"
    join = load("datagen/organ-join.yaml")["spec"]["template"]["spec"]["containers"][0]
    assert {e["name"]: e.get("value") for e in join["env"]} == {"ORGAN": env["ORGAN"], "SET": env["SET"]}
    assert '--out "/data/$ORGAN/data/$SET" /data/"$ORGAN"/data/"$SET".shards/*' in join["args"][0]
